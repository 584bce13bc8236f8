"""Lip rounding: the recogniser's rounded-vowel share, the person's rounding learned from their footage, and
its use in every prediction path."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from test_audio2exp import fake_sample

from nvp.audio2exp import Audio2ExpConfig, Audio2ExpressionNet, PersonMap
from nvp.audio_features import phoneme_labels
from nvp.person import PersonStyle, apply_style, rounding_tap, style_from_sample, transferred_style
from nvp.rounding import ROUNDED_PHONES, rounded_classes, rounded_share, rounding_direction

D = len(phoneme_labels())


def posterior_windows(share: np.ndarray, window: int = 16) -> np.ndarray:
    """``(T, window, D)`` log-posteriors whose rows give the rounded phones together probability
    ``share[t]`` (spread evenly over them) and the rest to the first other class."""
    rounded = rounded_classes()
    other = next(i for i in range(D) if i not in set(rounded))
    p = np.full((len(share), window, D), 1e-12)
    p[..., rounded] = (np.asarray(share)[:, None, None] / len(rounded)).clip(1e-12)
    p[..., other] = (1 - np.asarray(share))[:, None].clip(1e-12)
    return np.log(p).astype(np.float32)


def test_the_rounded_share_reads_the_rounded_phones_at_the_frame():
    assert len(rounded_classes()) == len(set(ROUNDED_PHONES) & set(phoneme_labels())) >= 15
    share = np.array([0.0, 0.3, 1.0, 0.55])
    np.testing.assert_allclose(rounded_share(posterior_windows(share)), share, atol=1e-5)
    with pytest.raises(ValueError, match="log-posteriors"):
        rounded_share(np.zeros((3, 16, 12), np.float32))


def test_the_rounding_direction_is_recovered_and_leaves_the_opening_alone():
    rng = np.random.default_rng(0)
    k = 20
    share = rng.uniform(0, 1, 400)
    true = rng.normal(size=k)
    opening = rng.normal(size=k)  # the gap's linear weights
    residual = (share - 0.3)[:, None] * true + 0.05 * rng.normal(size=(400, k))
    direction, mean = rounding_direction(residual, share)
    assert mean == pytest.approx(share.mean())
    np.testing.assert_allclose(direction, true, atol=0.03)
    kept, _ = rounding_direction(residual, share, opening)
    assert abs(kept @ opening) < 1e-5 * np.abs(opening).sum()
    np.testing.assert_allclose(kept, true - (true @ opening) / (opening @ opening) * opening, atol=0.03)
    assert rounding_direction(residual, np.full(400, 0.2)) is None  # no rounded vowel heard


def _rounding_style(k: int = 16) -> PersonStyle:
    rng = np.random.default_rng(1)
    pm = PersonMap(rng.normal(size=(k, 8)).astype(np.float32), np.zeros(k, np.float32))
    style = PersonStyle(pm, np.zeros(k, np.float32), "phonemes", "0" * 64, {})
    return dataclasses.replace(style, rounding=rng.normal(size=k).astype(np.float32), rounding_mean=0.25)


def test_a_rounding_style_moves_the_mouth_by_its_share_and_round_trips(tmp_path):
    style = _rounding_style()
    a = np.random.default_rng(2).normal(size=(5, 8)).astype(np.float32)
    share = np.array([0.25, 1.0, 0.0, 0.5, 0.25], np.float32)
    with pytest.raises(ValueError, match="rounded-vowel share"):
        apply_style(style, a, None, None)
    plain = apply_style(dataclasses.replace(style, rounding=None), a, None, None)
    out = apply_style(style, a, None, None, rounded=share)
    np.testing.assert_allclose(out - plain, (share - 0.25)[:, None] * style.rounding, atol=1e-5)
    back = PersonStyle.load(style.save(tmp_path / "s.npz"))
    np.testing.assert_array_equal(back.rounding, style.rounding)
    assert back.rounding_mean == 0.25
    # style transfer: the other person's rounding, as their opening and closures
    own = dataclasses.replace(style, rounding=None)
    assert transferred_style(own, style).rounding is style.rounding


def test_the_share_read_block_by_block_equals_the_whole_file():
    style = _rounding_style()
    share = np.random.default_rng(3).uniform(size=23)
    windows = posterior_windows(share)
    shares: list[np.ndarray] = []
    passed = list(rounding_tap(style, (windows[i : i + 5] for i in range(0, 23, 5)), shares))
    assert sum(len(b) for b in passed) == 23
    np.testing.assert_allclose(np.concatenate(shares), rounded_share(windows), atol=1e-6)
    none: list[np.ndarray] = []  # features that are not the recogniser's: no share to read
    list(rounding_tap(dataclasses.replace(style, rounding=None, feature_kind="mel"), [windows], none))
    assert none == []


def test_rounded_vowels_keep_the_lips_apart_where_the_opening_model_would_close_them():
    """The opening model's output is low on o / u; where its closing level would close the lips, a rounded
    vowel keeps them apart by ROUNDED_APART, while the text's p / b / m still seal them."""
    from nvp.person import ROUNDED_APART, OpeningStyle

    rng = np.random.default_rng(4)
    k = 16
    gw = rng.normal(size=k).astype(np.float32)
    direction = (gw / (gw @ gw)).astype(np.float32)
    opening = OpeningStyle(gw, 0.0, direction, 1.0, 0.0, 0.0, "0", closed_below=0.0)
    closed = rng.normal(size=k).astype(np.float32)
    style = dataclasses.replace(_rounding_style(k), rounding=None, closed_expression=closed, opening=opening)
    a = rng.normal(size=(4, 8)).astype(np.float32)
    z = np.full(4, -1.0, np.float32)  # far below the closing level: full blend to the closed mouth
    share = np.array([0.0, 1 / ROUNDED_APART, 0.25 / ROUNDED_APART, 1.0], np.float32)
    free = apply_style(dataclasses.replace(style, closed_expression=None), a, None, None, opening=z)
    out = apply_style(style, a, None, None, opening=z, rounded=share)
    kept = 1 - np.clip(ROUNDED_APART * share, 0, 1)  # the blend left: 1, 0, 0.75, 0
    np.testing.assert_allclose(out, free + kept[:, None] * (closed - free), atol=1e-5)
    text = apply_style(style, a, None, None, opening=z, rounded=share, text_closure=np.ones(4))
    np.testing.assert_allclose(text, np.broadcast_to(style.sealed_lips(), (4, k)), atol=1e-5)


def test_a_person_whose_lips_round_on_rounded_vowels_gets_their_rounding(face_model):
    """Synthetic footage: the person's mouth narrows along one coefficient exactly as much as the recogniser
    hears rounded vowels; the person map barely sees it (a random network's outputs), the fitted rounding
    must, and predicted mouths narrow on rounded vowels as the footage does."""
    torch.manual_seed(0)
    s = fake_sample(face_model, "r", 0, frames=300, dim=D)
    ident = s.tracked.identity
    eye = np.eye(face_model.num_exp, dtype=np.float32)
    base_width = face_model.mouth_width(ident, 0 * eye[:1])[0]
    narrows = int(np.argmin(face_model.mouth_width(ident, eye) - base_width))  # the most narrowing one
    share = np.clip(np.sin(np.arange(300) * 0.31), 0, 1)
    windows = posterior_windows(share)
    expression = s.expression.copy()
    expression[:, narrows] += 2.0 * share
    tracked = dataclasses.replace(s.tracked, expression=expression)
    sample = dataclasses.replace(s, windows=windows, tracked=tracked)
    net = Audio2ExpressionNet(Audio2ExpConfig(feature_dim=D)).eval()
    manifest = {"feature_kind": "phonemes", "sha256": "0" * 64}
    style = style_from_sample(net, manifest, sample, face_model)
    assert style.rounding is not None
    # the person map explains a little of it through the network's outputs, which read the same posteriors
    assert 1.6 <= style.rounding[narrows] <= 2.2
    a = np.zeros((2, net.cfg.audio_exp_dim), np.float32)
    wide, round_ = apply_style(style, a, None, None, rounded=np.array([0.0, 1.0], np.float32))
    w = face_model.mouth_width(ident, np.stack([wide, round_]))
    real = face_model.mouth_width(ident, (eye[narrows] * np.array([[0.0], [2.0]])).astype(np.float32))
    assert 0.8 <= (w[0] - w[1]) / (real[0] - real[1]) <= 1.1
    # a network that does not read the recogniser's classes gets no rounding
    mel = dataclasses.replace(s, windows=s.windows[..., :12])
    assert (
        style_from_sample(
            Audio2ExpressionNet(Audio2ExpConfig(feature_dim=12)).eval(), manifest, mel, face_model
        ).rounding
        is None
    )


def test_a_transcripts_rounded_vowels_round_the_lips_where_they_are_aligned(monkeypatch):
    """``nvp dub --transcript`` / ``nvp say``: frames the text's rounded vowels are aligned to get a rounded
    share of 1 (the audio's share elsewhere): the mouth moves along the person's rounding there, and only
    there."""
    import nvp.transcript as transcript
    from nvp.app.demo_voice import speech_script, synth_voice
    from nvp.person import predict_expressions

    net = Audio2ExpressionNet(Audio2ExpConfig(feature_dim=D)).eval()
    rng = np.random.default_rng(5)
    pm = PersonMap(rng.normal(size=(16, net.cfg.audio_exp_dim)).astype(np.float32), np.zeros(16, np.float32))
    style = dataclasses.replace(_rounding_style(), person_map=pm)
    audio = synth_voice(speech_script(2.0, rng), 2.0, rng)  # voiced, so the mouth is not at rest
    aligned = transcript.PhonemeAlignment(
        ("b", "u", "t"), np.array([0.5, 1.0, 1.5]), np.array([0.6, 1.2, 1.6])
    )
    monkeypatch.setattr(transcript, "align_transcript", lambda *a, **k: aligned)
    plain = predict_expressions(audio, 16000, 25.0, style, net)
    text = predict_expressions(audio, 16000, 25.0, style, net, transcript=("boot", "en-us"))
    moved = np.flatnonzero(np.abs(text - plain).max(1) > 1e-6)
    assert set(moved) <= set(range(23, 30)) and len(moved) >= 4  # u: 1.0-1.2 s from 0.94 s: frames 23-29
    d = (text - plain)[moved]  # along the rounding, never against it
    coeff = d @ style.rounding / (style.rounding @ style.rounding)
    np.testing.assert_allclose(d, coeff[:, None] * style.rounding, atol=1e-5)
    assert np.all(coeff > 0)
