"""Training material for the Audio2ExpressionNet: tracked expressions and speech-feature windows per video.

Tracking and feature extraction are cached under a cache directory, so re-running a training or an
evaluation only processes new videos.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from nvp.errors import FormatError
from nvp.face_model import default_face_model
from nvp.person import VideoSample
from nvp.tracked import TrackedSequence

log = logging.getLogger(__name__)


def tracked_cached(video: Path, cache: Path, progress: bool = True) -> TrackedSequence:
    """The video's tracking, computed once and kept in ``cache/tracks/<stem>``."""
    from tracking.track import track_video

    out = cache / "tracks" / video.stem
    sha = default_face_model().sha256
    if (out / "tracked.json").exists():
        try:
            seq = TrackedSequence.load(out)
            if seq.face_model_sha256 == sha:
                return seq
        except FormatError:
            pass
    seq, _ = track_video(video, progress=progress)
    seq.save(out)
    return seq


def features_cached(video: Path, cache: Path, kind: str, fps: float, num_frames: int) -> np.ndarray:
    """Feature windows ``(T, W, D)`` of the video's audio track, kept in ``cache/features``."""
    from nvp.audio_features import features_from_file, speaker_normalized
    from nvp.windows import frame_windows

    path = cache / "features" / f"{video.stem}_{kind}_{fps:.3f}_{num_frames}_sn.npy"
    if path.exists():
        return np.load(path)
    feats = speaker_normalized(features_from_file(video, kind=kind))
    windows = frame_windows(feats, fps, num_frames=num_frames).astype(np.float32)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path, windows)
    return windows


def load_sample(video: Path, cache: Path, kind: str = "phonemes", progress: bool = True) -> VideoSample:
    seq = tracked_cached(video, cache, progress)
    windows = features_cached(video, cache, kind, seq.fps, seq.num_frames)
    return VideoSample(name=video.name, windows=windows, tracked=seq)
