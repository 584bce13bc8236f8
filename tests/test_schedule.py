"""Ping-pong reuse of target frames."""

from __future__ import annotations

import numpy as np
import pytest

from nvp.schedule import target_frame_indices


@pytest.mark.parametrize(("n_out", "n_target"), [(10, 25), (25, 25), (100, 25), (7, 2), (5, 1)])
def test_ping_pong_never_jumps(n_out, n_target):
    idx = target_frame_indices(n_out, n_target)
    assert idx.shape == (n_out,) and idx[0] == 0
    assert idx.min() >= 0 and idx.max() < n_target
    assert np.abs(np.diff(idx)).max(initial=0) <= 1
    if n_target > 1:
        assert (np.diff(idx) != 0).all()  # the turning frame is not shown twice in a row


def test_forward_then_backward():
    np.testing.assert_array_equal(target_frame_indices(9, 4), [0, 1, 2, 3, 2, 1, 0, 1, 2])
    np.testing.assert_array_equal(target_frame_indices(3, 4, start=2), [2, 3, 2])


def test_empty_target_is_an_error():
    with pytest.raises(ValueError, match="at least one frame"):
        target_frame_indices(3, 0)
