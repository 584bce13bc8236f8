"""Voice activity: is there speech in a recording, and how much of each video frame's audio is voice.

Speech is told apart from silence, noise and music by Silero VAD v6 (MIT licence; its weights ship inside
the ``silero-vad`` wheel as ``silero_vad/data/silero_vad_16k.safetensors``, 1.2 MB), run by the few lines
of PyTorch in :func:`speech_probability`, written here: nothing is downloaded and the ``silero_vad`` package
is never imported (its import sets torch's global thread count to 1). The network reads 16 kHz audio in
chunks of 512 samples (32 ms) with the 64 samples before each chunk as context:

* front end: the chunk plus context (576 samples) reflect-padded by 64 samples on the right, a strided
  convolution with the file's 258 STFT kernels (256 samples, hop 128: 4 frames), magnitude of the 129 bins;
* encoder: four conv1d + ReLU layers, 129 → 128 → 64 → 64 → 128 channels, kernel 3, strides 1, 2, 2, 1
  (one 128-d vector per chunk);
* decoder: an LSTM (128) carried across chunks, ReLU, 1×1 conv to one logit, sigmoid: the probability that
  the chunk is speech.

The convolutions of all chunks run as one batch and the LSTM runs over the whole sequence, about a
thousand times faster than real time on one core. Outputs match the package's TorchScript model run chunk
by chunk to 2e-5 when given its weights (``tests/test_vad.py`` checks this when the TorchScript file loads);
the safetensors weights used here are the package's own second copy for runtimes without TorchScript (mean
absolute difference of probabilities 0.02 on real speech).

The old loudness gate is kept as :func:`energy_voice_activity`, the baseline of evaluations.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import math
import struct
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from nvp.audio_features import SAMPLE_RATE, prepare_audio
from nvp.errors import NvpError
from nvp.windows import num_video_frames

SILERO_PACKAGE = "silero-vad==6.2.3"
"""The registry package that ships the voice-activity weights (a dependency of nvp)."""
SILERO_WEIGHTS = ("data", "silero_vad_16k.safetensors")
"""Path of the weights inside the installed ``silero_vad`` package folder."""
SILERO_SHA256 = "c59271c284ae9c8335d795d60e0bfdb71aaaceec578d9bd9ffc1b8153c319ea1"
"""sha256 of that file in silero-vad 6.2.3; any other file is refused with a clear error."""
CHUNK = 512
"""Samples per probability (32 ms at 16 kHz)."""
CONTEXT = 64
"""Samples before each chunk that the network also reads."""
VAD_RATE = SAMPLE_RATE / CHUNK
"""Speech probabilities per second (31.25 Hz)."""
_BATCH_CHUNKS = 1024
"""Chunks whose convolutions run as one batch (33 s of audio). The probabilities do not depend on it; 4096
(131 s) took about 100 MB while it ran, which glibc then kept (:mod:`nvp.allocator`), no faster."""

SPEECH_THRESHOLD = 0.5
"""Speech probability at or above which a 32 ms chunk is speech (Silero's own default)."""
SPEECH_MIN_ACTIVE_S = 0.2
"""Total speech in seconds needed for :func:`speech_activity` to report speech."""


# ----------------------------------------------------------------------------------------- the model


def silero_weights_path() -> Path:
    """Path of Silero's 16 kHz weights in the installed ``silero_vad`` package (found, not imported)."""
    spec = importlib.util.find_spec("silero_vad")
    if spec is None or not spec.submodule_search_locations:
        raise NvpError(
            f"voice activity needs the '{SILERO_PACKAGE.split('==')[0]}' package, which is not installed "
            f"(pip install {SILERO_PACKAGE}, or reinstall nvp)"
        )
    path = Path(next(iter(spec.submodule_search_locations))).joinpath(*SILERO_WEIGHTS)
    if not path.is_file():
        raise NvpError(
            f"the voice-activity model is missing: {path} does not exist (reinstall {SILERO_PACKAGE})"
        )
    return path


def read_safetensors(path: Path) -> dict[str, np.ndarray]:
    """Every float32 tensor of a ``.safetensors`` file by name.

    Layout: u64 little-endian header length ``n``, ``n`` bytes of JSON ``{name: {"dtype", "shape",
    "data_offsets": [begin, end]}}`` (plus an optional ``__metadata__``), then the data; offsets are
    relative to the start of the data.
    """
    buf = Path(path).read_bytes()
    try:
        (n,) = struct.unpack_from("<Q", buf, 0)
        header = json.loads(buf[8 : 8 + n])
        data = memoryview(buf)[8 + n :]
        out = {}
        for name, info in header.items():
            if name == "__metadata__":
                continue
            if info["dtype"] != "F32":
                raise ValueError(f"tensor {name} has dtype {info['dtype']}, expected F32")
            begin, end = info["data_offsets"]
            if not 0 <= begin <= end <= len(data):
                raise ValueError(f"tensor {name} lies outside the file")
            out[name] = np.frombuffer(data[begin:end], "<f4").reshape(info["shape"]).copy()
        return out
    except (struct.error, ValueError, KeyError, TypeError) as exc:
        raise NvpError(f"{path}: damaged voice-activity weights ({exc})") from exc


@dataclass(frozen=True)
class _Silero:
    """Silero VAD's tensors (torch) and the LSTM module that runs its decoder."""

    stft: Any  # (258, 1, 256) real and imaginary STFT kernels
    convs: tuple  # 4 x (weight, bias, stride)
    lstm: Any  # torch.nn.LSTM(128, 128)
    out_weight: Any  # (1, 128, 1)
    out_bias: Any  # (1,)


_SHAPES = {
    "stft_conv.weight": (258, 1, 256),
    "conv1.weight": (128, 129, 3),
    "conv2.weight": (64, 128, 3),
    "conv3.weight": (64, 64, 3),
    "conv4.weight": (128, 64, 3),
    "lstm_cell.weight_ih": (512, 128),
    "lstm_cell.weight_hh": (512, 128),
    "final_conv.weight": (1, 128, 1),
}


def silero_from_weights(w: dict[str, np.ndarray]) -> _Silero:
    """The runnable model from its tensors (names as in the package's safetensors file)."""
    import torch

    for name, shape in _SHAPES.items():
        if name not in w or tuple(w[name].shape) != shape:
            found = tuple(w[name].shape) if name in w else "nothing"
            raise NvpError(f"voice-activity weights: expected {name} of shape {shape}, found {found}")
    t = {k: torch.from_numpy(np.ascontiguousarray(v, np.float32)) for k, v in w.items()}
    lstm = torch.nn.LSTM(128, 128, batch_first=True)
    with torch.no_grad():
        for k in ("weight_ih", "weight_hh", "bias_ih", "bias_hh"):
            getattr(lstm, f"{k}_l0").copy_(t[f"lstm_cell.{k}"])
    lstm.eval().requires_grad_(False)
    convs = tuple(
        (t[f"conv{i}.weight"], t[f"conv{i}.bias"], s) for i, s in zip((1, 2, 3, 4), (1, 2, 2, 1), strict=True)
    )
    return _Silero(t["stft_conv.weight"], convs, lstm, t["final_conv.weight"], t["final_conv.bias"])


@lru_cache(maxsize=1)
def load_silero() -> _Silero:
    """Silero VAD from the installed package, loaded on first use and kept (checked against its sha256)."""
    path = silero_weights_path()
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    if digest != SILERO_SHA256:
        raise NvpError(
            f"{path}: expected the voice-activity weights of {SILERO_PACKAGE} "
            f"(sha256 {SILERO_SHA256[:12]}…), found a file with sha256 {digest[:12]}… "
            f"(reinstall {SILERO_PACKAGE})"
        )
    return silero_from_weights(read_safetensors(path))


def _run_silero(model: _Silero, wav: np.ndarray) -> np.ndarray:
    """``(ceil(S / CHUNK),)`` speech probabilities of 16 kHz audio ``(S,)`` (zero-padded to whole chunks)."""
    import torch
    import torch.nn.functional as F

    n = -(-len(wav) // CHUNK)
    probs, state = [], None
    threads = torch.get_num_threads()
    # the layers are small: one thread is several times faster than two (the LSTM steps 25x under load)
    torch.set_num_threads(1)
    try:
        with torch.no_grad():
            for c0 in range(0, n, _BATCH_CHUNKS):
                c1 = min(n, c0 + _BATCH_CHUNKS)
                # chunk k with its context: samples [k*CHUNK - CONTEXT, (k+1)*CHUNK) of the audio, 0 outside
                x = torch.from_numpy(_zero_padded(wav, c0 * CHUNK - CONTEXT, c1 * CHUNK))
                frames = x.unfold(0, CHUNK + CONTEXT, CHUNK)
                h = F.pad(frames[:, None], (0, CONTEXT), mode="reflect")
                spec = F.conv1d(h, model.stft, stride=128)
                h = torch.sqrt(spec[:, :129] ** 2 + spec[:, 129:] ** 2)
                for weight, bias, stride in model.convs:
                    h = torch.relu(F.conv1d(h, weight, bias, stride=stride, padding=1))
                seq, state = model.lstm(h[None, :, :, 0], state)  # (1, chunks, 128)
                logit = F.conv1d(torch.relu(seq[0])[:, :, None], model.out_weight, model.out_bias)
                probs.append(torch.sigmoid(logit[:, 0, 0]))
    finally:
        torch.set_num_threads(threads)
    return torch.cat(probs).numpy().astype(np.float32)


def _zero_padded(wav: np.ndarray, start: int, stop: int) -> np.ndarray:
    """``wav[start:stop]`` with zeros where it reaches outside ``wav`` (a batch's samples, never a padded
    copy of all of them)."""
    seg = np.zeros(stop - start, np.float32)
    lo, hi = max(start, 0), min(stop, len(wav))
    seg[lo - start : hi - start] = wav[lo:hi]
    return seg


def speech_probability(audio: np.ndarray, sample_rate: int) -> np.ndarray:
    """``(ceil(S16 / 512),)`` float32 in [0, 1]: probability that each 32 ms chunk of the audio is speech.

    ``audio`` is ``(S,)`` mono float samples at ``sample_rate`` Hz (resampled to 16 kHz: ``S16`` samples);
    chunk ``k`` covers ``[k, k + 1) * 0.032`` s (:data:`VAD_RATE` per second). Silence, steady noise and
    music score near 0, speech (also whispered, sung or synthetic) near 1.
    """
    return _run_silero(load_silero(), prepare_audio(audio, sample_rate))


def speech_activity(audio: np.ndarray, sample_rate: int, min_active_s: float = SPEECH_MIN_ACTIVE_S) -> bool:
    """Whether ``(S,)`` mono audio holds speech: at least ``min_active_s`` seconds of 32 ms chunks whose
    :func:`speech_probability` reaches :data:`SPEECH_THRESHOLD` (all of it, for shorter audio).

    Silence, room tone, white noise and music give False; speech, even quiet or noisy, gives True.
    """
    p = speech_probability(audio, sample_rate)
    return enough_speech(int(np.count_nonzero(p >= SPEECH_THRESHOLD)), len(p), min_active_s)


def enough_speech(active: int, chunks: int, min_active_s: float = SPEECH_MIN_ACTIVE_S) -> bool:
    """:func:`speech_activity` from its counts: ``active`` of ``chunks`` 32 ms chunks are speech."""
    return active >= min(max(1, int(math.ceil(min_active_s * VAD_RATE - 1e-9))), chunks)


# ----------------------------------------------------------------------------- per video frame

VOICE_RAMP = (0.5, 0.8)
"""Speech probabilities mapped linearly onto voice activity 0 … 1 (below: 0, above: 1). Chosen with
``scripts/eval/vad.py`` on the speech clips of ``../shared/data/audio`` (no test video): against (0.3, 0.7),
pauses cut into speech under white noise close within 0.2 s in 89 % instead of 74 % of cases at 10 dB SNR
and 66 % instead of 37 % at 0 dB (clean: 100 % both); speech frames with activity >= 0.5: 84.1 % vs 84.8 %."""
VOICE_LEAD_S = 0.12
"""Voice activity starts this long before the speech does: lips move (open, or close for a p, b or m)
before the sound."""
VOICE_LAG_S = 0.0
"""Voice activity is held this long after the speech probability falls. The detector's own decay (its
LSTM) is hold enough: with 0.04 s, pauses in white noise at 10 dB SNR closed within 0.2 s in 71 % instead of
89 % of cases; with 0 the mouth of clean speech is closed (activity < 0.05) within 0.2 s of its end in
every case measured."""


def frame_speech_probability(
    audio: np.ndarray, sample_rate: int, fps: float, num_frames: int | None = None
) -> np.ndarray:
    """``(T,)`` float32: the highest :func:`speech_probability` of the chunks overlapping each video frame
    (frame ``i`` spans ``[i, i + 1) / fps`` s). ``T`` defaults to :func:`num_video_frames` of the duration;
    frames past the end of the audio get 0."""
    wav = prepare_audio(audio, sample_rate)
    t_count = num_video_frames(len(wav) / SAMPLE_RATE, fps) if num_frames is None else int(num_frames)
    if t_count <= 0:
        return np.zeros(0, np.float32)
    p = _run_silero(load_silero(), wav)
    return _per_frame_max(p, VAD_RATE, fps, t_count)


def _per_frame_max(p: np.ndarray, rate: float, fps: float, t_count: int) -> np.ndarray:
    """``(T,)`` maximum of the values ``p`` (one per ``1 / rate`` s) overlapping each video frame
    ``[i, i + 1) / fps`` (0 where none does)."""
    i = np.arange(t_count)
    first = np.floor(i / fps * rate + 1e-9).astype(int)
    last = np.maximum(first, np.ceil((i + 1) / fps * rate - 1e-9).astype(int) - 1)
    out = np.zeros(t_count, np.float32)
    for k in range(int(last.max() - first.min()) + 1 if t_count else 0):
        j = first + k
        ok = (j <= last) & (j < len(p))
        out[ok] = np.maximum(out[ok], p[j[ok]])
    return out


def activity_from_probability(prob: np.ndarray, fps: float) -> np.ndarray:
    """``(T,)`` voice activity in [0, 1] from per-frame speech probabilities ``(T,)``: the linear ramp
    :data:`VOICE_RAMP`, held :data:`VOICE_LEAD_S` before and :data:`VOICE_LAG_S` after (running maximum),
    then smoothed over 3 frames."""
    lo, hi = VOICE_RAMP
    act = np.clip((np.asarray(prob, np.float64) - lo) / (hi - lo), 0.0, 1.0)
    if len(act) == 0:
        return act.astype(np.float32)
    lead, lag = int(round(VOICE_LEAD_S * fps)), int(round(VOICE_LAG_S * fps))
    if lead or lag:
        padded = np.pad(act, (lag, lead), mode="edge")
        act = np.lib.stride_tricks.sliding_window_view(padded, lag + lead + 1).max(1)
    act = np.convolve(np.pad(act, 1, mode="edge"), np.ones(3) / 3, mode="valid")
    return np.clip(act, 0.0, 1.0).astype(np.float32)


def voice_activity(
    audio: np.ndarray, sample_rate: int, fps: float, num_frames: int | None = None
) -> np.ndarray:
    """``(T,)`` float32 in [0, 1]: how much each video frame's audio is voice (1) or not (0).

    :func:`frame_speech_probability` through :func:`activity_from_probability`. Pauses, silence, noise
    and music give 0, so the mouth rests there; the activity rises :data:`VOICE_LEAD_S` before speech
    and is 0 again within 0.2 s after it. ``T`` defaults to :func:`num_video_frames` of the duration.
    """
    return activity_from_probability(frame_speech_probability(audio, sample_rate, fps, num_frames), fps)


# ------------------------------------------------------------------------- the old loudness gate

ENERGY_THRESHOLD_DB = -50.0
"""Absolute RMS level in dBFS below which :func:`energy_voice_activity` never calls a frame voiced."""
ENERGY_RAMP_DB = 6.0
"""Half-width in dB of the soft ramp of :func:`energy_voice_activity` around its threshold."""
ENERGY_RELATIVE_DB = 45.0
"""A frame is voiced only within this many dB of the file's loud end (95th percentile)."""
ENERGY_HOLD_S = 0.2
"""Activity of :func:`energy_voice_activity` is held this long before and after every loud frame."""


def rms_envelope_db(audio: np.ndarray, sample_rate: int, block_s: float = 0.02) -> np.ndarray:
    """``(S // B,)`` float32 RMS level in dBFS of consecutive non-overlapping blocks of ``block_s`` seconds.

    ``B = round(block_s * sample_rate)`` samples; each block's mean is removed first (DC offset), its
    level is ``10 log10(mean(x^2))`` with 0 dBFS = RMS 1.0 (a full-scale sine is -3 dBFS), floored at
    -120 dBFS. Audio is clipped to [-1, 1] and NaN set to 0 first; a trailing partial block is dropped
    (for audio shorter than one block, the whole audio is one block).
    """
    arr = np.asarray(audio)
    if arr.ndim != 1 or arr.size == 0:
        raise NvpError(f"expected non-empty mono audio of shape (S,), found shape {arr.shape}")
    b = max(1, int(round(block_s * sample_rate)))
    nblocks = max(1, len(arr) // b)
    out = np.empty(nblocks, dtype=np.float32)
    step = max(1, (1 << 20) // b)  # ~1M samples at a time
    for k0 in range(0, nblocks, step):
        k1 = min(nblocks, k0 + step)
        x = arr[k0 * b : k1 * b] if len(arr) >= b else arr
        x = np.clip(np.nan_to_num(x.astype(np.float64), nan=0.0), -1.0, 1.0).reshape(k1 - k0, -1)
        out[k0:k1] = 10.0 * np.log10(np.maximum(x.var(axis=1), 1e-12))
    return out


def energy_voice_activity(
    audio: np.ndarray, sample_rate: int, fps: float, num_frames: int | None = None
) -> np.ndarray:
    """``(T,)`` float32 in [0, 1]: the loudness gate nvp used before :func:`voice_activity` (a baseline).

    Per video frame, the RMS level of the 40 ms around it is compared with
    ``max(ENERGY_THRESHOLD_DB, p95 - ENERGY_RELATIVE_DB)`` through a ramp of +-:data:`ENERGY_RAMP_DB`,
    held +-:data:`ENERGY_HOLD_S` and smoothed over 3 frames. Loud noise and music count as voice.
    """
    wav = prepare_audio(audio, sample_rate)
    t_count = num_video_frames(len(wav) / SAMPLE_RATE, fps) if num_frames is None else int(num_frames)
    if t_count == 0:
        return np.zeros(0, np.float32)
    block_s = 0.02
    env = rms_envelope_db(wav, SAMPLE_RATE, block_s)
    centres = (np.arange(len(env)) + 0.5) * block_s
    times = np.arange(t_count) / fps
    idx = np.clip(np.searchsorted(centres, times), 0, len(env) - 1)
    level = np.maximum(env[idx], env[np.maximum(idx - 1, 0)])
    threshold = max(ENERGY_THRESHOLD_DB, float(np.percentile(env, 95)) - ENERGY_RELATIVE_DB)
    act = np.clip((level - threshold) / (2 * ENERGY_RAMP_DB) + 0.5, 0.0, 1.0)
    hold = int(round(ENERGY_HOLD_S * fps))
    if hold:
        padded = np.pad(act, hold, mode="edge")
        act = np.lib.stride_tricks.sliding_window_view(padded, 2 * hold + 1).max(1)
    act = np.convolve(np.pad(act, 1, mode="edge"), np.ones(3) / 3, mode="valid")
    return act.astype(np.float32)


def with_white_noise(audio: np.ndarray, sample_rate: int, snr_db: float, seed: int) -> np.ndarray:
    """``(S,)`` float32: mono ``audio`` with white Gaussian noise mixed in at ``snr_db`` dB below the speech's
    active level (mean power of the 20 ms blocks within 30 dB of the loud end, the 95th percentile of
    :func:`rms_envelope_db`), clipped to [-1, 1]; the noise is drawn from ``seed`` (reproducible)."""
    x = np.asarray(audio, np.float64)
    env = rms_envelope_db(x, sample_rate, 0.02)
    active = float(np.mean(10 ** (env[env > np.percentile(env, 95) - 30] / 10)))
    noise = np.random.default_rng(seed).standard_normal(len(x))
    noise *= np.sqrt(active / 10 ** (snr_db / 10) / np.mean(noise**2))
    return np.clip(x + noise, -1.0, 1.0).astype(np.float32)
