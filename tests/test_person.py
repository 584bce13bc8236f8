"""Person maps on disk, expression prediction for new audio, and the person-map / predict commands."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import soundfile as sf
import torch
from test_cli import assert_one_line_error, nvp

from nvp.audio2exp import (
    Audio2ExpConfig,
    Audio2ExpressionNet,
    PersonMap,
    default_audio2exp,
    load_net,
    save_net,
)
from nvp.errors import FormatError
from nvp.person import PersonStyle, predict_expressions

K = 64


def _style(kind="mel", sha="0" * 64, seed=0):
    rng = np.random.default_rng(seed)
    pm = PersonMap(rng.normal(0, 0.1, (K, 32)).astype(np.float32), rng.normal(0, 0.1, K).astype(np.float32))
    return PersonStyle(pm, rng.normal(0, 0.1, K).astype(np.float32), kind, sha, {"video": "x.mp4"})


def test_person_style_round_trip(tmp_path):
    style = _style()
    js = style.save(tmp_path / "style")
    assert js.name == "style.json" and (tmp_path / "style.npz").exists()
    assert not list(tmp_path.glob(".*tmp*"))  # no temporary files left behind
    back = PersonStyle.load(js)
    np.testing.assert_array_equal(back.person_map.matrix, style.person_map.matrix)
    np.testing.assert_array_equal(back.person_map.bias, style.person_map.bias)
    np.testing.assert_array_equal(back.rest_expression, style.rest_expression)
    assert (back.feature_kind, back.audio2exp_sha256, back.info) == ("mel", "0" * 64, {"video": "x.mp4"})


def test_person_style_rejects_bad_files(tmp_path):
    with pytest.raises(FormatError, match="missing.json is missing"):
        PersonStyle.load(tmp_path / "missing.json")
    (tmp_path / "other.json").write_text(json.dumps({"format": "something else", "version": 1}))
    with pytest.raises(FormatError, match="expected nvp.person_map"):
        PersonStyle.load(tmp_path / "other.json")


def test_input_standardisation_is_saved_with_the_weights(tmp_path):
    net = Audio2ExpressionNet(Audio2ExpConfig(feature_dim=80))
    feats = torch.randn(500, 80) * 3 - 10
    net.per_frame.set_input_stats(feats)
    torch.testing.assert_close(net.per_frame.input_mean, feats.mean(0), atol=1e-4, rtol=0)
    save_net(net, tmp_path / "m", {"feature_kind": "mel"})
    back, _ = load_net(tmp_path / "m.json")
    torch.testing.assert_close(back.per_frame.input_std, net.per_frame.input_std)


@pytest.mark.parametrize("fps", [25.0, 30000 / 1001])
def test_predict_expressions_has_one_row_per_video_frame(fps):
    net = Audio2ExpressionNet(Audio2ExpConfig(feature_dim=80)).eval()
    audio = (0.1 * np.sin(np.linspace(0, 2000, 44100 * 2))).astype(np.float32)
    expr = predict_expressions(audio, 44100, fps, _style(), net)
    assert expr.shape == (int(np.ceil(2.0 * fps)), K) and np.isfinite(expr).all()
    assert predict_expressions(audio, 44100, fps, _style(), net, num_frames=10).shape == (10, K)


def test_predict_expressions_in_blocks_equals_one_pass(monkeypatch):
    """Windows are made block by block (bounded memory); the result must equal the whole-file path."""
    from nvp import person
    from nvp.audio2exp import audio_expressions
    from nvp.audio_features import extract_features, speaker_normalized
    from nvp.vad import voice_activity
    from nvp.windows import frame_windows

    torch.manual_seed(0)
    net = Audio2ExpressionNet(Audio2ExpConfig(feature_dim=80)).eval()
    rng = np.random.default_rng(2)
    audio = (0.2 * rng.standard_normal(16000 * 3)).astype(np.float32)
    style = _style()
    monkeypatch.setattr(person, "WINDOW_BLOCK", 7)  # 75 frames: 11 blocks, the last one partial
    blocked = predict_expressions(audio, 16000, 25.0, style, net)
    windows = frame_windows(speaker_normalized(extract_features(audio, 16000, kind="mel")), 25.0)
    expr = style.person_map.apply(audio_expressions(net, windows))
    voice = voice_activity(audio, 16000, 25.0, len(expr))[:, None]
    whole = style.rest_expression + voice * (expr - style.rest_expression)
    np.testing.assert_allclose(blocked, whole, atol=1e-5)


@pytest.mark.parametrize("pause", ["silence", "noise"])
def test_pauses_give_the_rest_expression_and_speech_does_not(pause):
    from nvp.app.demo_voice import speech_script, synth_voice

    net = Audio2ExpressionNet(Audio2ExpConfig(feature_dim=80)).eval()
    style = _style()
    rng = np.random.default_rng(1)
    speech = synth_voice(speech_script(2.0, rng), 2.0, rng)
    audio = np.concatenate([np.zeros(16000 * 2, np.float32), speech, np.zeros(16000 * 2, np.float32)])
    if pause == "noise":  # white noise at -30 dBFS throughout: not voice, the mouth still rests
        audio += (0.03 * rng.standard_normal(len(audio))).astype(np.float32)
    expr = predict_expressions(audio, 16000, 25.0, style, net)
    assert expr.shape == (150, K)
    np.testing.assert_allclose(expr[:40], np.broadcast_to(style.rest_expression, (40, K)), atol=1e-6)
    np.testing.assert_allclose(expr[-40:], np.broadcast_to(style.rest_expression, (40, K)), atol=1e-6)
    assert np.abs(expr[60:90] - style.rest_expression).max() > 1e-3  # speech is driven by the network
    steps = np.abs(np.diff(expr, axis=0)).max(1)
    assert steps.max() < 0.6 * np.abs(expr - style.rest_expression).max()  # no jump at the transitions


def test_rest_expression_is_the_most_closed_frames():
    from nvp.person import rest_expression

    expr = np.arange(20, dtype=np.float32)[:, None] * np.ones((1, 3), np.float32)
    gap = np.arange(20, 0, -1, dtype=np.float32)
    np.testing.assert_allclose(rest_expression(expr, gap, fraction=0.1), [18.5, 18.5, 18.5])


@pytest.mark.parametrize("kind", ["phonemes", "mel"])
def test_shipped_networks_load_with_provenance(kind):
    net, manifest = default_audio2exp(kind)
    assert manifest["feature_kind"] == kind
    assert net.cfg.feature_dim == (191 if kind == "phonemes" else 80)
    assert len(manifest["split"]["validation"]) >= 5
    assert not set(manifest["split"]["validation"]) & set(manifest["split"]["train"])
    assert manifest["validation"]["mouth_error_iod"] > 0
    assert len(manifest["sha256"]) == 64


def test_person_map_and_predict_commands(demo_clip, tmp_path):
    proc = nvp(
        "person-map", demo_clip.path, "-o", tmp_path / "style", "--features", "mel", "--cache", tmp_path
    )
    assert proc.returncode == 0, proc.stderr
    style = PersonStyle.load(tmp_path / "style.json")
    assert style.feature_kind == "mel" and np.isfinite(style.person_map.matrix).all()
    wav = tmp_path / "speech.wav"
    sf.write(wav, (0.2 * np.random.default_rng(0).standard_normal((48000, 2))).astype(np.float32), 48000)
    from nvp.app.corpus import cache_key

    track = tmp_path / "tracks" / cache_key(demo_clip.path)
    proc = nvp(
        "predict",
        wav,
        "--style",
        tmp_path / "style.json",
        "--fps",
        30,
        "--mesh",
        track,
        "-o",
        tmp_path / "p.npz",
    )
    assert proc.returncode == 0, proc.stderr
    with np.load(tmp_path / "p.npz") as z:
        assert z["expression"].shape == (30, K)
        assert z["vertices"].shape[:2] == (30, 468) and z["triangles"].shape[1] == 3


def test_predict_rejects_a_map_made_with_another_network(tmp_path):
    _style(kind="mel", sha="f" * 64).save(tmp_path / "style")
    sf.write(tmp_path / "a.wav", np.zeros(16000, np.float32), 16000)
    proc = nvp("predict", tmp_path / "a.wav", "--style", tmp_path / "style.json", "-o", tmp_path / "p.npz")
    assert_one_line_error(proc, "another audio2expressionnet")
    assert not (tmp_path / "p.npz").exists()


def _footage_with_pauses(face_model, pause_mouth, seed=0):
    """30 s of synthetic footage at 25 fps: speech (the mouth opening and closing along the coefficient that
    opens it most) with 0.6-1.6 s pauses in which ``pause_mouth(frame in the pause)`` says how far it is
    open (1 = a typical speaking opening). Returns expressions, gaps, voiced flags, the opening coefficient
    and its scale."""
    fps, t = 25.0, 750
    ident = np.zeros(face_model.num_id, np.float32)
    eye = np.eye(face_model.num_exp, dtype=np.float32)
    k = int(
        np.argmax(np.abs(face_model.inner_lip_gap(ident, eye) - face_model.inner_lip_gap(ident, 0 * eye)))
    )
    sign = np.sign(
        face_model.inner_lip_gap(ident, eye[k : k + 1] * 3)[0]
        - face_model.inner_lip_gap(ident, 0 * eye[:1])[0]
    )
    rng = np.random.default_rng(seed)
    amount = np.abs(np.sin(np.arange(t) * 0.7)) * rng.uniform(0.6, 1.4, t)  # syllables, closing between
    voiced = np.ones(t, bool)
    at = 20
    while at < t - 60:
        length = int(rng.integers(15, 40))
        voiced[at : at + length] = False
        amount[at : at + length] = [pause_mouth(j) for j in range(length)]
        at += length + int(rng.integers(40, 90))
    expr = np.zeros((t, face_model.num_exp), np.float32)
    expr[:, k] = sign * 3.0 * amount
    return fps, expr, face_model.inner_lip_gap(ident, expr), voiced, k


@pytest.mark.parametrize(
    "rests",
    [
        "closed",  # closes the lips 0.2 s into every pause
        "slightly_open",  # never closes them in pauses: a small opening throughout
        "wide_open",  # breathes through an open mouth in pauses, wider than they speak
    ],
)
def test_pauses_rest_as_the_person_rests_in_their_footage(face_model, rests):
    from nvp.metrics import closed_level, pause_mask
    from nvp.person import pause_rest

    pause_mouth = {
        "closed": lambda j: 0.6 if j < 5 else 0.0,
        "slightly_open": lambda j: 0.25,
        "wide_open": lambda j: 1.6,
    }[rests]
    fps, expr, gap, voiced, k = _footage_with_pauses(face_model, pause_mouth)
    ident = np.zeros(face_model.num_id, np.float32)
    rest, open_, delay = pause_rest(expr, gap, voiced, fps, lambda e: face_model.inner_lip_gap(ident, e))
    pauses = pause_mask(voiced, fps, 0.3)
    resting = closed_level(gap, 0.3)
    real_rests = np.mean(gap[pauses] <= resting)
    # new audio with other pauses: the mouth each frame rests towards, where the voice is off
    style = PersonStyle(
        PersonMap(np.zeros((K, 32), np.float32), np.zeros(K, np.float32)), rest, "mel", "0", {}
    )
    style = dataclasses.replace(style, pause_open=open_, pause_close_after_s=delay)
    _, _, _, new_voiced, _ = _footage_with_pauses(face_model, pause_mouth, seed=7)
    track = style.rest_track(new_voiced.astype(np.float32), fps)
    out_gap = face_model.inner_lip_gap(ident, track)[pause_mask(new_voiced, fps, 0.3)]
    out_rests = np.mean(out_gap <= resting)
    assert abs(out_rests - real_rests) <= 0.15, (out_rests, real_rests)
    assert out_gap.max() <= np.median(gap[voiced]) + 1e-6  # never wider than they speak
    if rests == "closed":
        assert real_rests > 0.6 and 0.1 <= delay <= 0.3
        assert np.median(out_gap) <= closed_level(gap)  # the lips closed, as theirs are
    elif rests == "slightly_open":  # their own small opening (resting, by the metric), not closed lips
        assert real_rests == 1 and delay == 0.3  # at once, but never within a gap between words
        np.testing.assert_allclose(np.median(out_gap), np.median(gap[pauses]), rtol=0.05)
        assert np.median(out_gap) > closed_level(gap)
    else:
        assert real_rests == 0 and delay == np.inf


def test_with_few_pauses_one_mouth_holds_them_no_wider_than_speech(face_model):
    from nvp.person import pause_rest

    fps, expr, gap, voiced, k = _footage_with_pauses(face_model, lambda j: 1.6)
    ident = np.zeros(face_model.num_id, np.float32)
    gap_of = lambda e: face_model.inner_lip_gap(ident, e)  # noqa: E731
    rest, open_, delay = pause_rest(expr, gap, voiced, fps, gap_of, timing_min_frames=10**6)
    assert open_ is None and delay == 0
    # their pauses are wider than their speech: the rest is cut back to their median speaking opening
    np.testing.assert_allclose(gap_of(rest[None])[0], np.median(gap[voiced]), rtol=0.1)
    assert gap_of(rest[None])[0] <= np.median(gap[voiced])
    assert pause_rest(expr, gap, np.ones_like(voiced), fps, gap_of) is None  # no pause: the caller decides


def test_a_style_that_rests_over_time_round_trips_and_needs_the_frame_rate(tmp_path):
    from nvp.person import apply_style

    style = dataclasses.replace(_style(), pause_open=np.full(K, 0.5, np.float32), pause_close_after_s=0.2)
    back = PersonStyle.load(style.save(tmp_path / "s.npz"))
    np.testing.assert_array_equal(back.pause_open, style.pause_open)
    assert back.pause_close_after_s == 0.2
    never = dataclasses.replace(style, pause_close_after_s=float("inf"))
    assert PersonStyle.load(never.save(tmp_path / "n.npz")).pause_close_after_s == float("inf")
    voice = np.array([1, 1, 0, 0, 0, 0, 0, 0, 0, 0, 1], np.float32)
    track = style.rest_track(voice, 25.0)
    np.testing.assert_allclose(track[2:6], 0.5)  # the first 0.2 s of the pause: the open mouth
    np.testing.assert_allclose(track[8:10], np.broadcast_to(style.rest_expression, (2, K)), atol=1e-6)
    with pytest.raises(ValueError, match="frame rate"):
        apply_style(style, np.zeros((11, 32), np.float32), None, voice)


def test_text_closures_close_the_lips_on_p_b_m_even_when_the_audio_model_does_not():
    from nvp.person import apply_style

    style = dataclasses.replace(_style(), closed_expression=np.full(K, -1.0, np.float32))
    audio_exp = np.random.default_rng(0).normal(size=(6, 32)).astype(np.float32)
    w = np.array([0, 1, 1, 0, 0.5, 0], np.float32)
    out = apply_style(style, audio_exp, None, None, text_closure=w)
    free = apply_style(style, audio_exp, None, None)
    np.testing.assert_allclose(out[[0, 3, 5]], free[[0, 3, 5]])
    np.testing.assert_allclose(out[1:3], -1.0, atol=1e-6)
    np.testing.assert_allclose(out[4], (free[4] - 1.0) / 2, atol=1e-6)


def test_range_calibration_widens_a_compressed_map_to_the_real_spread():
    from nvp.person import RANGE_GAIN_MAX, range_calibrated

    rng = np.random.default_rng(0)
    a = rng.normal(size=(200, 32)).astype(np.float32)
    pm = PersonMap(rng.normal(0, 0.1, (K, 32)).astype(np.float32), np.zeros(K, np.float32))

    def gap(e):
        return e[:, 0]

    pred = pm.apply(a)
    real = pred[:, 0].mean() + 1.5 * (pred[:, 0] - pred[:, 0].mean())  # the real mouth opens 1.5× as wide
    wide, gain = range_calibrated(pm, a, gap, real)
    assert gain == pytest.approx(1.5, rel=1e-3)
    np.testing.assert_allclose(gap(wide.apply(a)), real, atol=1e-5)
    np.testing.assert_allclose(wide.apply(a).mean(0), pred.mean(0), atol=1e-5)  # same mean mouth
    # never narrower, never wider than the limit
    assert range_calibrated(pm, a, gap, 0.5 * pred[:, 0])[1] == 1.0
    assert range_calibrated(pm, a, gap, 10 * pred[:, 0])[1] == RANGE_GAIN_MAX


def test_the_closure_head_closes_the_mouth_and_pauses_rest_it():
    from nvp.person import apply_style, closed_mouth

    style = _style()
    closed = np.full(K, 0.5, np.float32)
    style = PersonStyle(style.person_map, style.rest_expression, "mel", "0" * 64, {}, closed)
    a = np.random.default_rng(1).normal(size=(4, 32)).astype(np.float32)
    mapped = style.person_map.apply(a)
    out = apply_style(style, a, np.array([0.0, 1.0, 0.0, 1.0]), np.array([1.0, 1.0, 0.0, 0.0]))
    np.testing.assert_allclose(out[0], mapped[0], atol=1e-6)  # open where the head says open
    np.testing.assert_allclose(out[1], closed, atol=1e-6)  # closed where it says closed
    np.testing.assert_allclose(out[2:], np.stack([style.rest_expression] * 2), atol=1e-6)  # no voice: rest
    # the closed mouth is the mean of the person's closed frames while speaking
    expr = np.arange(10, dtype=np.float32)[:, None] * np.ones((1, K), np.float32)
    gap = np.array([0, 0, 0, 0, 5, 5, 5, 5, 9, 9], np.float32)
    voiced = np.array([0, 1, 1, 1, 1, 1, 1, 1, 1, 1], bool)
    np.testing.assert_allclose(closed_mouth(expr, gap, voiced), 2.0)
    np.testing.assert_allclose(closed_mouth(expr, gap), 1.5)


def test_style_round_trip_keeps_the_closed_mouth_and_reads_version_1(tmp_path):
    from nvp.artifact import save_artifact

    s = _style()
    closed = np.full(K, 0.25, np.float32)
    with_closed = PersonStyle(s.person_map, s.rest_expression, "mel", "0" * 64, {}, closed)
    np.testing.assert_array_equal(
        PersonStyle.load(with_closed.save(tmp_path / "v2")).closed_expression, closed
    )
    arrays = {"matrix": s.person_map.matrix, "bias": s.person_map.bias, "rest": s.rest_expression}
    fields = {"feature_kind": "mel", "audio2exp_sha256": "0" * 64, "info": {}}
    old = PersonStyle.load(save_artifact(tmp_path / "v1", "person_map", 1, arrays, fields))
    assert old.closed_expression is None
    np.testing.assert_array_equal(old.rest_expression, s.rest_expression)


def test_style_transfer_moves_the_mouth_statistics_towards_the_other_person(face_model):
    from nvp.errors import NvpError
    from nvp.metrics import closed_level
    from nvp.person import apply_style, transferred_style

    rng = np.random.default_rng(0)
    a = rng.normal(size=(300, 32)).astype(np.float32)
    closure = (rng.random(300) < 0.2).astype(np.float32)  # the closure head's say
    m = rng.normal(0, 0.05, (K, 32)).astype(np.float32)

    def person(gain, rest, closes):
        bias = np.zeros(K, np.float32)
        bias[0] = rest
        shut = np.full(K, rest / 2, np.float32) if closes else None
        return PersonStyle(PersonMap(gain * m, bias), bias.copy(), "mel", "0" * 64, {"video": "x"}, shut)

    def stats(style):
        gap = face_model.inner_lip_gap(
            np.zeros(face_model.num_id, np.float32), apply_style(style, a, closure, None)
        )
        closed = gap <= closed_level(gap_own)
        return np.percentile(gap, 95) - np.percentile(gap, 5), closed.mean(), gap

    own, other = person(1.0, 0.0, False), person(3.0, 0.5, True)  # the other opens wider and closes firmly
    gap_own = face_model.inner_lip_gap(
        np.zeros(face_model.num_id, np.float32), apply_style(own, a, closure, None)
    )
    moved = transferred_style(own, other)
    spread_own, closed_own, _ = stats(own)
    spread_other, _, _ = stats(other)
    spread_moved, closed_moved, _ = stats(moved)
    assert spread_own < spread_moved and spread_moved == pytest.approx(spread_other, rel=0.02)
    assert closed_moved > closed_own
    np.testing.assert_allclose(moved.rest_expression, own.rest_expression)  # at rest: their own mouth
    both = transferred_style(person(1.0, 0.3, True), other)  # closures close the own lips exactly
    np.testing.assert_allclose(both.closed_expression, person(1.0, 0.3, True).closed_expression, atol=1e-6)
    np.testing.assert_allclose(apply_style(moved, a, None, np.zeros(300))[0], own.rest_expression, atol=1e-6)
    with pytest.raises(NvpError, match="different"):
        transferred_style(own, PersonStyle(other.person_map, other.rest_expression, "mel", "1" * 64, {}))


def test_sealed_lips_touch_and_text_closures_seal_them():
    from nvp.person import OpeningStyle, apply_style

    rng = np.random.default_rng(3)
    gw = rng.normal(size=K).astype(np.float32)
    direction = (gw / (gw @ gw)).astype(np.float32)  # direction @ gap_weights = 1
    opening = OpeningStyle(gw, 0.05, direction, 1.0, 0.0, 0.0, "0")
    closed = (0.02 * direction + rng.normal(0, 0.1, K)).astype(np.float32)
    closed -= ((closed @ gw + 0.05 - 0.02) * direction).astype(np.float32)  # opening 0.02: a little apart
    style = dataclasses.replace(_style(), closed_expression=closed, opening=opening)
    assert opening.opening_of(closed[None])[0] == pytest.approx(0.02, abs=1e-5)
    assert opening.opening_of(style.sealed_lips()[None])[0] == pytest.approx(0.0, abs=1e-5)
    audio_exp = rng.normal(size=(3, 32)).astype(np.float32)
    out = apply_style(
        style, audio_exp, None, None, opening=np.zeros(3, np.float32), text_closure=np.array([0, 1, 0])
    )
    np.testing.assert_allclose(out[1], style.sealed_lips(), atol=1e-5)
    free = apply_style(style, audio_exp, None, None, opening=np.zeros(3, np.float32))
    np.testing.assert_allclose(out[[0, 2]], free[[0, 2]])
