"""The demo's synthetic voice and the speech rhythm it shares with the demo clip's mouth.

``SpeechScript`` is a continuous mouth-opening signal (syllables at 3–6 Hz, closed-mouth pauses);
``synth_voice`` turns it into a voiced, vowel-like sound whose loudness follows the mouth, so the demo clip's
picture and sound match without any recorded speech.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

AUDIO_RATE = 16000
"""Sample rate of the demo audio, Hz."""


def smoothstep(x: np.ndarray) -> np.ndarray:
    """Cubic ease ``3x² - 2x³`` of ``x`` clipped to [0, 1]."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


@dataclass(frozen=True)
class SpeechScript:
    """Continuous mouth-opening signal as knots of a monotone cubic (values in [0, 1])."""

    times: np.ndarray
    values: np.ndarray
    pitch_offsets: np.ndarray  # per knot: relative intonation (for the voice), ~[-1, 1]
    vowel: np.ndarray  # per knot: second-formant position in [0, 1] (front/back vowel)

    def __call__(self, t: np.ndarray) -> np.ndarray:
        from scipy.interpolate import PchipInterpolator

        v = PchipInterpolator(self.times, self.values, extrapolate=False)(np.asarray(t, float))
        return np.clip(np.nan_to_num(v, nan=0.0), 0.0, 1.0)

    def knot_signal(self, values: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Another per-knot quantity, interpolated smoothly the same way."""
        from scipy.interpolate import PchipInterpolator

        return PchipInterpolator(self.times, values, extrapolate=True)(
            np.clip(t, self.times[0], self.times[-1])
        )


def speech_script(seconds: float, rng: np.random.Generator) -> SpeechScript:
    """Random phrases of syllables (3–6 syllables/s) separated by closed-mouth pauses.

    Every clip starts with a short pause. Each syllable opens the mouth to a random amplitude; between
    syllables the mouth nearly or fully closes (bilabial consonants close it completely).
    """
    times = [0.0]
    values = [0.0]
    t = float(rng.uniform(0.25, 0.45))  # initial pause
    end = seconds + 0.5
    while t < end:
        times.append(t)
        values.append(0.0)
        phrase_end = t + rng.uniform(0.9, 2.2)
        while t < phrase_end:
            dur = 1.0 / rng.uniform(3.0, 6.0)
            amp = rng.uniform(0.3, 1.0)
            times.append(t + dur * rng.uniform(0.4, 0.6))
            values.append(amp)
            t += dur
            closed = rng.random() < 0.3
            times.append(t)
            values.append(0.0 if closed else amp * rng.uniform(0.05, 0.35))
        values[-1] = 0.0  # phrase ends closed
        t += rng.uniform(0.25, 0.7)  # pause
    times_arr = np.asarray(times)
    n = len(times_arr)
    return SpeechScript(
        times=times_arr,
        values=np.asarray(values),
        pitch_offsets=rng.uniform(-1.0, 1.0, n),
        vowel=rng.uniform(0.0, 1.0, n),
    )


def speech_opening(seconds: float, fps: float, seed: int = 0) -> np.ndarray:
    """The normalised mouth-opening signal (``[0, 1]``) of the demo clip, sampled at ``fps`` frames/s."""
    s = speech_script(seconds, np.random.default_rng(seed))
    return s(np.arange(round(seconds * fps)) / fps)


def _resonator(x: np.ndarray, freq: np.ndarray, bw: float, rate: int, block: int) -> np.ndarray:
    """Second-order resonator (unit gain at DC) with a centre frequency that changes every ``block``
    samples; the filter state is carried across blocks."""
    from scipy.signal import lfilter

    out = np.empty_like(x)
    zi = np.zeros(2)
    r = np.exp(-np.pi * bw / rate)
    for start in range(0, len(x), block):
        f = float(freq[start])
        c = 2.0 * r * np.cos(2.0 * np.pi * f / rate)
        a = [1.0, -c, r * r]
        b = [1.0 - c + r * r]
        out[start : start + block], zi = lfilter(b, a, x[start : start + block], zi=zi)
    return out


def synth_voice(
    speech: SpeechScript, seconds: float, rng: np.random.Generator, rate: int = AUDIO_RATE
) -> np.ndarray:
    """A voiced, vowel-like sound whose loudness follows the mouth opening (silent when it is closed).

    A Rosenberg glottal pulse train around 120 Hz (intonation + jitter) is differentiated (lip radiation)
    and passed through three formant resonators; the first formant rises with the opening, the second
    moves between back and front vowels. Returns float32 mono in [-1, 1], ``round(seconds * rate)`` samples.
    """
    n = round(seconds * rate)
    t = np.arange(n) / rate
    opening = speech(t)
    pitch = speech.knot_signal(speech.pitch_offsets, t)
    f0 = 120.0 * (1.0 + 0.06 * pitch + 0.05 * opening) * (1.0 + 0.004 * rng.standard_normal(n))
    phase = np.cumsum(f0 / rate) % 1.0
    open_q, close_q = 0.4, 0.16  # Rosenberg pulse: opening and closing phase fractions
    flow = np.where(
        phase < open_q,
        0.5 * (1.0 - np.cos(np.pi * phase / open_q)),
        np.where(phase < open_q + close_q, np.cos(0.5 * np.pi * (phase - open_q) / close_q), 0.0),
    )
    source = np.diff(flow, prepend=0.0) + 0.002 * rng.standard_normal(n)  # + a little aspiration
    f1 = 300.0 + 500.0 * opening
    f2 = 900.0 + 1300.0 * np.clip(speech.knot_signal(speech.vowel, t), 0.0, 1.0)
    f3 = np.full(n, 2600.0)
    block = rate // 200
    y = source
    for freq, bw in ((f1, 90.0), (f2, 110.0), (f3, 160.0)):
        y = _resonator(y, freq, bw, rate, block)
    envelope = np.clip(opening / 0.15, 0.0, 1.0) ** 0.8 * (0.4 + 0.6 * opening)
    y = y * envelope
    peak = float(np.max(np.abs(y))) if n else 0.0
    if peak > 0:
        y = y * (0.7 / peak)
    return y.astype(np.float32)
