"""Copies of a training clip's speech as other voices, rooms and microphones would give it (training
augmentation for the opening model and the network; issue 44).

An augmentation is named by a kind and an amount, e.g. ``speed1.1``, ``room0.5``, ``noise10``:

- ``speedF``: the audio played ``F`` times as fast (resampled: pitch and formants scale by ``F``, as a
  higher or lower voice with a shorter or longer vocal tract; the standard "speed perturbation" of speech
  recognition). The clip's frames play ``F`` times as fast with it, so each frame keeps its own sound: the
  features are read at ``F`` times the frame rate and the targets are unchanged.
- ``roomT``: the audio in a reverberant room of reverberation time ``T`` seconds (a synthetic impulse
  response: the direct sound and an exponentially decaying diffuse tail, 60 dB down after ``T``).
- ``noiseS``: white noise at ``S`` dB below the speech's active level (:func:`nvp.vad.with_white_noise`).

Every copy is reproducible from its seed. Pure functions on mono float waveforms.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

from nvp.errors import NvpError

KINDS = ("speed", "room", "noise")
_NAME = re.compile(r"^(speed|room|noise)(\d+(?:\.\d+)?)$")


@dataclass(frozen=True)
class Augmentation:
    kind: str
    amount: float

    @property
    def name(self) -> str:
        return f"{self.kind}{self.amount:g}"

    @property
    def time_scale(self) -> float:
        """How many times as fast the copy plays (the clip's frame rate is multiplied by it)."""
        return self.amount if self.kind == "speed" else 1.0

    def apply(self, audio: np.ndarray, rate: int, seed: int) -> np.ndarray:
        """``(S',)`` float32: the copy of mono ``audio`` (``rate`` Hz; ``S' = S / time_scale``)."""
        if self.kind == "speed":
            return speed_perturbed(audio, self.amount)
        if self.kind == "room":
            return reverberant(audio, rate, self.amount, seed)
        from nvp.vad import with_white_noise

        return with_white_noise(audio, rate, self.amount, seed)


def parse_augmentation(name: str) -> Augmentation:
    """``"speed1.1"`` → ``Augmentation("speed", 1.1)``; one clear error for anything else."""
    m = _NAME.match(name.strip())
    if not m:
        raise NvpError(f"unknown augmentation '{name}': expected speedF (e.g. speed0.9), roomT (seconds, "
                       "e.g. room0.5) or noiseS (dB, e.g. noise10)")  # fmt: skip
    a = Augmentation(m.group(1), float(m.group(2)))
    if a.kind == "speed" and not 0.5 <= a.amount <= 2.0:
        raise NvpError(f"augmentation '{name}': the speed must be within 0.5-2")
    if a.kind == "room" and not 0.05 <= a.amount <= 3.0:
        raise NvpError(f"augmentation '{name}': the reverberation time must be within 0.05-3 s")
    return a


def speed_perturbed(audio: np.ndarray, factor: float) -> np.ndarray:
    """``audio`` played ``factor`` times as fast: resampled by ``1 / factor`` (polyphase, anti-aliased),
    then heard at the original rate."""
    from scipy.signal import resample_poly

    f = Fraction(factor).limit_denominator(100)
    out = resample_poly(np.asarray(audio, np.float64), f.denominator, f.numerator)
    return np.clip(out, -1.0, 1.0).astype(np.float32)


def room_impulse_response(
    rate: int, rt60_s: float, seed: int, direct_to_reverb_db: float = 3.0
) -> np.ndarray:
    """``(N,)`` a synthetic room's impulse response: a unit direct sound, then from 2.5 ms a diffuse tail of
    Gaussian noise decaying by 60 dB over ``rt60_s`` (Sabine's exponential decay), its energy
    ``direct_to_reverb_db`` below the direct sound's, cut 60 dB down."""
    n = int(rt60_s * rate)
    t = np.arange(n) / rate
    tail = np.random.default_rng(seed).standard_normal(n) * 10 ** (-3 * t / rt60_s)
    tail[: int(0.0025 * rate)] = 0.0
    tail *= np.sqrt(10 ** (-direct_to_reverb_db / 10) / max(float(np.sum(tail**2)), 1e-12))
    tail[0] = 1.0
    return tail


def reverberant(audio: np.ndarray, rate: int, rt60_s: float, seed: int) -> np.ndarray:
    """``audio`` as heard in a room (:func:`room_impulse_response`), same length and same RMS level."""
    from scipy.signal import fftconvolve

    x = np.asarray(audio, np.float64)
    y = fftconvolve(x, room_impulse_response(rate, rt60_s, seed))[: len(x)]
    y *= np.sqrt(np.mean(x**2) / max(float(np.mean(y**2)), 1e-20))
    return np.clip(y, -1.0, 1.0).astype(np.float32)
