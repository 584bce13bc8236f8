"""Tests for nvp.windows: video frame counts and per-frame feature windows."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nvp.audio_features import AudioFeatures, extract_features
from nvp.errors import NvpError
from nvp.windows import frame_windows, num_video_frames

SR = 16000


def impulse_features(rate: float, n: int, at: int) -> AudioFeatures:
    v = np.zeros((n, 1), np.float32)
    v[at] = 1.0
    return AudioFeatures(values=v, rate=rate, kind="phonemes", duration_s=n / rate)


def test_windows_exact_at_25fps():
    # 50 Hz features, impulse at 1.0 s; at 25 fps every window sample lies on a feature frame.
    f = impulse_features(50.0, 150, at=50)
    w = frame_windows(f, 25.0)
    assert w.shape == (75, 16, 1)
    assert w[25, :, 0].argmax() == 8 and w[25, 8, 0] == 1.0 and w[25].sum() == 1.0
    assert w[24, 10, 0] == 1.0  # 0.96 s + 2 / 50 s
    assert w[26, 6, 0] == 1.0  # 1.04 s - 2 / 50 s
    assert w[20].sum() == 0.0  # 0.8 s: the window [0.64, 0.94] s misses 1.0 s


@pytest.mark.parametrize("fps", [25.0, 30.0, 30000 / 1001])
def test_windows_match_reference_interpolation(fps):
    rng = np.random.default_rng(1)
    f = AudioFeatures(rng.standard_normal((173, 3)).astype(np.float32), 50.0, "phonemes", 173 / 50)
    w = frame_windows(f, fps, window=16)
    assert w.shape == (math.ceil(173 / 50 * fps - 1e-6), 16, 3)
    for i in [0, 1, 7, len(w) // 2, len(w) - 1]:
        times = i / fps + (np.arange(16) - 8) / 50.0
        for d in range(3):
            ref = np.interp(times, f.times(), f.values[:, d])  # edge values outside, like edge padding
            np.testing.assert_allclose(w[i, :, d], ref, atol=1e-5)


def test_windows_edge_padding_and_num_frames():
    f = AudioFeatures(np.arange(10, dtype=np.float32)[:, None], 50.0, "phonemes", 0.2)
    w = frame_windows(f, 25.0, num_frames=7, window=4)
    assert w.shape == (7, 4, 1)
    np.testing.assert_array_equal(w[0, :, 0], [0, 0, 0, 1])  # t - 2/50, t - 1/50 clamp to frame 0
    np.testing.assert_array_equal(w[6, :, 0], [9, 9, 9, 9])  # 0.24 s is after the last frame (0.18 s)


def test_windows_from_a_first_frame_are_a_slice_of_all_windows():
    f = AudioFeatures(np.random.default_rng(0).random((120, 3), dtype=np.float32), 50.0, "phonemes", 2.4)
    whole = frame_windows(f, 30.0)
    np.testing.assert_array_equal(frame_windows(f, 30.0, num_frames=50, first=20), whole[20:50])
    assert frame_windows(f, 30.0, first=len(whole)).shape == (0, 16, 3)
    with pytest.raises(NvpError, match="first frame"):
        frame_windows(f, 30.0, first=len(whole) + 1)


def test_num_video_frames():
    assert num_video_frames(20.0, 25.0) == 500
    assert num_video_frames(2.0, 30000 / 1001) == 60  # 59.94 -> 60
    assert num_video_frames(1.0, 29.97) == 30
    assert num_video_frames(0.0, 25.0) == 0


def test_mel_windows_span_320ms_and_keep_constants():
    f = AudioFeatures(np.full((101, 2), -5.0, np.float32), 100.0, "mel", 1.0)
    w = frame_windows(f, 25.0)
    np.testing.assert_allclose(w, -5.0, atol=1e-6)  # smoothing keeps constants; edges padded


@pytest.mark.parametrize("fps", [25.0, 30000 / 1001])
def test_click_lands_at_window_centre(fps):
    i = 37
    t = i / fps + 0.004  # a click 4 ms after video frame i
    audio = np.zeros(3 * SR, np.float32)
    s = int(round(t * SR))
    audio[s : s + 16] = np.hanning(16).astype(np.float32)
    f = extract_features(audio, SR, kind="mel")
    w = frame_windows(f, fps)
    energy = w[i].mean(axis=1)  # (16,) mean log-mel power at each window position
    assert energy.argmax() == 8
    # the frame nearest the click is the one whose centre sample is loudest
    assert np.argmax(w[:, 8].mean(axis=1)) == i
