"""Evaluation metrics on cases with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from nvp.metrics import av_offset, closure_f1, inner_lip_gap, jitter, landmark_error, psnr, ssim


def test_identical_images_and_landmarks():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (32, 40, 3), dtype=np.uint8)
    assert psnr(img, img) == float("inf")
    assert ssim(img, img) == pytest.approx(1.0, abs=1e-5)
    lm = rng.normal(0, 10, (5, 478, 2))
    assert np.all(landmark_error(lm, lm) == 0)


def test_psnr_matches_the_formula():
    a = np.zeros((10, 10, 3), np.uint8)
    b = np.full((10, 10, 3), 16, np.uint8)
    assert psnr(a, b) == pytest.approx(10 * np.log10(255**2 / 16**2))
    assert ssim(a, b) < 1.0


@pytest.mark.parametrize("k", [-3, 0, 2, 5])
def test_av_offset_finds_a_shift(k):
    rng = np.random.default_rng(1)
    real = np.convolve(rng.random(300), np.ones(4) / 4, mode="same")
    generated = np.roll(real, k)  # generated[t + k] == real[t]
    lag, corr = av_offset(generated, real)
    assert lag == k and corr > 0.9


def test_frozen_mouth_has_zero_closure_recall():
    real = np.abs(np.sin(np.linspace(0, 20, 200))) * 10
    frozen = np.full_like(real, real.mean())
    r = closure_f1(frozen, real, threshold=2.0)
    assert r["closure_recall"] == 0 and r["closure_f1"] == 0
    perfect = closure_f1(real, real, threshold=2.0)
    assert perfect["closure_precision"] == perfect["closure_recall"] == 1


def test_jitter_and_gap():
    still = np.zeros((6, 478, 2))
    assert np.all(jitter(still) == 0)
    lm = np.zeros((1, 478, 2))
    lm[0, 14, 1] = 3.0
    assert inner_lip_gap(lm)[0] == 3.0
