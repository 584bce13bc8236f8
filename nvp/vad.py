"""Voice activity: is there speech in a recording, and how much of each video frame's audio is voice."""

from __future__ import annotations

import math

import numpy as np

from nvp.audio_features import SAMPLE_RATE, prepare_audio
from nvp.errors import NvpError
from nvp.windows import num_video_frames

SPEECH_THRESHOLD_DB = -45.0
"""RMS level in dBFS above which a 20 ms block counts as active. On the real speech clips in
``../shared/data/audio`` the 90th-percentile block level is between -35 and -7 dBFS and pauses sit between
-120 and -45 dBFS (a few noisy recordings have a floor near -30 dBFS, which is still 'active')."""
SPEECH_MIN_ACTIVE_S = 0.2
"""Total active duration in seconds needed for :func:`speech_activity` to report speech."""


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


def speech_activity(
    audio: np.ndarray,
    sample_rate: int,
    threshold_db: float = SPEECH_THRESHOLD_DB,
    min_active_s: float = SPEECH_MIN_ACTIVE_S,
) -> bool:
    """Whether audio contains speech-like energy: at least ``min_active_s`` seconds of 20 ms blocks whose
    RMS level (:func:`rms_envelope_db`) exceeds ``threshold_db`` dBFS (default -45).

    This is an energy test, not a voice detector: silence, digital zeros, dither and quiet room tone
    give False; speech, but also music or loud noise, give True.
    """
    block_s = 0.02
    env = rms_envelope_db(audio, sample_rate, block_s)
    needed = max(1, int(math.ceil(min_active_s / block_s - 1e-9)))
    active = int(np.count_nonzero(env > threshold_db))
    if len(env) < needed:  # shorter than min_active_s: all of it must be active
        return active == len(env)
    return active >= needed


VOICE_THRESHOLD_DB = -50.0
"""Absolute RMS level in dBFS below which a video frame is never voiced (:func:`voice_activity`)."""
VOICE_RAMP_DB = 6.0
"""Half-width in dB of the soft ramp of :func:`voice_activity` around its threshold."""
VOICE_RELATIVE_DB = 45.0
"""A frame counts as voiced only within this many dB of the file's loud end (95th percentile), so a
recording with a high noise floor still has pauses."""
VOICE_HOLD_S = 0.2
"""Voice activity is held this long before and after every voiced frame: lips move before the sound
starts and close after it ends, and pauses shorter than about twice this (breaths between phrases, when
speakers often keep the mouth open) are left to the network. A compromise measured with
``scripts/eval_audio2exp.py``: on held-out real videos, holds of 0.12 / 0.2 / 0.3 s lowered the correlation
of predicted and tracked mouth opening by 0.18 / 0.05 / 0.01 (real speakers often keep the mouth open in
short pauses); on 87 other voices they raised the correlation of mouth opening and loudness from 0.07
(no gate) to 0.36 / 0.27 / 0.19."""


def voice_activity(
    audio: np.ndarray, sample_rate: int, fps: float, num_frames: int | None = None
) -> np.ndarray:
    """``(T,)`` float32 in [0, 1]: how much each video frame's audio is voice (1) or silence (0).

    Per video frame (at ``i / fps`` s), the RMS level of the 40 ms around it (:func:`rms_envelope_db` on
    20 ms blocks) is compared with ``max(VOICE_THRESHOLD_DB, p95 - VOICE_RELATIVE_DB)`` through a linear
    ramp of +-:data:`VOICE_RAMP_DB`; then held (running maximum over +-:data:`VOICE_HOLD_S`) and
    smoothed over 3 frames so that transitions take a few frames. ``T`` defaults to
    :func:`num_video_frames` of the audio duration.
    """
    wav = prepare_audio(audio, sample_rate)
    t_count = num_video_frames(len(wav) / SAMPLE_RATE, fps) if num_frames is None else int(num_frames)
    if t_count == 0:
        return np.zeros(0, np.float32)
    block_s = 0.02
    env = rms_envelope_db(wav, SAMPLE_RATE, block_s)
    centres = (np.arange(len(env)) + 0.5) * block_s
    times = np.arange(t_count) / fps
    # level of the ~40 ms around each frame: the louder of the two nearest blocks
    idx = np.clip(np.searchsorted(centres, times), 0, len(env) - 1)
    level = np.maximum(env[idx], env[np.maximum(idx - 1, 0)])
    threshold = max(VOICE_THRESHOLD_DB, float(np.percentile(env, 95)) - VOICE_RELATIVE_DB)
    act = np.clip((level - threshold) / (2 * VOICE_RAMP_DB) + 0.5, 0.0, 1.0)
    hold = int(round(VOICE_HOLD_S * fps))
    if hold:
        padded = np.pad(act, hold, mode="edge")
        act = np.lib.stride_tricks.sliding_window_view(padded, 2 * hold + 1).max(1)
    act = np.convolve(np.pad(act, 1, mode="edge"), np.ones(3) / 3, mode="valid")
    return act.astype(np.float32)
