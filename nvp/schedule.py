"""Which target frame each output frame shows when the new audio is longer (or shorter) than the footage."""

from __future__ import annotations

import numpy as np


def target_frame_indices(num_output: int, num_target: int, start: int = 0) -> np.ndarray:
    """``(num_output,)`` target frame index per output frame: the footage plays forward from ``start``,
    then backward, then forward again (0, 1, …, n-1, n-2, …, 1, 0, 1, …), so consecutive output frames
    always show neighbouring target frames and the head never jumps. A one-frame target repeats."""
    return ping_pong(np.arange(num_output, dtype=np.int64) + start, num_target)


def ping_pong(positions: np.ndarray, num_target: int) -> np.ndarray:
    """Target frame index at each of the footage's ``positions`` (frames played since the start, int) when
    it plays forward, backward and forward again (see :func:`target_frame_indices`)."""
    if num_target < 1:
        raise ValueError(f"expected a target of at least one frame, found {num_target}")
    k = np.asarray(positions, np.int64)
    if num_target == 1:
        return np.zeros(k.shape, np.int64)
    period = 2 * (num_target - 1)
    k = k % period
    return np.where(k < num_target, k, period - k)


def stream_positions(first: int, count: int, step: float) -> np.ndarray:
    """``(count,)`` the footage frame (counted from the start) that output frames ``first`` … of a stream
    ``step`` footage frames apart (its rate is the footage's over ``step`` ≥ 1) show: the nearest, so the
    head moves at its real speed."""
    return np.floor(np.arange(first, first + count) * step + 0.5).astype(np.int64)
