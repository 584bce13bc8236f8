"""The log-mel front end, a leaf: numpy/scipy only, no other project module.

Both ``"mel"`` features (:mod:`nvp.audio_features`) and Whisper's front end (:mod:`nvp.whisper_encoder`)
build on :func:`mel_filterbank`; it lives here so that neither of those modules imports the other (they
used to import each other).

Log-mel (D = 80, 100 frames/s): 25 ms periodic-Hann window (400 samples) zero-padded to a 512-point FFT,
10 ms hop (160 samples), frames centred at ``160 * j`` samples (the signal is zero-padded by 200 samples at
both ends, so there are ``S // 160 + 1`` frames), power spectrum ``|X|^2 / sum(window^2)``, 80 triangular
filters on the Slaney mel scale from 0 to 8 kHz with Slaney area normalisation, natural log of
``max(power, MEL_POWER_FLOOR)``.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

SAMPLE_RATE = 16000
"""Sample rate in Hz at which all features are computed."""
MEL_BANDS = 80
MEL_WIN = 400
"""Analysis window in samples (25 ms)."""
MEL_HOP = 160
"""Hop in samples (10 ms)."""
MEL_NFFT = 512
MEL_RATE = SAMPLE_RATE / MEL_HOP
"""Mel frames per second (100 Hz)."""
MEL_POWER_FLOOR = 1e-10
"""Power floor before the log: silence gives ``log(1e-10) = -23.03`` in every band."""
MEL_CHUNK_S = 30.0
"""Default chunk length in seconds for mel extraction (the result does not depend on it)."""


@lru_cache(maxsize=4)
def mel_filterbank(
    num_bands: int = MEL_BANDS,
    n_fft: int = MEL_NFFT,
    sample_rate: int = SAMPLE_RATE,
    fmax: float | None = None,
) -> np.ndarray:
    """``(num_bands, n_fft // 2 + 1)`` float32 triangular mel filters (Slaney scale and area norm).

    Slaney's scale is linear below 1 kHz (200/3 Hz per mel) and logarithmic above. Filter ``b`` rises from
    mel point ``b`` to ``b + 1`` and falls to ``b + 2`` (``num_bands + 2`` points evenly spaced from 0 Hz
    to ``fmax``, default Nyquist), and is scaled by ``2 / (f_{b+2} - f_b)`` so that each band measures a
    power density. The returned array is read-only.
    """
    fmax = sample_rate / 2 if fmax is None else fmax
    f_sp = 200.0 / 3
    min_log_hz = 1000.0
    min_log_mel = min_log_hz / f_sp
    logstep = math.log(6.4) / 27.0

    def hz_to_mel(f: np.ndarray) -> np.ndarray:
        f = np.asarray(f, dtype=np.float64)
        lin = f / f_sp
        log = min_log_mel + np.log(np.maximum(f, 1e-9) / min_log_hz) / logstep
        return np.where(f >= min_log_hz, log, lin)

    def mel_to_hz(m: np.ndarray) -> np.ndarray:
        m = np.asarray(m, dtype=np.float64)
        return np.where(m >= min_log_mel, min_log_hz * np.exp(logstep * (m - min_log_mel)), f_sp * m)

    edges = mel_to_hz(np.linspace(hz_to_mel(0.0), hz_to_mel(fmax), num_bands + 2))
    bins = np.linspace(0.0, sample_rate / 2, n_fft // 2 + 1)
    lower, centre, upper = edges[:-2, None], edges[1:-1, None], edges[2:, None]
    rising = (bins[None, :] - lower) / (centre - lower)
    falling = (upper - bins[None, :]) / (upper - centre)
    fb = np.maximum(0.0, np.minimum(rising, falling)) * (2.0 / (upper - lower))
    out = fb.astype(np.float32)
    out.setflags(write=False)
    return out


@lru_cache(maxsize=1)
def _mel_window() -> np.ndarray:
    n = np.arange(MEL_WIN)
    win = (0.5 - 0.5 * np.cos(2 * np.pi * n / MEL_WIN)).astype(np.float32)  # periodic Hann
    win.setflags(write=False)
    return win


def log_mel_frames(audio: np.ndarray, f0: int, f1: int) -> np.ndarray:
    """Log-mel frames ``f0 .. f1-1`` ``(f1 - f0, 80)`` of 16 kHz audio, as if zero-padded at both ends."""
    from scipy.fft import rfft

    half = MEL_WIN // 2
    s0 = f0 * MEL_HOP - half
    s1 = (f1 - 1) * MEL_HOP + half
    seg = np.zeros(s1 - s0, dtype=np.float32)
    a0, a1 = max(s0, 0), min(s1, len(audio))
    if a1 > a0:
        seg[a0 - s0 : a1 - s0] = audio[a0:a1]
    frames = np.lib.stride_tricks.sliding_window_view(seg, MEL_WIN)[::MEL_HOP]
    win = _mel_window()
    spec = rfft(frames * win, n=MEL_NFFT, axis=-1)
    power = (spec.real**2 + spec.imag**2) / np.float32(np.sum(win.astype(np.float64) ** 2))
    mel = power.astype(np.float32) @ mel_filterbank().T
    return np.log(np.maximum(mel, MEL_POWER_FLOOR)).astype(np.float32)


def extract_log_mel(audio: np.ndarray, chunk_s: float = MEL_CHUNK_S) -> np.ndarray:
    """``(S // 160 + 1, 80)`` log-mel frames of 16 kHz audio ``(S,)``, in chunks of ``chunk_s`` seconds
    (the result does not depend on them)."""
    n = len(audio) // MEL_HOP + 1
    step = max(1, int(round(chunk_s * MEL_RATE)))
    out = np.empty((n, MEL_BANDS), dtype=np.float32)
    for f0 in range(0, n, step):
        f1 = min(n, f0 + step)
        out[f0:f1] = log_mel_frames(audio, f0, f1)
    return out
