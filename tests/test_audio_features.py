"""Speech features: shapes and rates, alignment to video frames, silence/clipping, chunking, file input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import soundfile as sf

from nvp import audio_features
from nvp.audio_features import (
    MEL_BANDS,
    MEL_POWER_FLOOR,
    MEL_RATE,
    PHONEME_DIM,
    PHONEME_LOG_FLOOR,
    PHONEME_RATE,
    PHONETIC_DIM,
    SAMPLE_RATE,
    AudioFeatures,
    _phoneme_chunks,
    extract_features,
    features_from_file,
    mel_filterbank,
    phoneme_labels,
    recogniser_features,
    speaker_normalized,
)
from nvp.errors import MediaError, NvpError
from nvp.windows import frame_windows

SR = SAMPLE_RATE


def speechlike(seconds: float, sr: int = SR, level: float = 0.3, seed: int = 0) -> np.ndarray:
    """Vowel-like test signal: a gliding-pitch harmonic tone with formant-weighted partials, chopped into
    syllables of 120-250 ms by a smooth envelope, with a little noise for consonants."""
    rng = np.random.default_rng(seed)
    n = int(round(seconds * sr))
    t = np.arange(n) / sr
    f0 = 120 + 30 * np.sin(2 * np.pi * 0.7 * t) + 15 * np.sin(2 * np.pi * 2.3 * t)
    phase = 2 * np.pi * np.cumsum(f0) / sr
    formants = np.array([700.0, 1200.0, 2600.0])
    x = np.zeros(n)
    for h in range(1, 30):
        f = h * f0
        amp = sum(np.exp(-(((f - fm) / 150.0) ** 2)) for fm in formants) + 0.05
        x += amp * np.sin(h * phase) / h
    env = np.zeros(n)
    pos = 0
    while pos < n:
        syl = int(rng.uniform(0.12, 0.25) * sr)
        gap = int(rng.uniform(0.03, 0.12) * sr)
        end = min(n, pos + syl)
        env[pos:end] = np.sin(np.linspace(0, np.pi, end - pos))
        pos = end + gap
    x = x * env + 0.02 * rng.standard_normal(n) * env
    return (level * x / np.abs(x).max()).astype(np.float32)


def babble(seconds: float, sr: int = SR, seed: int = 0) -> np.ndarray:
    """Syllable-like test signal that hama hears as phones (about 10 % non-blank frames): noise-burst
    consonants followed by 100-220 ms vowels (harmonics of a falling 100-160 Hz pitch weighted by the
    formants of one of six vowels), short gaps and occasional 0.3-0.5 s pauses."""
    rng = np.random.default_rng(seed)
    n = int(round(seconds * sr))
    x = np.zeros(n)
    vowels = [(730, 1090, 2440), (270, 2290, 3010), (300, 870, 2240), (530, 1840, 2480), (660, 1720, 2410)]
    pos = int(0.2 * sr)
    while pos < n - sr // 2:
        c = int(rng.uniform(0.04, 0.09) * sr)
        burst = rng.standard_normal(c + 1) * 0.15
        if rng.random() < 0.5:
            burst = np.diff(burst) * 2  # high-passed: fricative-like
        x[pos : pos + c] += burst[:c] * np.hanning(c)
        pos += c
        length = int(rng.uniform(0.10, 0.22) * sr)
        t = np.arange(length) / sr
        f0 = rng.uniform(100, 160) * (1 - 0.15 * t / t[-1])
        phase = 2 * np.pi * np.cumsum(f0) / sr
        formants = vowels[rng.integers(len(vowels))]
        v = np.zeros(length)
        for h in range(1, 40):
            f = h * f0
            amp = sum(
                g * np.exp(-(((f - fm) / (60 + 0.05 * fm)) ** 2))
                for fm, g in zip(formants, (1, 0.6, 0.3), strict=True)
            )
            v += (amp + 0.01) * np.sin(h * phase)
        x[pos : pos + length] += 0.3 * v / np.abs(v).max() * np.hanning(length) ** 0.5
        pos += length + int(rng.uniform(0.0, 0.1) * sr if rng.random() < 0.8 else rng.uniform(0.3, 0.5) * sr)
    return (0.5 * x / np.abs(x).max()).astype(np.float32)


# ------------------------------------------------------------------------------------ shapes and rates


def test_clean_16k_audio_is_used_as_it_is_other_audio_is_copied_and_cleaned():
    from nvp.audio_features import prepare_audio

    clean = speechlike(1.0)
    assert prepare_audio(clean, SR) is clean  # no copy of what the dub already holds (an hour: 230 MB)
    dirty = clean.copy()
    dirty[[10, 20, 30]] = [np.nan, 2.0, -np.inf]
    out = prepare_audio(dirty, SR)
    assert out is not dirty and np.isnan(dirty[10]) and dirty[20] == 2.0  # the caller's audio untouched
    assert list(out[[10, 20, 30]]) == [0.0, 1.0, -1.0] and np.array_equal(out[:10], clean[:10])
    assert prepare_audio(clean.astype(np.float64), SR).dtype == np.float32


def test_mel_shapes_and_rate():
    audio = speechlike(1.0)
    f = extract_features(audio, SR, kind="mel")
    assert f.kind == "mel" and f.rate == MEL_RATE == 100.0
    assert f.values.shape == (SR // 160 + 1, MEL_BANDS) and f.values.dtype == np.float32
    assert f.duration_s == pytest.approx(1.0)
    assert np.isfinite(f.values).all() and f.values.min() >= math.log(MEL_POWER_FLOOR) - 1e-5
    np.testing.assert_allclose(f.times()[:3], [0.0, 0.01, 0.02])


def test_mel_filterbank_covers_every_band():
    fb = mel_filterbank()
    assert fb.shape == (80, 257)
    assert (fb.sum(axis=1) > 0).all()  # no empty band at the low end


def test_phoneme_shapes_and_rate():
    audio = babble(1.0)
    f = extract_features(audio, SR, kind="phonemes")
    assert f.kind == "phonemes" and f.rate == PHONEME_RATE == 50.0
    assert f.values.shape == (SR // 320 + 1, PHONEME_DIM) == (51, 191) and f.values.dtype == np.float32
    assert np.isfinite(f.values).all()
    assert f.values.min() >= PHONEME_LOG_FLOOR and f.values.max() <= 1e-5
    np.testing.assert_allclose(np.exp(f.values).sum(axis=1), 1.0, atol=1e-3)
    labels = phoneme_labels()
    assert len(labels) == PHONEME_DIM and labels[-1] == "<blank>"


def test_phonetic_features_come_from_the_same_pass():
    """The recogniser's hidden features: same frames as the posteriors, one pass gives both, and they
    describe the sound (not constant over a syllable-like signal)."""
    audio = babble(1.0)
    post, phon = recogniser_features(audio, SR)
    assert phon.kind == "phonetic" and phon.rate == post.rate == PHONEME_RATE
    assert phon.values.shape == (SR // 320 + 1, PHONETIC_DIM) and phon.values.dtype == np.float32
    np.testing.assert_array_equal(post.values, extract_features(audio, SR, kind="phonemes").values)
    np.testing.assert_array_equal(phon.values, extract_features(audio, SR, kind="phonetic").values)
    assert np.isfinite(phon.values).all() and phon.values.std(0).mean() > 0.1


def test_other_sample_rate_is_resampled():
    f = extract_features(speechlike(1.5, sr=22050), 22050, kind="mel")
    assert f.duration_s == pytest.approx(1.5, abs=1e-4)
    assert f.values.shape == (24000 // 160 + 1, MEL_BANDS)


@pytest.mark.parametrize(
    ("audio", "sr", "kind"),
    [
        (np.zeros((2, 100), np.float32), SR, "mel"),
        (np.zeros(0, np.float32), SR, "mel"),
        (np.zeros(100, np.int16), SR, "mel"),
        (np.zeros(100, np.float32), 0, "mel"),
        (np.zeros(100, np.float32), SR, "deepspeech"),
    ],
)
def test_bad_input_raises(audio, sr, kind):
    with pytest.raises(NvpError, match="expected|must be"):
        extract_features(audio, sr, kind=kind)


def test_audio_features_validates():
    with pytest.raises(NvpError, match="float32"):
        AudioFeatures(np.zeros((3, 2)), 50.0, "mel", 0.06)
    with pytest.raises(NvpError, match="2-D"):
        AudioFeatures(np.zeros(3, np.float32), 50.0, "mel", 0.06)
    with pytest.raises(NvpError, match="rate"):
        AudioFeatures(np.zeros((3, 2), np.float32), 0.0, "mel", 0.06)


# ------------------------------------------------------------------------------ silence and clipping


def test_silence_is_finite():
    silence = np.zeros(SR, np.float32)
    mel = extract_features(silence, SR, kind="mel").values
    np.testing.assert_allclose(mel, math.log(MEL_POWER_FLOOR), rtol=1e-6)
    ph = extract_features(silence, SR, kind="phonemes").values
    assert np.isfinite(ph).all()


def test_clipped_and_nan_input():
    audio = 3.0 * speechlike(1.0, level=1.0)  # peaks at 3: heavily clipped
    with_nan = audio.copy()
    with_nan[100:200] = np.nan
    for kind in ["mel", "phonemes"]:
        f = extract_features(audio, SR, kind=kind)
        ref = extract_features(np.clip(audio, -1, 1), SR, kind=kind)
        assert np.isfinite(f.values).all()
        np.testing.assert_array_equal(f.values, ref.values)
    assert np.isfinite(extract_features(with_nan, SR, kind="mel").values).all()


# ------------------------------------------------------------------------------------------- chunking


def test_mel_chunked_equals_whole_70s():
    audio = np.tile(speechlike(7.0, seed=3), 10)
    audio[: SR // 2] = 0  # silence at the start too
    chunked = extract_features(audio, SR, kind="mel")  # 30 s chunks
    odd = extract_features(audio, SR, kind="mel", chunk_s=7.37)  # seams off the hop grid
    whole = extract_features(audio, SR, kind="mel", chunk_s=1000.0)
    assert whole.values.shape == (70 * SR // 160 + 1, MEL_BANDS)
    np.testing.assert_allclose(chunked.values, whole.values, atol=1e-4)
    np.testing.assert_allclose(odd.values, whole.values, atol=1e-4)


@pytest.mark.parametrize("n", [1401, 1500, 2316, 2999, 5000, 30001])
def test_phoneme_chunk_plan(n):
    chunk, overlap = 1400, 200
    ranges = _phoneme_chunks(n, chunk, overlap)
    assert ranges[0][0] == 0 and ranges[-1][1] == n
    for (a0, a1), (b0, _) in zip(ranges, ranges[1:], strict=False):
        assert a1 - a0 <= chunk and b0 > a0
        assert a1 - b0 >= overlap  # enough overlap to cross-fade
    for (_, a1), (c0, _) in zip(ranges, ranges[2:], strict=False):
        assert a1 <= c0  # never three chunks on one frame


def test_chunk_assembly_is_exact_for_a_local_recognizer(monkeypatch):
    """With a stand-in recogniser whose frames depend only on their own 320 samples, chunked phoneme
    extraction (overlaps, cross-fades) must reproduce the single pass exactly."""

    def fake(audio: np.ndarray) -> np.ndarray:
        n = len(audio) // 320 + 1
        padded = np.zeros(n * 320, np.float32)
        padded[: len(audio)] = audio
        energy = (padded.reshape(n, 320) ** 2).mean(axis=1, keepdims=True)
        logits = np.log(energy + 1e-6) * np.linspace(0.0, 1.0, PHONEME_DIM)[None, :]
        logp = (logits - np.log(np.exp(logits).sum(axis=1, keepdims=True))).astype(np.float32)
        return logp, logp[:, :PHONETIC_DIM] * 0.5 + 1.0

    monkeypatch.setattr(audio_features, "_recognizer", lambda: fake)
    audio = np.tile(speechlike(7.0, seed=3), 10)  # 70 s
    whole, whole_hidden = audio_features._extract_phonemes(audio, chunk_s=1000.0)  # one pass (no limit)
    for chunk_s in [28.0, 5.3]:
        chunked = extract_features(audio, SR, kind="phonemes", chunk_s=chunk_s)
        assert chunked.values.shape == (70 * SR // 320 + 1, PHONEME_DIM)
        np.testing.assert_allclose(chunked.values, whole, atol=1e-4)
        phonetic = extract_features(audio, SR, kind="phonetic", chunk_s=chunk_s)
        assert phonetic.values.shape == (70 * SR // 320 + 1, PHONETIC_DIM)
        np.testing.assert_allclose(phonetic.values, whole_hidden, atol=1e-4)


def test_phonemes_chunked_close_to_whole():
    """hama attends over its whole input, so chunking changes posteriors slightly (module docstring)."""
    audio = babble(12.0, seed=5)
    whole = extract_features(audio, SR, kind="phonemes")  # one 12 s pass
    chunked = extract_features(audio, SR, kind="phonemes", chunk_s=5.0)
    assert chunked.values.shape == whole.values.shape == (12 * SR // 320 + 1, PHONEME_DIM)
    assert (whole.values.argmax(1) != 190).mean() > 0.05  # not all blank: the test is not trivial
    p_whole, p_chunked = np.exp(whole.values), np.exp(chunked.values)
    np.testing.assert_allclose(p_chunked.sum(axis=1), 1.0, atol=1e-3)
    assert (whole.values.argmax(1) == chunked.values.argmax(1)).mean() > 0.85
    assert np.abs(p_whole - p_chunked).sum(axis=1).mean() < 0.3


def test_phoneme_model_matches_hamas_engine():
    """nvp.phoneme_model runs hama's weights in PyTorch; hama's own native engine is the reference."""
    from hama import ASRModel, _engine

    if not _engine.available():
        pytest.skip("hama's native engine is not available on this platform")
    audio = babble(8.0, seed=11)
    session = ASRModel().session
    ref, lengths = session.run(
        ["log_probs", "out_lengths"], {"waveform": audio[None], "waveform_lengths": np.array([len(audio)])}
    )
    ref = np.maximum(ref[0, : int(np.asarray(lengths).reshape(-1)[0])], -30.0)
    ours = extract_features(audio, SR, kind="phonemes").values
    assert ours.shape == ref.shape == (len(audio) // 320 + 1, PHONEME_DIM)
    assert (ref.argmax(1) != 190).mean() > 0.05  # not all blank
    assert (ours.argmax(1) == ref.argmax(1)).mean() > 0.995
    assert np.abs(np.exp(ours) - np.exp(ref)).max() < 0.02


def test_phonemes_of_very_short_audio():
    for n in (1, 150, 200, 201, 319, 320):
        assert extract_features(np.full(n, 0.1, np.float32), SR).values.shape == (n // 320 + 1, PHONEME_DIM)


def test_phoneme_model_rejects_foreign_and_damaged_archives(tmp_path):
    from nvp.phoneme_model import hama_archive, load_phoneme_model

    bad = tmp_path / "x.hama"
    bad.write_bytes(b"PK\x03\x04 not a hama archive")
    with pytest.raises(NvpError, match="not a hama weights archive"):
        load_phoneme_model(bad)
    bad.write_bytes(hama_archive().read_bytes()[:5000])  # truncated
    with pytest.raises(NvpError, match="damaged hama weights archive"):
        load_phoneme_model(bad)


# ---------------------------------------------------------------------------------------------- files


def test_features_from_stereo_44k_wav(tmp_path):
    sr = 44100
    left = speechlike(1.5, sr=sr)
    stereo = np.stack([left, np.zeros_like(left)], axis=1)
    path = tmp_path / "stereo.wav"
    sf.write(path, stereo, sr, subtype="PCM_16")
    f = features_from_file(path, kind="mel")
    assert f.rate == MEL_RATE and f.values.shape[1] == MEL_BANDS
    assert f.duration_s == pytest.approx(1.5, abs=0.01)
    assert abs(f.values.shape[0] - (int(1.5 * SR) // 160 + 1)) <= 1
    ref = extract_features(left / 2, sr, kind="mel")  # mono mix of (left, silence)
    n = min(len(ref.values), len(f.values))
    loud = ref.values[:n] > -10  # compare where there is signal
    assert np.median(np.abs(f.values[:n][loud] - ref.values[:n][loud])) < 0.1
    w = frame_windows(f, 25.0)
    assert w.shape == (38, 16, MEL_BANDS)


def test_features_from_missing_file(tmp_path):
    with pytest.raises(MediaError):
        features_from_file(tmp_path / "nope.wav", kind="mel")


def test_speaker_normalisation_removes_a_channel_gain_and_keeps_silence_low():
    rng = np.random.default_rng(0)
    voice = (0.1 * rng.standard_normal(16000)).astype(np.float32)
    audio = np.concatenate([voice, np.zeros(16000, np.float32)])
    base = speaker_normalized(extract_features(audio, 16000, kind="mel"))
    louder = speaker_normalized(extract_features(0.5 * audio, 16000, kind="mel"))
    speech = slice(5, 95)  # frames of the noise burst (away from its edges)
    np.testing.assert_allclose(louder.values[speech], base.values[speech], atol=1e-3)
    assert abs(float(base.values[speech].mean())) < 0.1  # speech is centred
    assert base.values[120:190].mean() < base.values[speech].mean() - 5  # silence stays far below speech


def test_speaker_normalisation_leaves_phoneme_posteriors_alone():
    f = AudioFeatures(values=np.full((10, 191), -3.0, np.float32), rate=50.0, kind="phonemes", duration_s=0.2)
    assert speaker_normalized(f) is f
