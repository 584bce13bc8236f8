"""Voice activity (nvp.vad): speech against silence, noise and music; timing per video frame; the model."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from nvp import vad
from nvp.errors import NvpError
from nvp.vad import (
    VOICE_LEAD_S,
    activity_from_probability,
    energy_voice_activity,
    rms_envelope_db,
    speech_activity,
    speech_probability,
    voice_activity,
)

SR = 16000
FPS = 25.0


def voice(seconds: float, seed: int = 0, rate: int = SR) -> np.ndarray:
    """Synthetic voiced speech: the demo's glottal-pulse voice through formants, phrases of 3-6 syllables
    per second with short pauses (it starts with 0.25-0.45 s of silence), 0.7 peak."""
    from nvp.app.demo_voice import speech_script, synth_voice

    rng = np.random.default_rng(seed)
    return synth_voice(speech_script(seconds, rng), seconds, rng, rate)


def voiced_span(x: np.ndarray) -> tuple[float, float]:
    """First and last audible sample of ``x``, in seconds."""
    on = np.flatnonzero(np.abs(x) > 1e-3 * np.abs(x).max())
    return on[0] / SR, on[-1] / SR


def music(seconds: float) -> np.ndarray:
    """Piano-like notes (six harmonics, exponential decay) of a pentatonic melody, at -20 dBFS."""
    rng = np.random.default_rng(3)
    notes = []
    for _ in range(int(seconds / 0.25)):
        f = 220.0 * 2 ** (rng.choice([0, 2, 4, 7, 9, 12]) / 12)
        t = np.arange(SR // 4) / SR
        notes.append(sum(0.6**k * np.sin(2 * np.pi * f * (k + 1) * t) for k in range(6)) * np.exp(-4 * t))
    x = np.concatenate(notes)
    return (0.1 * x / np.sqrt(np.mean(x**2))).astype(np.float32)


def noise(seconds: float, rms: float = 0.05, seed: int = 1) -> np.ndarray:
    return (rms * np.random.default_rng(seed).standard_normal(int(seconds * SR))).astype(np.float32)


# ------------------------------------------------------------------------------ speech or not


def test_voiced_sound_is_speech_and_noise_music_silence_are_not():
    assert speech_activity(voice(1.5), SR)
    assert speech_activity(0.01 * voice(1.5), SR)  # quiet: peaks at -43 dBFS
    assert not speech_activity(np.zeros(SR, np.float32), SR)
    assert not speech_activity(noise(2.0, 1e-4), SR)  # room tone, -80 dBFS
    assert not speech_activity(noise(2.0, 0.1), SR)  # loud white noise, -20 dBFS
    assert not speech_activity(music(2.0), SR)
    tone = (0.3 * np.sin(2 * np.pi * 200 * np.arange(SR) / SR)).astype(np.float32)
    assert not speech_activity(tone, SR)


def test_the_old_loudness_gate_took_noise_and_music_for_voice():
    """The baseline kept for evaluations: this is what the detector fixes."""
    assert energy_voice_activity(noise(2.0, 0.1), SR, FPS).min() == 1.0
    assert energy_voice_activity(music(2.0), SR, FPS).mean() > 0.9
    assert voice_activity(noise(2.0, 0.1), SR, FPS).max() == 0.0
    assert voice_activity(music(2.0), SR, FPS).mean() < 0.1


def test_speech_in_noise_is_still_speech():
    v = voice(2.0)
    noisy = v + noise(2.0, rms=float(np.sqrt(np.mean(v**2))) / np.sqrt(10))  # 10 dB SNR
    assert speech_activity(noisy, SR)
    assert voice_activity(noisy, SR, FPS)[int(voiced_span(v)[0] * FPS) :].mean() > 0.6


def test_speech_activity_needs_enough_speech():
    gap = np.zeros(SR, np.float32)
    v = voice(1.5)
    start, _ = voiced_span(v)
    burst = v[int(start * SR) : int((start + 0.1) * SR)]
    assert not speech_activity(np.concatenate([gap, burst, gap]), SR)
    assert speech_activity(np.concatenate([gap, v, gap]), SR)


def test_probability_shape_range_and_rate():
    p = speech_probability(voice(1.0, rate=44100), 44100)  # resampled to 16 kHz first
    assert p.shape == (int(np.ceil(SR / vad.CHUNK)),) and p.dtype == np.float32
    assert 0.0 <= p.min() and p.max() <= 1.0
    assert vad.VAD_RATE == pytest.approx(31.25)


def test_long_audio_in_blocks_equals_one_batch(monkeypatch):
    """The LSTM state is carried across the convolution batches."""
    audio = np.concatenate([voice(1.0), np.zeros(SR // 2, np.float32), voice(1.0, seed=1)])
    whole = speech_probability(audio, SR)
    monkeypatch.setattr(vad, "_BATCH_CHUNKS", 7)
    np.testing.assert_allclose(speech_probability(audio, SR), whole, atol=1e-5)


# ----------------------------------------------------------------------------- per video frame


def test_voice_activity_follows_speech_and_closes_within_0_2_s():
    silence = np.zeros(SR, np.float32)
    speech = voice(2.0)
    audio = np.concatenate([silence, speech, silence, silence])  # 5 s
    start, end = (1.0 + t for t in voiced_span(speech))
    v = voice_activity(audio, SR, FPS)
    assert v.shape == (125,) and v.dtype == np.float32
    assert 0.0 <= v.min() and v.max() <= 1.0
    assert v[: int((start - VOICE_LEAD_S) * FPS) - 1].max() == 0.0  # silence before: mouth at rest
    assert v[int((start - 0.08) * FPS)] > 0  # lips start moving before the sound
    assert v[int(start * FPS) + 2 : int(end * FPS)].mean() > 0.8  # speech (with its short pauses)
    assert v[int(np.ceil((end + 0.2) * FPS)) :].max() < 0.05  # closed within 0.2 s of the end
    assert voice_activity(np.zeros(8000, np.float32), SR, 30.0).max() == 0.0
    assert voice_activity(audio, SR, FPS, num_frames=7).shape == (7,)
    assert voice_activity(audio, SR, FPS, num_frames=140)[125:].max() == 0.0  # past the end: silence


def test_activity_from_probability_lead_and_smoothing():
    p = np.zeros(40)
    p[20:30] = 0.95
    act = activity_from_probability(p, FPS)
    lead = int(round(VOICE_LEAD_S * FPS))
    on = np.flatnonzero(act > 0)
    # ramp: 0.95 >= 0.8 gives 1; held `lead` frames early; the 3-frame mean adds one frame each side
    assert on[0] == 20 - lead - 1 and on[-1] == 30 - 1 + round(vad.VOICE_LAG_S * FPS) + 1
    assert act[20 - lead + 1 : 29].min() == pytest.approx(1.0)
    assert act[20 - lead - 1] == pytest.approx(1 / 3)
    lo, hi = vad.VOICE_RAMP
    mid = activity_from_probability(np.full(10, (lo + hi) / 2), FPS)
    np.testing.assert_allclose(mid, 0.5, atol=1e-6)
    assert activity_from_probability(np.zeros(0), FPS).shape == (0,)


def test_per_frame_max_of_overlapping_chunks():
    p = np.array([0.1, 0.9, 0.2, 0.3, 0.0], np.float32)  # 4 per second
    # frames of 0.5 s: [0, 0.5) holds chunks 0-1, [0.5, 1) chunks 2-3, [1, 1.5) chunk 4, then none
    np.testing.assert_allclose(vad._per_frame_max(p, 4.0, 2.0, 4), [0.9, 0.3, 0.0, 0.0])
    # frames of 0.2 s against chunks of 0.25 s: frame 1 [0.2, 0.4) overlaps chunks 0 and 1
    np.testing.assert_allclose(vad._per_frame_max(p, 4.0, 5.0, 3), [0.1, 0.9, 0.9])


def test_rms_envelope_db_reference_levels():
    t = np.arange(SR) / SR
    sine = np.sin(2 * np.pi * 1000 * t).astype(np.float32)
    env = rms_envelope_db(sine, SR)
    assert env.shape == (50,)
    np.testing.assert_allclose(env, 10 * np.log10(0.5), atol=0.05)  # full-scale sine: -3 dBFS
    assert (rms_envelope_db(np.zeros(SR, np.float32), SR) == -120).all()


# -------------------------------------------------------------------------------- the model file


def test_nothing_is_loaded_at_import():
    code = "import sys, nvp.vad as v; print('torch' in sys.modules, v.load_silero.cache_info().currsize)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "0"]


def test_missing_package_gives_a_clear_error(monkeypatch):
    import importlib.util

    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    with pytest.raises(NvpError, match="silero-vad"):
        vad.silero_weights_path()


def test_damaged_or_foreign_weights_give_a_clear_error(tmp_path, monkeypatch):
    bad = tmp_path / "w.safetensors"
    bad.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{not json at all")
    with pytest.raises(NvpError, match="damaged"):
        vad.read_safetensors(bad)
    monkeypatch.setattr(vad, "silero_weights_path", lambda: bad)
    vad.load_silero.cache_clear()
    try:
        with pytest.raises(NvpError, match="sha256"):
            vad.load_silero()
    finally:
        vad.load_silero.cache_clear()
    with pytest.raises(NvpError, match="expected stft_conv.weight"):
        vad.silero_from_weights({})


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_matches_the_packages_torchscript_model():
    """The module here with the TorchScript file's weights gives that model's outputs, chunk by chunk."""
    import torch

    path = vad.silero_weights_path().with_name("silero_vad.jit")
    try:
        jit = torch.jit.load(str(path), map_location="cpu").eval()
    except Exception as exc:  # TorchScript may be gone from a future torch
        pytest.skip(f"TorchScript model does not load: {exc}")
    sd = {k: v.numpy() for k, v in jit.state_dict().items() if k.startswith("_model.")}
    w = {
        "stft_conv.weight": sd["_model.stft.forward_basis_buffer"],
        "final_conv.weight": sd["_model.decoder.decoder.2.weight"],
        "final_conv.bias": sd["_model.decoder.decoder.2.bias"],
    }
    for i in range(4):
        for k in ("weight", "bias"):
            w[f"conv{i + 1}.{k}"] = sd[f"_model.encoder.{i}.reparam_conv.{k}"]
    for k in ("weight_ih", "weight_hh", "bias_ih", "bias_hh"):
        w[f"lstm_cell.{k}"] = sd[f"_model.decoder.rnn.{k}"]
    audio = np.concatenate([voice(1.0), noise(0.5)])
    ours = vad._run_silero(vad.silero_from_weights(w), audio)
    pad = torch.from_numpy(np.pad(audio, (0, -len(audio) % vad.CHUNK)))
    with torch.no_grad():
        ref = [jit(pad[i : i + vad.CHUNK], SR)[0, 0].item() for i in range(0, len(pad), vad.CHUNK)]
    np.testing.assert_allclose(ours, ref, atol=2e-5)


def test_white_noise_is_mixed_at_the_asked_snr_and_reproducibly():
    from nvp.vad import with_white_noise

    rng = np.random.default_rng(0)
    sr = 16000
    speech = (0.1 * np.sin(2 * np.pi * 200 * np.arange(2 * sr) / sr)).astype(np.float32)
    speech[sr // 2 : sr] = 0  # a pause does not count towards the speech's level
    for snr in (20.0, 0.0):
        noisy = with_white_noise(speech, sr, snr, seed=3)
        noise = noisy.astype(np.float64) - speech
        active = np.mean(speech[speech != 0].astype(np.float64) ** 2)
        assert 10 * np.log10(active / np.mean(noise**2)) == pytest.approx(snr, abs=0.3)
        np.testing.assert_array_equal(noisy, with_white_noise(speech, sr, snr, seed=3))
    assert not np.array_equal(with_white_noise(speech, sr, 0, 3), with_white_noise(speech, sr, 0, 4))
    assert np.abs(with_white_noise(rng.uniform(-1, 1, sr), sr, -20, 1)).max() <= 1.0
