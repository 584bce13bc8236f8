"""hama's phoneme recogniser (waveform → 191 phone log-posteriors at 50 Hz) as a PyTorch module.

The ``hama`` wheel (Apache-2.0) ships the weights (``hama/assets/asr_waveform.hama``) and runs them in its
own single-threaded native engine at about 8× real time on a 2-core machine. This module reads the same
weights from the installed package at run time and runs the network in PyTorch (about 100× real time on
one thread). Checked against hama's engine on the 81 speech clips of ../shared/data/audio (42 816 frames):
the same most likely phone on every frame, mean absolute difference of probabilities 2e-8 (the engine
rounds the log-mel to float16, so float32 summation-order noise moves about 1e-4 of the log-mel values by
one float16 step). ``tests/test_audio_features.py`` repeats the check on synthetic speech.

Architecture (from the archive's tensor names and shapes and the engine's outputs):

* front end: reflect-pad 200 samples, STFT with the archive's windowed DFT kernels (400-sample window,
  hop 160, 201 bins), power spectrum, the archive's 80-band mel filterbank, ``log(max(mel, 1e-10))``
  rounded to float16, no normalisation;
* subsampling: conv1d 80 → 144, kernel 3, stride 2, padding 1, then GELU (the engine uses
  ``sqrt(2) = 1.4140625``, float16-rounded);
* 4 Conformer blocks (width 144, 4 heads, feed-forward 576, depthwise kernel 31, no positional
  encoding): ``x += FFN(x) / 2; x += MHSA(LN(x)); x += Conv(x); x += FFN(x) / 2; x = LN(x)`` with
  FFN = LN → Linear → SiLU → Linear and Conv = LN → pointwise 288 → GLU → depthwise (batch norm folded
  into its weights) → SiLU → pointwise 144;
* output: 1×1 conv 144 → 191, log-softmax.

Output frames: ``len(audio) // 320 + 1``. Attention is global and unmasked, so a frame's posteriors depend
on the whole input (never pad to batch).
"""

from __future__ import annotations

import importlib.util
import struct
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from nvp.errors import NvpError

N_FFT = 400
HOP = 160
WIDTH = 144
HEADS = 4
BLOCKS = 4
CONV_KERNEL = 31
LOG_FLOOR = 1e-10
GELU_SQRT2 = 1.4140625
_DTYPES = {0: np.float32, 1: np.float16}
_POINTWISE = ("conv.pointwise1", "conv.pointwise2")


def hama_archive() -> Path:
    """Path of ``asr_waveform.hama`` in the installed hama package (found without importing hama)."""
    spec = importlib.util.find_spec("hama")
    if spec is None or not spec.submodule_search_locations:
        raise NvpError("phoneme features need the 'hama' package (pip install hama==1.7.0)")
    path = Path(next(iter(spec.submodule_search_locations))) / "assets" / "asr_waveform.hama"
    if not path.is_file():
        raise NvpError(f"hama's phoneme model is missing: {path} does not exist")
    return path


def read_archive(path: Path) -> dict[str, np.ndarray]:
    """Every tensor of a ``.hama`` archive by name (float32 or float16).

    Layout, little endian: ``b"HAMAPK"``, u8 version, u8 flags, u32 count; per tensor u16 name length,
    the name, u8 dtype (0 float32, 1 float16), u8 ndim, u32 dims, u64 offset, u64 size in bytes; the data
    section starts at the next multiple of 16 after the header, offsets are relative to it.
    """
    buf = Path(path).read_bytes()
    if buf[:6] != b"HAMAPK":
        raise NvpError(f"{path}: not a hama weights archive")
    try:
        return _tensors(buf)
    except (struct.error, IndexError, KeyError, ValueError, UnicodeDecodeError) as exc:
        raise NvpError(f"{path}: damaged hama weights archive ({exc})") from exc


def _tensors(buf: bytes) -> dict[str, np.ndarray]:
    (count,) = struct.unpack_from("<I", buf, 8)
    pos, entries = 12, []
    for _ in range(count):
        (n,) = struct.unpack_from("<H", buf, pos)
        name = buf[pos + 2 : pos + 2 + n].decode()
        dtype, ndim = _DTYPES[buf[pos + 2 + n]], buf[pos + 3 + n]
        pos += 4 + n
        shape = struct.unpack_from(f"<{ndim}I", buf, pos)
        offset, size = struct.unpack_from("<QQ", buf, pos + 4 * ndim)
        pos += 4 * ndim + 16
        entries.append((name, dtype, shape, offset, size))
    base = (pos + 15) // 16 * 16
    return {
        name: np.frombuffer(buf, dtype, size // np.dtype(dtype).itemsize, base + offset).reshape(shape).copy()
        for name, dtype, shape, offset, size in entries
    }


class _FeedForward(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(WIDTH)
        self.fc1 = nn.Linear(WIDTH, 4 * WIDTH)
        self.fc2 = nn.Linear(4 * WIDTH, WIDTH)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.silu(self.fc1(self.norm(x))))


class _SelfAttention(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(WIDTH)
        self.in_proj = nn.Linear(WIDTH, 3 * WIDTH)
        self.out_proj = nn.Linear(WIDTH, WIDTH)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, t, _ = x.shape
        qkv = self.in_proj(self.norm(x)).view(b, t, 3, HEADS, WIDTH // HEADS).permute(2, 0, 3, 1, 4)
        y = F.scaled_dot_product_attention(qkv[0], qkv[1], qkv[2])
        return self.out_proj(y.transpose(1, 2).reshape(b, t, WIDTH))


class _ConvModule(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(WIDTH)
        self.pointwise1 = nn.Conv1d(WIDTH, 2 * WIDTH, 1)
        self.depthwise = nn.Conv1d(WIDTH, WIDTH, CONV_KERNEL, padding=CONV_KERNEL // 2, groups=WIDTH)
        self.pointwise2 = nn.Conv1d(WIDTH, WIDTH, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.glu(self.pointwise1(self.norm(x).transpose(1, 2)), dim=1)
        return self.pointwise2(F.silu(self.depthwise(y))).transpose(1, 2)


class _ConformerBlock(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.ffn1, self.attn = _FeedForward(), _SelfAttention()
        self.conv, self.ffn2 = _ConvModule(), _FeedForward()
        self.norm = nn.LayerNorm(WIDTH)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + 0.5 * self.ffn1(x)
        x = x + self.attn(x)
        x = x + self.conv(x)
        return self.norm(x + 0.5 * self.ffn2(x))


class PhonemeModel(nn.Module):
    """``forward(wav (B, S) float32 at 16 kHz) → (B, S // 320 + 1, 191)`` log-posteriors (``outputs``: also
    a hidden layer's features)."""

    def __init__(self, mels: int = 80, classes: int = 191) -> None:
        super().__init__()
        bins = N_FFT // 2 + 1
        self.register_buffer("dft", torch.zeros(2 * bins, 1, N_FFT))  # real rows, then imaginary
        self.register_buffer("mel_fb", torch.zeros(bins, mels))
        self.stem = nn.Conv1d(mels, WIDTH, 3, stride=2, padding=1)
        self.blocks = nn.ModuleList(_ConformerBlock() for _ in range(BLOCKS))
        self.proj = nn.Conv1d(WIDTH, classes, 1)

    def log_mel(self, wav: torch.Tensor) -> torch.Tensor:
        """``(B, S) → (B, 80, S // 160 + 1)``."""
        spec = F.conv1d(F.pad(wav[:, None], (N_FFT // 2, N_FFT // 2), mode="reflect"), self.dft, stride=HOP)
        re, im = spec.chunk(2, dim=1)
        mel = (re * re + im * im).transpose(1, 2) @ self.mel_fb
        return torch.log(mel.clamp_min(LOG_FLOOR)).half().float().transpose(1, 2)

    def forward(self, wav: torch.Tensor) -> torch.Tensor:
        return self.outputs(wav)[0]

    def outputs(self, wav: torch.Tensor, hidden_block: int = BLOCKS) -> tuple[torch.Tensor, torch.Tensor]:
        """Log-posteriors ``(B, T, 191)`` and the hidden features ``(B, T, 144)`` after conformer block
        ``hidden_block`` (1 … 4) of one pass."""
        x = self.stem(self.log_mel(wav))
        x = (0.5 * x * (1.0 + torch.erf(x / GELU_SQRT2))).transpose(1, 2)
        hidden = x
        for i, block in enumerate(self.blocks, 1):
            x = block(x)
            if i == hidden_block:
                hidden = x
        return F.log_softmax(self.proj(x.transpose(1, 2)).transpose(1, 2), dim=-1), hidden


def load_phoneme_model(path: Path | None = None) -> PhonemeModel:
    """The model with the weights of a ``.hama`` archive (default: hama's packaged one), in eval mode."""
    path = path or hama_archive()
    w = {k: torch.from_numpy(v.astype(np.float32)) for k, v in read_archive(path).items()}
    pre = "acoustic_model.model."
    try:
        model = PhonemeModel(w["mel_fb"].shape[1], w[pre + "proj.bias"].shape[0])
        state = {
            "dft": torch.cat([w["stft_real_kernel"], w["stft_imag_kernel"]]),
            "mel_fb": w["mel_fb"],
            "stem.weight": w["onnx::Conv_801"],
            "stem.bias": w["onnx::Conv_802"],
            "proj.weight": w[pre + "proj.weight"],
            "proj.bias": w[pre + "proj.bias"],
        }
        # the ONNX export left some tensors unnamed; they are numbered in block order: per block six
        # matmul weights stored (in, out), and the depthwise conv's weight and bias (batch norm folded in);
        # the first two numbered convs are the stem
        matmuls = sorted((int(k.rsplit("_", 1)[1]), k) for k in w if k.startswith("onnx::MatMul_"))
        convs = sorted((int(k.rsplit("_", 1)[1]), k) for k in w if k.startswith("onnx::Conv_"))[2:]
        if len(matmuls) != 6 * BLOCKS or len(convs) != 2 * BLOCKS:
            raise KeyError("numbered tensors")
        linear = [
            ("ffn1.fc1", "ffn1.fc1.bias"),
            ("ffn1.fc2", "ffn1.fc2.bias"),
            ("attn.in_proj", "attn.in_proj_bias"),
            ("attn.out_proj", "attn.out_proj.bias"),
            ("ffn2.fc1", "ffn2.fc1.bias"),
            ("ffn2.fc2", "ffn2.fc2.bias"),
        ]
        for i in range(BLOCKS):
            b, s = f"blocks.{i}.", f"{pre}blocks.{i}."
            for (dst, bias), (_, key) in zip(linear, matmuls[6 * i : 6 * i + 6], strict=True):
                state[b + dst + ".weight"] = w[key].T
                state[b + dst + ".bias"] = w[s + bias]
            for dst in ("ffn1.norm", "ffn2.norm", "conv.norm", "norm", "attn.norm", *_POINTWISE):
                src = "attn_norm" if dst == "attn.norm" else dst
                state[b + dst + ".weight"] = w[s + src + ".weight"]
                state[b + dst + ".bias"] = w[s + src + ".bias"]
            state[b + "conv.depthwise.weight"] = w[convs[2 * i][1]]
            state[b + "conv.depthwise.bias"] = w[convs[2 * i + 1][1]]
        model.load_state_dict(state, strict=True)
    except (KeyError, RuntimeError) as exc:
        raise NvpError(
            f"{path}: unexpected layout of hama's phoneme model ({exc}); nvp expects hama 1.7.0"
        ) from exc
    return model.eval()
