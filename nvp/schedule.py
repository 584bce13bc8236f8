"""Which target frame each output frame shows when the new audio is longer (or shorter) than the footage."""

from __future__ import annotations

import numpy as np


def target_frame_indices(num_output: int, num_target: int, start: int = 0) -> np.ndarray:
    """``(num_output,)`` target frame index per output frame: the footage plays forward from ``start``,
    then backward, then forward again (0, 1, …, n-1, n-2, …, 1, 0, 1, …), so consecutive output frames
    always show neighbouring target frames and the head never jumps. A one-frame target repeats."""
    if num_target < 1:
        raise ValueError(f"expected a target of at least one frame, found {num_target}")
    if num_target == 1:
        return np.zeros(num_output, np.int64)
    period = 2 * (num_target - 1)
    k = (np.arange(num_output, dtype=np.int64) + start) % period
    return np.where(k < num_target, k, period - k)
