"""Ping-pong reuse of target frames."""

from __future__ import annotations

import numpy as np
import pytest

from nvp.schedule import ping_pong, stream_positions, target_frame_indices


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


def test_a_slower_stream_shows_the_nearest_footage_frame_and_keeps_its_speed():
    np.testing.assert_array_equal(stream_positions(0, 5, 1.5), [0, 2, 3, 5, 6])  # 0, 1.5, 3, 4.5, 6
    np.testing.assert_array_equal(stream_positions(3, 2, 2.0), [6, 8])
    np.testing.assert_array_equal(stream_positions(0, 4, 1.0), [0, 1, 2, 3])
    assert np.all(np.diff(stream_positions(0, 1000, 1.0001)) >= 1)  # never one footage frame twice
    np.testing.assert_array_equal(ping_pong(np.array([0, 3, 4, 6, 7]), 4), [0, 3, 2, 0, 1])
