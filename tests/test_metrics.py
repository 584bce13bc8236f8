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


# ------------------------------------------------------------------------------- lip-sync behaviour


def test_bilabial_classes_in_the_recognisers_phone_set():
    from nvp.audio_features import phoneme_labels
    from nvp.metrics import BILABIAL_PHONES, bilabial_classes

    labels = phoneme_labels()
    idx = bilabial_classes(labels)
    assert sorted(labels[i] for i in idx) == sorted(BILABIAL_PHONES)
    assert {"p", "b", "m"} <= {labels[i] for i in idx} and "ɸ" not in {labels[i] for i in idx}
    with pytest.raises(ValueError, match="p, b or m"):
        bilabial_classes(["a", "t"])


def test_bilabial_frames_from_posteriors():
    from nvp.metrics import bilabial_frames

    logp = np.tile(np.log([0.7, 0.1, 0.1, 0.1]), (10, 1))  # 50 Hz rows; classes 1 and 2 are bilabial
    logp[3] = np.log([0.2, 0.3, 0.3, 0.2])  # 0.6: bilabial
    logp[7] = np.log([0.6, 0.2, 0.1, 0.1])  # 0.3: not
    # 25 fps: frame i covers rows 2i, 2i+1
    b = bilabial_frames(logp, np.array([1, 2]), 50.0, 25.0, 6)
    np.testing.assert_array_equal(b, [False, True, False, False, False, False])
    assert bilabial_frames(logp, np.array([1, 2]), 50.0, 25.0, 6, threshold=0.25)[[1, 3]].all()


def test_closed_level_and_bilabial_closure_rate():
    from nvp.metrics import bilabial_closure_rate, closed_level

    real = np.concatenate([np.zeros(5), np.linspace(0, 10, 96)])  # min 0, p95 9.5
    assert closed_level(real) == pytest.approx(0.15 * np.percentile(real, 95))
    gap = np.full(10, 5.0)
    gap[[2, 6]] = 0.5
    bil = np.zeros(10, bool)
    bil[[2, 4, 7]] = True  # 2: closed there; 4: closed 2 frames before; 7: closed one frame before
    assert bilabial_closure_rate(gap, bil, level=1.0, before=1) == pytest.approx(2 / 3)
    assert bilabial_closure_rate(gap, bil, level=1.0, before=0) == pytest.approx(1 / 3)
    assert bilabial_closure_rate(gap, bil, level=1.0, before=2) == 1.0
    bil[:] = False
    bil[5] = True  # closed one frame after only
    assert bilabial_closure_rate(gap, bil, 1.0, before=0) == 0.0
    assert bilabial_closure_rate(gap, bil, 1.0, before=0, after=1) == 1.0
    assert np.isnan(bilabial_closure_rate(gap, np.zeros(10, bool), 1.0, before=2))
    assert np.isnan(bilabial_closure_rate(np.full(10, np.nan), bil, 1.0, before=2))


def test_pause_mask_keeps_only_long_pauses():
    from nvp.metrics import pause_mask

    voiced = np.ones(30, bool)
    voiced[:4] = False  # 4 frames at the start: 0.16 s at 25 fps, too short
    voiced[10:18] = False  # 8 frames: 0.32 s
    voiced[25:] = False  # 5 frames at the end: 0.2 s
    m = pause_mask(voiced, 25.0, 0.3)
    np.testing.assert_array_equal(np.flatnonzero(m), np.arange(10, 18))
    assert pause_mask(voiced, 25.0, 0.15).sum() == 4 + 8 + 5
    assert not pause_mask(np.ones(5, bool), 25.0).any() and pause_mask(np.zeros(8, bool), 25.0).all()


def test_pause_behaviour_of_still_and_talking_mouths():
    from nvp.metrics import pause_behaviour

    speech = np.zeros(40, bool)
    speech[:20] = True
    pauses = ~speech
    talking = np.tile([0.0, 4.0], 20)  # |delta| 4 everywhere, open half the time
    r = pause_behaviour(talking, pauses, speech, rest_level=1.0)
    assert r["pause_closed_fraction"] == pytest.approx(0.5) and r["pause_motion_ratio"] == pytest.approx(1.0)
    still = talking.copy()
    still[20:] = 0.5
    r = pause_behaviour(still, pauses, speech, rest_level=1.0)
    assert r["pause_closed_fraction"] == 1.0 and r["pause_motion_ratio"] == 0.0
    r = pause_behaviour(still, np.zeros(40, bool), speech, 1.0)
    assert np.isnan(r["pause_closed_fraction"]) and np.isnan(r["pause_motion_ratio"])


def test_opening_range_ratio():
    from nvp.metrics import opening_range_ratio

    real = np.linspace(0, 10, 101)
    assert opening_range_ratio(real, real) == pytest.approx(1.0)
    assert opening_range_ratio(0.5 * real, real) == pytest.approx(0.5)
    assert np.isnan(opening_range_ratio(real, np.zeros(5)))


def test_eval_lip_metrics_measure_output_and_real_alike():
    """nvp eval's landmark metrics on made-up mediapipe landmarks with known lip behaviour."""
    from nvp.app.evaluate import _lip_metrics

    groups = {
        "lips_outer": np.array([61, 17]),
        "lips_inner": np.array([13, 14]),
        "left_eye": np.array([263]),
        "right_eye": np.array([33]),
    }
    t = 40
    real = np.zeros((t, 478, 2))
    real[:, 263, 0], real[:, 33, 0] = 100.0, 0.0  # interocular distance 100 px
    real_gap = np.tile([0.0, 20.0], t // 2)  # talks, closing every other frame
    real_gap[20:] = 0.0  # then rests closed
    real[:, 14, 1] = real_gap
    gen = real.copy()
    gen[:, 14, 1] = np.tile([10.0, 20.0], t // 2)  # never closes, keeps talking in the pause
    timing = {
        "bilabial": np.isin(np.arange(t), [4, 10]),
        "speech": np.arange(t) < 20,
        "pauses": np.arange(t) >= 20,
        "fps": 25.0,
    }
    m = _lip_metrics(real, gen, np.ones(t, bool), groups, timing)
    assert m["bilabial_frames"] == 2 and m["pause_frames"] == 20
    assert m["bilabial_closure_rate_real"] == 1.0 and m["bilabial_closure_rate"] == 0.0
    assert m["bilabial_closure_ratio"] == 0.0
    assert m["pause_closed_fraction_real"] == 1.0 and m["pause_closed_fraction"] == 0.0
    assert m["pause_motion_ratio_real"] == 0.0 and m["pause_motion_ratio"] == pytest.approx(1.0)
    assert m["opening_range_ratio"] == pytest.approx(1.0)
    assert m["closure_recall"] == 0.0


def test_eval_takes_each_held_out_frames_detail_from_another_frame_a_second_away():
    from types import SimpleNamespace

    from nvp.app.evaluate import detail_sources

    t = 200
    yaw = np.radians(np.r_[np.zeros(150), np.linspace(0, 20, 50)])  # the head turns in the last 2 s
    rot = np.zeros((t, 3, 3))
    rot[:, 0, 0] = rot[:, 2, 2] = np.cos(yaw)
    rot[:, 0, 2], rot[:, 2, 0] = np.sin(yaw), -np.sin(yaw)
    rot[:, 1, 1] = 1
    seq = SimpleNamespace(rotation=rot, fps=25.0)
    held = np.arange(100, 200)
    src = detail_sources(seq, held, count=8)
    assert len(np.unique(src)) <= 8 and set(src) <= set(held.tolist())
    assert (np.abs(src - held) >= 25).all()  # never the frame itself or its neighbours
    assert src[-1] >= 150  # a turned head takes its detail from a turned frame
    short = np.arange(100, 120)  # under a second held out: the farthest frame
    assert (np.abs(detail_sources(seq, short, count=8) - short) >= 9).all()


def test_eval_mouth_box_summary_pools_detail_and_skips_frames_without_a_face():
    from nvp.app.evaluate import mouth_box_summary

    # PSNR, high-frequency and Laplacian energy, agreement, high-frequency sums of interior, lips, skin
    real = np.array(
        [[np.inf, 4.0, 2.0, 4.0, 1.0, 4.0, 8.0], [np.inf, 16.0, 4.0, 16.0, 3.0, 4.0, 30.0], [np.nan] * 7]
    )
    made = np.array(
        [[30.0, 2.0, 1.0, 1.0, 1.0, 1.0, 6.0], [np.inf, 10.0, 3.0, 9.0, 3.0, 1.0, 20.0], [np.nan] * 7]
    )
    out = mouth_box_summary(made, real)
    # per region, pooled too: the interior kept, the lips a quarter, the skin two thirds
    assert [out[f"hf_ratio_{r}"] for r in ("interior", "lips", "skin")] == pytest.approx([1.0, 0.25, 26 / 38])
    assert out["psnr_mouth"] == 30.0  # identical frames (inf) and faceless ones left out of the mean
    assert out["hf_ratio_mouth"] == pytest.approx(12 / 20)  # pooled, not the mean of 0.5 and 0.625
    assert out["laplacian_ratio_mouth"] == pytest.approx(4 / 6)
    assert out["hf_in_place_mouth"] == pytest.approx(10 / np.sqrt(12 * 20))
    assert mouth_box_summary(real, real)["hf_in_place_mouth"] == pytest.approx(1.0)
    assert np.isnan(mouth_box_summary(made[2:], real[2:])["hf_ratio_mouth"])
