"""Tests for nvp.image_metrics with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from nvp.image_metrics import (
    border_band,
    detail_in_place,
    high_frequency_agreement,
    high_frequency_energy,
    high_frequency_sums,
    laplacian_energy,
    masked_psnr,
    masked_ssim,
    mouth_box,
    mouth_regions,
    seam_gradient_ratio,
)


def textured(seed: int = 0, size: int = 64) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(40, 215, (size, size, 3)).astype(np.uint8)


def test_masked_psnr_counts_only_the_mask():
    a = np.full((8, 8, 3), 100, np.uint8)
    b = a.copy()
    b[:4] += 10  # differs by 10 in the top half only
    top = np.zeros((8, 8), bool)
    top[:4] = True
    assert masked_psnr(a, b, top) == pytest.approx(20 * np.log10(255 / 10))
    assert masked_psnr(a, b, ~top) == float("inf")
    assert np.isnan(masked_psnr(a, b, np.zeros((8, 8), bool)))


def test_masked_ssim_is_one_where_equal_and_lower_where_not():
    a = textured()
    b = a.copy()
    b[32:] = textured(1)[32:]
    top = np.zeros(a.shape[:2], bool)
    top[:24] = True
    assert masked_ssim(a, b, top) == pytest.approx(1.0, abs=1e-4)
    assert masked_ssim(a, b, ~top) < 0.5


def test_mouth_box_grows_by_the_mouth_width_and_clips():
    lips = np.array([[40.0, 50.0], [60.0, 50.0], [50.0, 45.0], [50.0, 55.0]])  # 20 px wide
    assert mouth_box(lips, (100, 100)) == (33, 67, 28, 72)  # 0.6 * 20 = 12 px on each side
    assert mouth_box(lips, (60, 65)) == (33, 60, 28, 65)


def test_fine_detail_energies_fall_with_blur_and_rise_with_grain():
    import cv2

    real = textured(size=96)
    box = (16, 80, 16, 80)

    def ratios(fake: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
        return (
            high_frequency_energy(fake, box) / high_frequency_energy(ref, box),
            laplacian_energy(fake, box) / laplacian_energy(ref, box),
        )

    assert ratios(real, real) == pytest.approx((1.0, 1.0))
    hf, lap = ratios(cv2.GaussianBlur(real, (7, 7), 2.0), real)
    assert hf < 0.2 and lap < 0.5
    smooth = cv2.GaussianBlur(real, (9, 9), 3.0)
    grainy = np.clip(smooth + np.random.default_rng(5).normal(0, 20, smooth.shape), 0, 255).astype(np.uint8)
    assert ratios(grainy, smooth)[0] > 5.0


def test_seam_ratio_is_one_without_a_seam_and_grows_with_one():
    real = np.full((64, 64, 3), 120, np.uint8)
    weight = np.zeros((64, 64), np.float32)
    weight[16:48, 16:48] = 1.0
    band = border_band(weight, 2)
    assert band[16, 30] and band[15, 30] and not band[30, 30] and not band[2, 2]
    real = real + (np.indices((64, 64))[1][..., None] // 8).astype(np.uint8)  # a gentle ramp
    assert seam_gradient_ratio(real, real, weight) == pytest.approx(1.0)
    seam = real.copy()
    seam[16:48, 16:48] += 30  # the painted square is brighter: a visible edge at its border
    assert seam_gradient_ratio(seam, real, weight) > 2.0
    assert np.isnan(seam_gradient_ratio(real, real, np.zeros_like(weight)))


def test_detail_in_place_tells_the_footage_own_detail_from_specks_and_misplaced_detail():
    """The energy ratio counts any fine detail; its correlation with the real frame's says whether it is
    the footage's, in place: 1 for the frame itself, high for a blurred copy (less of the same detail),
    about 0 for grain or the same texture moved by two pixels."""
    import cv2

    real = textured(size=96)
    box = (16, 80, 16, 80)

    def in_place(fake: np.ndarray) -> float:
        e = [high_frequency_energy(fake, box)], [high_frequency_energy(real, box)]
        return detail_in_place(np.array([high_frequency_agreement(fake, real, box)]), *map(np.array, e))

    blurred = cv2.GaussianBlur(real, (3, 3), 0.8)
    grainy = np.clip(blurred + np.random.default_rng(3).normal(0, 30, real.shape), 0, 255).astype(np.uint8)
    assert in_place(real) == pytest.approx(1.0)
    assert in_place(blurred) > 0.6  # 0.69: little detail (energy ratio 0.06), all of it in place
    assert abs(in_place(np.roll(real, 2, axis=1))) < 0.3  # all the detail, two pixels off
    # grain on the blurred copy: six times the energy (0.39), a third of the agreement (0.26)
    assert high_frequency_energy(grainy, box) > 5 * high_frequency_energy(blurred, box)
    assert in_place(grainy) < 0.5 * in_place(blurred)
    assert np.isnan(detail_in_place(np.zeros(1), np.zeros(1), np.zeros(1)))


def test_mouth_regions_split_the_box_and_the_detail_lost_is_found_where_it_was_lost():
    import cv2

    outer = np.array([[20, 32], [32, 24], [44, 32], [32, 42]], float)  # a diamond of lips
    inner = np.array([[26, 32], [32, 30], [38, 32], [32, 35]], float)
    box = (10, 54, 10, 54)
    regions = mouth_regions(outer, inner, box)
    assert {k: v.shape for k, v in regions.items()} == {k: (44, 44) for k in ("interior", "lips", "skin")}
    total = sum(v.astype(int) for v in regions.values())
    assert (total == 1).all()  # every pixel of the box in exactly one
    assert regions["interior"][32 - 10, 32 - 10] and regions["lips"][27 - 10, 32 - 10]
    assert regions["skin"][0, 0] and 0 < regions["interior"].sum() < regions["lips"].sum()
    real = textured(3)
    soft = real.copy()  # the lips blurred, interior and skin kept
    lips = np.zeros(real.shape[:2], bool)
    lips[10:54, 10:54] = regions["lips"]
    soft[lips] = cv2.GaussianBlur(real, (7, 7), 2.0)[lips]
    kept = high_frequency_sums(soft, box, regions)
    truth = high_frequency_sums(real, box, regions)
    assert kept["lips"] < 0.1 * truth["lips"]
    # the 5×5 filter reaches 2 px into the neighbours only
    assert kept["skin"] > 0.95 * truth["skin"] and kept["interior"] > 0.9 * truth["interior"]
    assert sum(truth.values()) == pytest.approx(high_frequency_energy(real, box) * 44 * 44, rel=1e-5)
