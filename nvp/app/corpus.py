"""Training material for the Audio2ExpressionNet: tracked expressions and speech-feature windows per video.

Tracking and feature extraction are cached under a cache directory, so re-running a training or an
evaluation only processes new videos.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from nvp.artifact import file_sha256, load_artifact, save_artifact
from nvp.errors import FormatError, NvpError
from nvp.face_model import default_face_model
from nvp.gaze import SPREAD_KEY
from nvp.person import VideoSample
from nvp.tracked import TrackedSequence

log = logging.getLogger(__name__)


def cache_key(video: Path) -> str:
    """``<stem>-<first 16 hex digits of the file's sha256>``: two files with the same name never share a
    cache entry, and an edited file gets a new one."""
    return f"{video.stem}-{file_sha256(video)[:16]}"


def tracked_cached(video: Path, cache: Path, progress: bool = True) -> TrackedSequence:
    """The video's tracking, computed once and kept in ``cache/tracks/<key>`` (see :func:`cache_key`); a
    damaged or outdated entry (another face model, other tracker settings) is recomputed."""
    from dataclasses import asdict

    from tracking.fit import TrackingConfig
    from tracking.track import track_video

    out = cache / "tracks" / cache_key(video)
    try:
        seq = TrackedSequence.load(out)
        settings = json.loads(json.dumps(asdict(TrackingConfig())))  # as stored (tuples become lists)
        same = seq.face_model_sha256 == default_face_model().sha256 and seq.info.get("fit_config") == settings
        if same and seq.iris is not None and SPREAD_KEY in seq.info:  # else made before nvp measured gaze
            return seq
    except FormatError:
        pass
    seq, _ = track_video(video, progress=progress)
    seq.save(out)
    return seq


def features_cached(
    video: Path, cache: Path, kind: str, fps: float, num_frames: int, augment: str | None = None
) -> np.ndarray:
    """Feature windows ``(T, W, D)`` of the video's audio track — or of its copy under ``augment`` (a name
    :func:`nvp.augment.parse_augmentation` reads, seeded by the file's content; a faster or slower copy is
    read at that many times the frame rate, so frame ``t`` keeps its own sound) — kept in
    ``cache/features`` (an artifact: written atomically; a damaged entry is recomputed). ``"phonemes"``
    and ``"phonetic"`` of the clean audio come from one recogniser pass, so computing either caches both."""
    from nvp.audio_features import SAMPLE_RATE, extract_features, recogniser_features, speaker_normalized
    from nvp.augment import parse_augmentation
    from nvp.media import read_audio
    from nvp.windows import frame_windows

    key = cache_key(video)
    copy = parse_augmentation(augment) if augment else None
    suffix = f"_{copy.name}" if copy else ""

    def path(k: str) -> Path:
        return cache / "features" / f"{key}_{k}_{fps:.3f}_{num_frames}_sn{suffix}.json"

    try:
        return load_artifact(path(kind), "feature_windows", 1).arrays["windows"]
    except (FormatError, KeyError):
        pass
    audio = read_audio(video, SAMPLE_RATE)
    if copy is not None:
        audio = copy.apply(audio, SAMPLE_RATE, int(key[-16:], 16) % 2**32)
    if kind in ("phonemes", "phonetic") and copy is None:  # copies are only trained on
        made = {f.kind: f for f in recogniser_features(audio, SAMPLE_RATE)}
    else:
        made = {kind: extract_features(audio, SAMPLE_RATE, kind=kind)}
    rate = fps * (copy.time_scale if copy else 1.0)
    for k, feats in made.items():
        windows = frame_windows(speaker_normalized(feats), rate, num_frames=num_frames).astype(np.float32)
        fields = {"video": video.name, "kind": k, "augment": copy.name if copy else None}
        save_artifact(path(k), "feature_windows", 1, {"windows": windows}, fields)
        made[k] = windows
    return made[kind]


def load_sample(
    video: Path,
    cache: Path,
    kind: str = "phonemes",
    progress: bool = True,
    augments: tuple[str, ...] = (),
) -> VideoSample:
    """The video's tracking and feature windows (cached), plus windows of each of ``augments``' copies of
    its audio as ``VideoSample.augmented`` (training augmentation, :mod:`nvp.augment`)."""
    seq = tracked_cached(video, cache, progress)
    windows = features_cached(video, cache, kind, seq.fps, seq.num_frames)
    copies = tuple(features_cached(video, cache, kind, seq.fps, seq.num_frames, a) for a in augments)
    return VideoSample(name=video.name, windows=windows, tracked=seq, augmented=copies)


VIDEO_SUFFIXES = (".mp4", ".mov", ".mkv", ".avi", ".webm", ".m4v")


def corpus_split(
    folder: Path,
    val: list[str] | None,
    exclude: list[str] | None,
    cache: Path,
    kind: str,
    progress: bool = True,
    augments: tuple[str, ...] = (),
) -> tuple[list[VideoSample], list[VideoSample], dict]:
    """The videos of ``folder`` as training and validation samples (tracked and featurised, cached), and
    the split as a dict for the model's manifest. ``val``: file names of validation videos (default: five
    spread over the sorted list); ``exclude``: file names left out; a video that cannot be used (no face,
    no audio) is skipped with a warning. Training videos also get windows of their audio's copies under
    ``augments`` (:func:`load_sample`)."""
    videos = sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in VIDEO_SUFFIXES)
    if not videos:
        raise NvpError(f"no videos ({', '.join(VIDEO_SUFFIXES)}) in {folder}")
    val_names = set(val or [])
    unknown = val_names - {v.name for v in videos}
    if unknown:
        raise NvpError(f"validation videos not in the corpus: {', '.join(sorted(unknown))}")
    if not val_names:
        val_names = {v.name for v in videos[:: max(len(videos) // 5, 1)][:5]}
    excluded = set(exclude or [])
    samples = []
    for v in videos:
        if v.name in excluded:
            continue
        try:
            copies = () if v.name in val_names else tuple(augments)
            samples.append(load_sample(v, cache, kind, progress=progress, augments=copies))
        except NvpError as e:
            log.warning("skipping %s: %s", v.name, e)
    train_set = [s for s in samples if s.name not in val_names]
    val_set = [s for s in samples if s.name in val_names]
    split = {
        "train": [s.name for s in train_set],
        "validation": [s.name for s in val_set],
        "excluded": sorted(excluded),
    }
    return train_set, val_set, split
