"""Which speech features for the opening model, per language: the shipped recipe on each candidate kind.

    python -m scripts.eval.compare_opening_features CORPUS --cache /tmp/nvp-cache \
        --kinds whisper whisper_base_l1 whisper_base_l2 [whisper_base_l2+phonetic ...] [--out DIR]

``CORPUS`` is a folder of the clips (or links to them) that ``nvp train-opening`` trains on: the train and
validation clips of ``scripts/data_split.json`` plus ``video_wide/``. For each kind, the opening model is made
exactly as ``nvp train-opening CORPUS --val <validation clips> --features KIND`` makes it
(:func:`nvp.app.train_opening.train_opening`: ridge regression, the ridge chosen on the validation people) and
written to ``DIR/opening_<kind>.json``. Reported per kind:

- the validation people's opening correlation (whole clips, the model alone: predicted vs tracked inner-lip
  gap), per clip, per language and on average — what the choice is made on;
- a second look at other languages from the *training* people (the test split is never read): each
  non-English training person (:data:`LEAVE_OUT`) is left out in turn, the model refitted without their clips
  at the ridge validation chose, and their clips predicted. These people are few and short (German 20 s, a
  Spanish spokesperson with a 50-90 px face, two 3-4 s clips of unknown or likely-Chinese speech), so this is
  a rough signal, marked as such wherever it is quoted.

A kind ``A+B`` joins the windows of two kinds channel by channel (measurement only; such a model cannot be
used by ``nvp dub``). ``KIND@COPY,COPY`` also trains on those copies of the training clips' audio
(``nvp train-opening --augment``, :mod:`nvp.augment`), e.g. ``whisper@speed0.9,speed1.1,room0.5``; validation
clips are never copied. Tracking and features come from ``--cache`` (``nvp.app.corpus``).

``--test-models M1.json M2.json`` (after the choice; nothing is trained or chosen): each opening model's
whole-clip correlation (the model alone, as on validation) on every test clip of ``scripts/data_split.json``,
per language — more frames per language than ``scripts/eval/lipsync.py``'s last 20 % of each clip.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from nvp.app.corpus import corpus_split
from nvp.app.report import markdown_table
from nvp.app.train_opening import RIDGES, correlations, opening_targets, train_opening
from nvp.face_model import default_face_model
from nvp.opening import NormalEquations, normal_equations
from scripts.common import SPLIT, VIDEOS

LEAVE_OUT = {
    "German (mimictalk)": ("de", ["mimictalk__German_20s.mp4"], ["mimictalk__German_20s.mp4"]),
    "Spanish / English spokesperson Maria (video_wide)": (
        "es",
        ["wth2025__Maria-Spanish.mp4", "websitetalkingheads__Maria.mp4"],
        ["wth2025__Maria-Spanish.mp4", "websitetalkingheads__Maria.mp4"],
    ),
    "likely Chinese (megactor CHTF_4)": (
        "zh?",
        ["megactor__audio_CHTF_4.mp4"],
        ["megactor__audio_CHTF_4.mp4"],
    ),
    "unknown language (megactor CHTF_3)": (
        "?",
        ["megactor__audio_CHTF_3.mp4"],
        ["megactor__audio_CHTF_3.mp4"],
    ),
}
"""Non-English training people: (language, clips left out of the fit, clips predicted). Maria speaks English
in ``websitetalkingheads__Maria.mp4`` and Spanish in the other: both are left out, both predicted."""
CLIP_LANGUAGE = {"wth2025__Maria-Spanish.mp4": "es"}
"""Languages of corpus clips outside ``scripts/data_split.json`` that are not English (video_wide)."""


def load(corpus: Path, val: list[str], cache: Path, kind: str, augments: tuple[str, ...] = ()):
    """Training and validation samples of a kind, or of ``A+B`` (windows joined channel by channel)."""
    parts = [corpus_split(corpus, val, None, cache, k, False, augments) for k in kind.split("+")]
    if len(parts) == 1:
        return parts[0]
    (train, valid, split), *rest = parts

    def join(samples, others):
        by_name = [{s.name: s for s in o} for o in others]
        return [
            replace(s, windows=np.concatenate([s.windows, *(b[s.name].windows for b in by_name)], axis=2))
            for s in samples
        ]

    return join(train, [r[0] for r in rest]), join(valid, [r[1] for r in rest]), split


def sums_of(samples, targets: dict[str, np.ndarray]) -> NormalEquations:
    """The normal equations of ``samples`` and their augmented copies (as ``train_opening`` makes them)."""
    return normal_equations(
        (w for s in samples for w in (s.windows, *s.augmented)),
        (targets[s.name] for s in samples for _ in range(1 + len(s.augmented))),
    )


def minus(a: NormalEquations, b: NormalEquations) -> NormalEquations:
    """The sums of ``a`` without the frames of ``b``."""
    return replace(a, xtx=a.xtx - b.xtx, xty=a.xty - b.xty, xs=a.xs - b.xs, ys=a.ys - b.ys, n=a.n - b.n)


def report_test(models: list[Path], split: dict, lang: dict, cache: Path, out: Path) -> int:
    """Each model's whole-clip opening correlation on the test clips, per language (reported only)."""
    from nvp.app.corpus import load_sample
    from nvp.opening import OpeningModel

    shared = VIDEOS
    face = default_face_model()
    per_clip: dict[str, dict[str, float]] = {}
    for path in models:
        model = OpeningModel.load(path)
        if set(split["test"]) & (set(model.info["split"]["train"]) | set(model.info["split"]["validation"])):
            raise SystemExit(f"{path} was made with test clips")
        samples = [load_sample(shared / c, cache, model.feature_kind, progress=False) for c in split["test"]]
        per_clip[path.name] = correlations(model, samples, face)
    rows = []
    for language in sorted({lang[c] for c in split["test"]}):
        clips = [c for c in split["test"] if lang[c] == language]
        rows.append(
            {"language": language, "clips": len(clips)}
            | {m: f"{np.mean([per_clip[m][c] for c in clips]):.3f}" for m in per_clip}
        )
    rows.append(
        {"language": "all", "clips": len(split["test"])}
        | {m: f"{np.mean(list(v.values())):.3f}" for m, v in per_clip.items()}
    )
    out.mkdir(parents=True, exist_ok=True)
    (out / "test_whole_clips.json").write_text(json.dumps(per_clip, indent=1) + "\n")
    text = (
        "## Opening correlation on the test clips (whole clips, the model alone; reported, not chosen on)\n\n"
    )
    text += markdown_table(rows, list(rows[0]))
    (out / "test_whole_clips.md").write_text(text)
    print(text)
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("corpus", type=Path, help="folder of the training + validation clips (links are fine)")
    ap.add_argument("--kinds", nargs="+", default=[], help="feature kinds, or A+B for two joined")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/nvp-cache"))
    ap.add_argument("--split", type=Path, default=SPLIT)
    ap.add_argument("--out", type=Path, default=Path("out/opening_features"))
    ap.add_argument(
        "--ridges",
        type=float,
        nargs="+",
        default=RIDGES,
        help="ridge strengths tried (default: the recipe's)",
    )
    ap.add_argument("--test-models", nargs="+", type=Path, help="report these models on the test clips only")
    args = ap.parse_args(argv)
    split = json.loads(args.split.read_text())
    lang = {c: v["language"] for v in split["people"].values() for c in v["clips"]} | CLIP_LANGUAGE
    if args.test_models:
        return report_test(args.test_models, split, lang, args.cache, args.out)
    if not args.kinds:
        ap.error("expected --kinds (or --test-models)")
    if set(split["test"]) & {p.name for p in args.corpus.iterdir()}:
        raise SystemExit("the corpus holds test clips: they must never be used for choosing")
    face = default_face_model()
    args.out.mkdir(parents=True, exist_ok=True)
    results = {}
    for kind in args.kinds:
        t0 = time.perf_counter()
        features, _, copies = kind.partition("@")
        augments = tuple(c for c in copies.split(",") if c)
        if augments and "+" in features:
            ap.error(f"{kind}: copies of joined kinds are not supported")
        train, valid, used = load(args.corpus, split["validation"], args.cache, features, augments)
        path = args.out / f"opening_{kind.replace('+', '_and_').replace('@', '_with_').replace(',', '_')}"
        model, summary = train_opening(
            train,
            valid,
            face,
            path,
            tuple(args.ridges),
            provenance={"split": used, "augments": list(augments)},
            kind=features,
        )
        per_lang: dict[str, list[float]] = {}
        for name, c in summary["validation_per_video"].items():
            per_lang.setdefault(lang.get(name, "en"), []).append(c)
        # each non-English training person left out in turn, refitted at the ridge validation chose
        targets = {s.name: opening_targets(s, face) for s in train}
        sums = sums_of(train, targets)
        left_out = {}
        for who, (_, out_clips, predicted) in LEAVE_OUT.items():
            theirs = [s for s in train if s.name in out_clips]
            if not theirs:
                continue
            without = minus(sums, sums_of(theirs, targets))
            m = without.solve(summary["ridge"])
            left_out[who] = correlations(m, [s for s in theirs if s.name in predicted], face)
        results[kind] = {
            "model": str(path.with_suffix(".json")),
            "ridge": summary["ridge"],
            "validation_corr": summary["validation_corr"],
            "validation_corr_by_ridge": summary["validation_corr_by_ridge"],
            "validation_per_language": {k: float(np.mean(v)) for k, v in per_lang.items()},
            "validation_per_video": summary["validation_per_video"],
            "left_out_training_people": left_out,
            "dim": int(model.weight.shape[1]),
            "seconds": time.perf_counter() - t0,
        }
        print(
            f"{kind}: validation {summary['validation_corr']:.3f} (ridge {summary['ridge']:g}); left out: "
            + ", ".join(f"{c} {v:.3f}" for d in left_out.values() for c, v in d.items()),
            flush=True,
        )
        del train, valid, sums
    (args.out / "results.json").write_text(json.dumps(results, indent=1) + "\n")
    rows = []
    for kind, r in results.items():
        loo = {c: v for d in r["left_out_training_people"].values() for c, v in d.items()}
        rows.append(
            {
                "features": kind,
                "D": r["dim"],
                "ridge": f"{r['ridge']:g}",
                "validation corr (mean of 12)": f"{r['validation_corr']:.3f}",
                **{f"val {k}": f"{v:.3f}" for k, v in sorted(r["validation_per_language"].items())},
                **{f"left out: {c.split('__')[1].removesuffix('.mp4')}": f"{v:.3f}" for c, v in loo.items()},
            }
        )
    text = (
        "## Opening model per feature kind (validation people; left-out training people)\n\n"
        + markdown_table(rows, list(rows[0]))
    )
    (args.out / "results.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
