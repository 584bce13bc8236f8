"""Copies of training speech as other voices, rooms and microphones (nvp.augment), and training on them."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from nvp.augment import (
    parse_augmentation,
    reverberant,
    room_impulse_response,
    speed_perturbed,
)
from nvp.errors import NvpError

RATE = 16000


def tone(hz: float, seconds: float = 1.0) -> np.ndarray:
    t = np.arange(int(seconds * RATE)) / RATE
    return (0.3 * np.sin(2 * np.pi * hz * t)).astype(np.float32)


def peak_hz(x: np.ndarray) -> float:
    spectrum = np.abs(np.fft.rfft(x * np.hanning(len(x))))
    return float(np.fft.rfftfreq(len(x), 1 / RATE)[np.argmax(spectrum)])


def test_a_faster_copy_is_shorter_and_higher_by_the_same_factor():
    x = tone(200.0)
    for factor in (0.9, 1.1):
        y = speed_perturbed(x, factor)
        assert abs(len(y) - len(x) / factor) <= 1
        assert peak_hz(y) == pytest.approx(200.0 * factor, abs=2.0)
        assert y.dtype == np.float32 and np.abs(y).max() <= 1.0
    a = parse_augmentation("speed1.1")
    assert a.time_scale == 1.1 and len(a.apply(x, RATE, 0)) == len(speed_perturbed(x, 1.1))


def test_a_room_copy_keeps_length_and_level_and_decays_by_its_reverberation_time():
    h = room_impulse_response(RATE, 0.5, seed=1)
    assert h[0] == 1.0 and len(h) == RATE // 2
    energy = np.cumsum(h[::-1] ** 2)[::-1]  # Schroeder's backward integral of the tail
    at = lambda s: 10 * np.log10(energy[int(s * RATE)] / energy[int(0.01 * RATE)])  # noqa: E731
    assert at(0.25) == pytest.approx(-60 * (0.25 - 0.01) / 0.5, abs=3.0)  # 60 dB over 0.5 s
    x = tone(300.0) * np.hanning(RATE).astype(np.float32)
    y = reverberant(x, RATE, 0.5, seed=1)
    assert y.shape == x.shape and np.sqrt(np.mean(y**2)) == pytest.approx(np.sqrt(np.mean(x**2)), rel=0.01)
    assert np.abs(y[-100:]).mean() > np.abs(x[-100:]).mean()  # the room rings on after the sound
    assert np.array_equal(y, reverberant(x, RATE, 0.5, seed=1))  # reproducible
    assert not np.array_equal(y, reverberant(x, RATE, 0.5, seed=2))


def test_a_noise_copy_has_the_asked_signal_to_noise_ratio():
    x = tone(250.0, 2.0)
    y = parse_augmentation("noise10").apply(x, RATE, 3)
    snr = 10 * np.log10(np.mean(x.astype(np.float64) ** 2) / np.mean((y - x).astype(np.float64) ** 2))
    assert snr == pytest.approx(10.0, abs=0.5)


@pytest.mark.parametrize(
    "name, message",
    [
        ("pitch3", "unknown augmentation 'pitch3'"),
        ("speed", "unknown augmentation"),
        ("speed3", "within 0.5-2"),
        ("room9", "within 0.05-3 s"),
    ],
)
def test_bad_augmentation_names_get_one_clear_error(name, message):
    with pytest.raises(NvpError, match=message):
        parse_augmentation(name)
    assert parse_augmentation(" noise20 ").name == "noise20"


def test_a_speed_copy_keeps_every_frame_on_its_own_sound(demo_clip, tmp_path):
    """The copy's features are read at the faster frame rate: one window per frame of the clip, as for the
    clean audio, cached under the copy's name."""
    from nvp.app.corpus import features_cached

    clean = features_cached(demo_clip.path, tmp_path, "whisper", 25.0, 30)
    fast = features_cached(demo_clip.path, tmp_path, "whisper", 25.0, 30, "speed1.1")
    assert fast.shape == clean.shape and not np.allclose(fast, clean)
    names = sorted(p.name for p in (tmp_path / "features").glob("*.json"))
    assert len(names) == 2 and any(n.endswith("_sn_speed1.1.json") for n in names)
    again = features_cached(demo_clip.path, tmp_path, "whisper", 25.0, 30, "speed1.1")
    assert np.array_equal(again, fast)  # from the cache


def test_the_opening_model_trains_on_the_copies_too(face_model, tmp_path):
    from nvp.app.train_opening import train_opening
    from tests.test_opening import _opening_sample

    train_set = [_opening_sample(face_model, f"t{i}", i) for i in range(3)]
    val_set = [_opening_sample(face_model, "v", 9)]
    plain, _ = train_opening(train_set, val_set, face_model, tmp_path / "a", ridges=(10.0,))
    # a copy with its first channel doubled: the normal equations hold both, so the fit changes
    copied = [dataclasses.replace(s, augmented=(s.windows * np.r_[2.0, np.ones(s.windows.shape[2] - 1)],))
              for s in train_set]  # fmt: skip
    both, info = train_opening(copied, val_set, face_model, tmp_path / "b", ridges=(10.0,))
    assert not np.allclose(both.weight, plain.weight)
    assert info["train_frames"] == 360  # frames of footage; the copies add none
