"""Aligning speech features to video frames: how many frames cover the audio, and the per-frame feature
windows the Audio2ExpressionNet reads (rates travel with the features; no constants per kind)."""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np

from nvp.audio_features import AudioFeatures
from nvp.errors import NvpError

DEFAULT_WINDOW_RATE = 50.0
"""Default spacing of the samples inside a per-frame window, in samples per second: 16 samples at 50 Hz
span 320 ms (as with the DeepSpeech features of Neural Voice Puppetry) whatever the feature rate."""


def num_video_frames(duration_s: float, fps: float) -> int:
    """Number of video frames at ``fps`` needed to cover ``duration_s`` seconds: ``ceil(duration * fps)``.

    A product within 1e-6 of an integer counts as that integer (20 s at 25 fps is 500 frames, not 501).
    """
    x = duration_s * fps
    return max(0, int(math.ceil(x - 1e-6)))


def tent_smooth(values: np.ndarray, factor: float) -> np.ndarray:
    """Low-pass ``(N, ...)`` along N with a triangular kernel of half-width ``factor`` frames (normalised;
    ``factor <= 1``: unchanged).

    This is the anti-aliasing filter for reading features of rate ``r`` at spacing ``factor / r``: for
    ``factor == 2`` the kernel is ``[1/4, 1/2, 1/4]``. Edges are extended with the edge values.
    """
    from scipy.ndimage import convolve1d

    half = int(math.ceil(factor)) - 1
    j = np.arange(-half, half + 1, dtype=np.float64)
    kernel = np.maximum(0.0, 1.0 - np.abs(j) / factor)
    kernel /= kernel.sum()
    return convolve1d(values, kernel.astype(np.float32), axis=0, mode="nearest")


def frame_windows(
    features: AudioFeatures,
    fps: float,
    num_frames: int | None = None,
    window: int = 16,
    window_rate: float = DEFAULT_WINDOW_RATE,
    block: int = 2048,
    first: int = 0,
) -> np.ndarray:
    """Per-video-frame windows of features, ``(T - first, window, D)`` float32 (see
    :func:`iter_frame_windows`, which yields them ``block`` frames at a time)."""
    blocks = list(iter_frame_windows(features, fps, num_frames, window, window_rate, block, first))
    if not blocks:
        return np.empty((0, window, features.dim), dtype=np.float32)
    return blocks[0] if len(blocks) == 1 else np.concatenate(blocks)


def iter_frame_windows(
    features: AudioFeatures,
    fps: float,
    num_frames: int | None = None,
    window: int = 16,
    window_rate: float = DEFAULT_WINDOW_RATE,
    block: int = 2048,
    first: int = 0,
) -> Iterator[np.ndarray]:
    """Per-video-frame windows of features, ``(≤ block, window, D)`` float32 arrays for frames ``first,
    first + 1, … T - 1`` in order, so the windows of a long file need not all be in memory at once.

    Video frame ``i`` is at time ``t_i = i / fps`` seconds. Its window holds the features at times
    ``t_i + (k - window // 2) / window_rate`` for ``k = 0 .. window - 1``, so position ``window // 2`` is
    ``t_i`` itself and the window spans ``window / window_rate`` seconds (320 ms for 16 at 50 Hz).
    Feature values at a time ``t`` are read from the feature time line (frame ``n`` at ``n / rate``) by
    linear interpolation between the two nearest frames, and times before the first or after the last
    frame take the edge frame's value (edge padding). When ``window_rate`` is below the feature rate
    (e.g. 100 Hz mel read at 50 Hz) the features are first smoothed with a triangular kernel of half-width
    ``rate / window_rate`` frames so that the coarser sampling does not alias (for mel at 100 Hz and the
    default 50 Hz: weights 1/4, 1/2, 1/4). At 25 fps and 50 Hz phoneme features every window sample falls
    exactly on a feature frame (no interpolation); at 29.97 or 30 fps samples in between are blended.

    Args:
        features: the audio features (any kind and rate).
        fps: video frame rate in frames per second, e.g. 25, 30 or 29.97 (30000/1001).
        num_frames: T; default :func:`num_video_frames` of the audio duration, ``ceil(duration * fps)``.
        window: samples per window (W).
        window_rate: samples per second inside a window.
        block: video frames per yielded array (bounds temporary memory to a few times a block).
        first: the first video frame to make a window for (windows of a long file can be made in blocks).

    Yields:
        ``(B, W, D)`` float32 windows of consecutive frames, ``first .. T - 1`` in all.
    """
    if not (math.isfinite(fps) and fps > 0):
        raise NvpError(f"expected a positive video frame rate, found {fps!r}")
    if not (math.isfinite(window_rate) and window_rate > 0):
        raise NvpError(f"expected a positive window sample rate in Hz, found {window_rate!r}")
    if window < 1:
        raise NvpError(f"expected a window of at least 1 feature frame, found {window}")
    if features.num_frames == 0:
        raise NvpError("expected at least one feature frame, found none")
    t_count = num_video_frames(features.duration_s, fps) if num_frames is None else int(num_frames)
    if t_count < 0:
        raise NvpError(f"expected a non-negative number of video frames, found {num_frames}")
    if not 0 <= first <= t_count:
        raise NvpError(f"expected a first frame between 0 and {t_count}, found {first}")

    src = features.values
    factor = features.rate / window_rate
    if factor > 1.0 + 1e-9:
        src = tent_smooth(src, factor)
    n = features.num_frames
    offsets = (np.arange(window, dtype=np.float64) - window // 2) / window_rate
    for b0 in range(first, t_count, block):
        b1 = min(t_count, b0 + block)
        times = np.arange(b0, b1, dtype=np.float64) / fps
        pos = (times[:, None] + offsets[None, :]) * features.rate
        near = np.round(pos)
        pos = np.where(np.abs(pos - near) < 1e-6, near, pos)  # exact grid hits stay exact
        pos = np.clip(pos, 0.0, n - 1)
        i0 = np.floor(pos).astype(np.int64)
        i1 = np.minimum(i0 + 1, n - 1)
        w = (pos - i0).astype(np.float32)[..., None]
        yield (src[i0] * (1.0 - w) + src[i1] * w).astype(np.float32, copy=False)
