"""``nvp train-opening``: the generic mouth-opening model (:mod:`nvp.opening`) from a corpus of talking
videos, in closed form, its ridge chosen on the validation videos."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nvp.errors import NvpError
from nvp.face_model import FaceModel
from nvp.opening import FEATURE_KIND, OpeningModel, normal_equations, standardized_opening
from nvp.person import VideoSample

RIDGES = (1e3, 3e3, 1e4, 3e4, 1e5)
"""Ridge strengths tried (frames; inputs standardised). For the shipped model (the 32 train people of
``scripts/data_split.json`` plus ``video_wide``, 34,864 frames) the validation people's mean correlation
was 0.638 / 0.638 / 0.636 / 0.629 / 0.615."""


def opening_targets(sample: VideoSample, model: FaceModel) -> np.ndarray:
    """``(T,)`` the video's standardised tracked inner-lip gap, NaN on frames without a face."""
    gap = model.inner_lip_gap(sample.tracked.identity, sample.expression)
    return np.where(sample.valid, standardized_opening(gap, sample.valid), np.nan).astype(np.float32)


def correlations(opening: OpeningModel, samples: list[VideoSample], model: FaceModel) -> dict[str, float]:
    """Per video: correlation of the predicted opening with the tracked inner-lip gap (valid frames)."""
    out = {}
    for s in samples:
        ok = s.valid
        gap = model.inner_lip_gap(s.tracked.identity, s.expression)[ok]
        pred = opening.predict(s.windows, s.tracked.fps)[ok]
        varies = ok.sum() > 2 and gap.std() > 1e-9 and pred.std() > 1e-9
        out[s.name] = float(np.corrcoef(pred, gap)[0, 1]) if varies else 0.0
    return out


def train_opening(
    train_set: list[VideoSample],
    val_set: list[VideoSample],
    model: FaceModel,
    out: Path,
    ridges: tuple[float, ...] = RIDGES,
    provenance: dict | None = None,
    kind: str = FEATURE_KIND,
) -> tuple[OpeningModel, dict]:
    """Fit one model per ridge on ``train_set`` (windows of ``kind`` features, by default
    :data:`nvp.opening.FEATURE_KIND`; each sample's augmented copies count as more frames with the same
    targets), keep the one whose mean validation correlation is highest (the largest
    ridge on ties; the largest ridge without validation videos), write ``out`` (.npz + .json) and return it
    with its summary."""
    if not train_set:
        raise NvpError("no training videos")
    widths = {s.windows.shape[2] for s in train_set + val_set}
    if len(widths) != 1:
        raise NvpError(f"training and validation windows differ in feature width: {sorted(widths)}")
    targets = [opening_targets(s, model) for s in train_set]
    sums = normal_equations(
        (w for s in train_set for w in (s.windows, *s.augmented)),
        (y for s, y in zip(train_set, targets, strict=True) for _ in range(1 + len(s.augmented))),
    )
    fits = {}
    for ridge in ridges:
        m = sums.solve(ridge)
        per_video = correlations(m, val_set, model)
        fits[ridge] = (m, per_video, float(np.mean(list(per_video.values()))) if per_video else 0.0)
    ridge = max(fits, key=lambda r: (fits[r][2], r))
    m, per_video, score = fits[ridge]
    summary = {
        "feature_kind": kind,
        "ridge": ridge,
        "validation_corr": score,
        "validation_corr_by_ridge": {f"{r:g}": v[2] for r, v in fits.items()},
        "validation_per_video": per_video,
        "train_frames": int(sum(s.valid.sum() for s in train_set)),
        **(provenance or {}),
    }
    manifest = OpeningModel(m.weight, m.bias, m.window_step, info=summary, feature_kind=kind).save(out)
    return OpeningModel.load(manifest), summary


def train_opening_on_corpus(
    corpus: Path,
    output: Path,
    val: list[str] | None = None,
    exclude: list[str] | None = None,
    cache: Path | None = None,
    kind: str | None = None,
    progress: bool = True,
    augments: tuple[str, ...] = (),
) -> tuple[dict, int]:
    """``nvp train-opening``: the opening model of feature ``kind`` (default: the shipped model's) fitted on
    the videos of the folder ``corpus`` (``val`` / ``exclude`` as :func:`nvp.app.corpus.corpus_split`
    takes them; tracking and features cached in ``cache``, default ``cache`` beside ``output``), also on
    the training videos' copies under ``augments`` (:mod:`nvp.augment`), and saved at ``output``. Returns
    :func:`train_opening`'s summary and the number of validation videos."""
    from nvp.app.corpus import corpus_split
    from nvp.face_model import default_face_model

    kind = kind or FEATURE_KIND
    cache = Path(cache) if cache else Path(output).parent / "cache"
    train_set, val_set, split = corpus_split(Path(corpus), val, exclude, cache, kind, progress, augments)
    _, summary = train_opening(
        train_set,
        val_set,
        default_face_model(),
        Path(output),
        provenance={"split": split, "corpus": str(corpus), "augments": list(augments)},
        kind=kind,
    )
    return summary, len(val_set)
