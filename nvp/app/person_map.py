"""``nvp person-map``: a person's talking style learned (closed form) from their video alone."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from nvp.app.corpus import load_sample
from nvp.audio2exp import default_audio2exp
from nvp.face_model import default_face_model
from nvp.opening import FEATURE_KIND, default_opening_model
from nvp.person import style_from_sample, voiced_frames


def person_map(
    video: Path, output: Path, features: str = "phonemes", cache: Path | None = None, progress: bool = True
) -> tuple[int, Path]:
    """Learn the talking style of the person in ``video`` for the shipped network of ``features`` and save
    it at ``output`` (``.npz`` + ``.json``); ``cache``: tracking and features (default: ``.nvp-cache``
    beside the output). Returns the frames it learned from and the ``.json`` written."""
    net, manifest = default_audio2exp(features)
    cache = Path(cache) if cache else Path(output).parent / ".nvp-cache"
    sample = load_sample(Path(video), cache, features, progress=progress)
    opening_windows = load_sample(Path(video), cache, FEATURE_KIND, progress=False).windows
    sample = replace(sample, opening_windows=opening_windows)
    voiced = voiced_frames(Path(video), sample.tracked.fps, sample.tracked.num_frames)
    opening = default_opening_model()
    style = style_from_sample(net, manifest, sample, default_face_model(), voiced=voiced, opening=opening)
    return int(sample.valid.sum()), style.save(Path(output))
