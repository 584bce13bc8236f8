"""The motion audio does not determine: a person's blinks and brows, learned from their footage and sampled
for new speech (exports and avatars, where no footage shows the upper face).

``nvp dub`` copies the eyes and brows from the footage. An animation made from audio alone (``nvp predict
--export``) has no footage: its upper face moved only as far as the audio model moves it (barely). As in
MeshTalk, where audio leaves the motion open it is sampled plausibly rather than left still: the person's own
blink (the expression change of their blinks), at their own rate, and their brows raised with the speech's
emphasis within the range their footage shows. Measured on the face model's mesh (detector landmark indices,
:attr:`nvp.face_model.FaceModel.landmark_vertices`), so footage and output are judged the same way.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

LIDS = ((159, 145, 33, 133), (386, 374, 362, 263))
"""Per eye: upper lid, lower lid, the two corners (mediapipe face-mesh landmarks)."""
BROWS = ((105, 33, 133), (334, 362, 263))
"""Per side: the brow's middle and the eye corners below it."""
BLINK_BELOW = 0.5
"""An eye counts as closed (a blink) when its openness is below this fraction of the person's median."""
OPEN_FROM = 0.8
"""Frames whose openness reaches this fraction of the median count as open eyes (a blink's reference)."""
AROUND = 6
"""Frames before and after a blink in which its open-eye reference is looked for: the half-closed frames
next to a blink are not it (with them, the learned blink closed the eyes a third less than the real ones)."""
PRIOR_BLINKS_PER_MIN = 17.0
"""Blinks per minute of people in conversation (about 15-25, Bentivoglio et al. 1997: 26 talking, 17 at
rest): the rate a person's own is pulled towards when their footage is short."""
PRIOR_MINUTES = 0.25
"""Footage minutes the prior rate weighs as: a 10 s clip with no blink gets 12/min, 2 minutes with 30 get
15.1/min."""
MIN_BLINK_GAP_S = 0.6
"""No two blinks closer than this."""
BROW_SMOOTH_S = 0.25
"""Brow motion follows the speech's loudness envelope smoothed over this long."""


def eye_openness(points: np.ndarray) -> np.ndarray:
    """``(T,)`` mean over both eyes of the lid gap over the eye's width, for landmarks ``(T, >=468, 2|3)``."""
    p = np.asarray(points, np.float64)
    out = []
    for up, lo, a, b in LIDS:
        out.append(np.linalg.norm(p[:, up] - p[:, lo], axis=-1) / np.linalg.norm(p[:, a] - p[:, b], axis=-1))
    return np.mean(out, 0)


def brow_height(points: np.ndarray) -> np.ndarray:
    """``(T,)`` mean over both sides of the brow middle's distance from its eye's corner line, over the
    distance between the outer eye corners (a raise is positive), for landmarks ``(T, >=468, 2|3)``."""
    p = np.asarray(points, np.float64)
    span = np.linalg.norm(p[:, 33] - p[:, 263], axis=-1)
    out = []
    for brow, a, b in BROWS:
        out.append(np.linalg.norm(p[:, brow] - 0.5 * (p[:, a] + p[:, b]), axis=-1) / span)
    return np.mean(out, 0)


def blink_runs(openness: np.ndarray, valid: np.ndarray) -> list[tuple[int, int]]:
    """``(first frame, length)`` of each run of valid frames with both eyes' mean openness below
    :data:`BLINK_BELOW` of the median over valid frames."""
    shut = np.asarray(valid, bool) & (openness < BLINK_BELOW * np.median(openness[valid]))
    edges = np.diff(np.concatenate([[0], shut.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return [(int(s), int(e - s)) for s, e in zip(starts, ends, strict=True)]


@dataclass(frozen=True)
class UpperFace:
    """A person's blinks and brows.

    Attributes:
        blink: ``(K_exp,)`` their blink: the mean expression change from the open eyes around each blink in
            their footage (:data:`OPEN_FROM`, :data:`AROUND`) to its closed frames.
        blinks_per_min: their rate (pulled towards :data:`PRIOR_BLINKS_PER_MIN` on short footage).
        blink_s: how long their eyes stay below the blink level (median over their blinks; 0.1 s without).
        brow: ``(K_exp,)`` expression change per unit of :func:`brow_height` (least squares over their
            footage); None when their brows do not move.
        brow_low, brow_rest, brow_high: their brow height's 5th, 50th and 95th percentile.
    """

    blink: np.ndarray | None
    blinks_per_min: float
    blink_s: float
    brow: np.ndarray | None
    brow_low: float
    brow_rest: float
    brow_high: float


def learn_upper_face(points: np.ndarray, expression: np.ndarray, valid: np.ndarray, fps: float) -> UpperFace:
    """A person's :class:`UpperFace` from their footage's mesh landmarks ``(T, >=468, 2|3)`` (the face
    model's vertices at the detector's landmarks, so the output is measured the same way), expressions
    ``(T, K_exp)`` and valid frames ``(T,)``."""
    valid = np.asarray(valid, bool)
    expression = np.asarray(expression, np.float64)
    openness = eye_openness(points)
    runs = blink_runs(openness, valid)
    wide = valid & (openness >= OPEN_FROM * np.median(openness[valid]))
    deltas = []
    for s, n in runs:  # the closed frames against the open eyes just around them
        around = np.zeros(len(valid), bool)
        around[max(s - AROUND, 0) : s] = True
        around[s + n : s + n + AROUND] = True
        around &= wide
        if around.any():
            deltas.append(expression[s : s + n].mean(0) - expression[around].mean(0))
    blink = np.mean(deltas, 0).astype(np.float32) if deltas else None
    minutes = valid.sum() / fps / 60.0
    rate = (len(runs) + PRIOR_BLINKS_PER_MIN * PRIOR_MINUTES) / (minutes + PRIOR_MINUTES)
    blink_s = float(np.median([n for _, n in runs]) / fps) if runs else 0.1
    h = brow_height(points)[valid]
    e = expression[valid]
    centred = h - h.mean()
    spread = float(centred @ centred)
    brow = (centred @ (e - e.mean(0)) / spread).astype(np.float32) if spread > 1e-12 else None
    lo, mid, hi = (float(v) for v in np.percentile(h, [5, 50, 95]))
    return UpperFace(blink, float(rate), blink_s, brow, lo, mid, hi)


def blink_track(upper: UpperFace, num_frames: int, fps: float, rng: np.random.Generator) -> np.ndarray:
    """``(T,)`` blink weights in [0, 1] (1: the eyes as closed as in the person's blinks): blinks at the
    person's rate (gamma-distributed intervals, shape 3: less regular than a clock, never closer than
    :data:`MIN_BLINK_GAP_S`), each closed for their blink length with a half-closed frame before and after."""
    w = np.zeros(num_frames, np.float32)
    if upper.blinks_per_min <= 0:
        return w
    mean_gap = 60.0 / upper.blinks_per_min
    closed = max(1, int(round(upper.blink_s * fps)))
    t = rng.uniform(0.0, mean_gap)
    while True:
        f = int(round(t * fps))
        if f >= num_frames:
            return w
        w[max(f - 1, 0)] = max(w[max(f - 1, 0)], 0.5)
        w[f : f + closed] = 1.0
        if f + closed < num_frames:
            w[f + closed] = max(w[f + closed], 0.5)
        t += max(MIN_BLINK_GAP_S, rng.gamma(3.0, mean_gap / 3.0))


def brow_track(upper: UpperFace, loudness: np.ndarray, voice: np.ndarray, fps: float) -> np.ndarray:
    """``(T,)`` brow heights: at rest (their median) in silence, raised towards their 95th percentile with the
    speech's emphasis (the loudness ``(T,)`` in dB, smoothed over :data:`BROW_SMOOTH_S`, above its median
    over voiced frames, scaled so its 95th percentile reaches the top), never outside their 5th-95th range."""
    voice = np.asarray(voice, np.float64)
    k = max(1, int(round(BROW_SMOOTH_S * fps)))
    smooth = np.convolve(np.asarray(loudness, np.float64), np.ones(k) / k, mode="same")
    speaking = voice >= 0.5
    if not speaking.any():
        return np.full(len(voice), upper.brow_rest)
    lo, top = np.percentile(smooth[speaking], [50, 95])
    emphasis = np.clip((smooth - lo) / max(top - lo, 1e-6), 0.0, 1.0) * voice
    h = upper.brow_rest + emphasis * (upper.brow_high - upper.brow_rest)
    return np.clip(h, upper.brow_low, upper.brow_high)


def upper_face_motion(
    upper: UpperFace, audio: np.ndarray, sample_rate: int, voice: np.ndarray, fps: float, seed: int = 0
) -> np.ndarray:
    """``(T, K_exp)`` expression offsets that blink and move the brows for mono ``audio`` with voice
    activity ``voice`` ``(T,)`` at ``fps`` (:func:`blink_track`, :func:`brow_track`); ``seed`` makes the
    blinks reproducible."""
    t = len(voice)
    k = len(upper.blink) if upper.blink is not None else len(upper.brow) if upper.brow is not None else 0
    out = np.zeros((t, k), np.float32)
    if upper.blink is not None:
        out += blink_track(upper, t, fps, np.random.default_rng(seed))[:, None] * upper.blink
    if upper.brow is not None:
        out += (brow_track(upper, frame_loudness(audio, sample_rate, fps, t), voice, fps) - upper.brow_rest)[
            :, None
        ] * upper.brow
    return out.astype(np.float32)


def frame_loudness(audio: np.ndarray, sample_rate: int, fps: float, num_frames: int) -> np.ndarray:
    """``(T,)`` level in dBFS of mono ``audio`` at each video frame's middle (the 20 ms blocks of
    :func:`nvp.vad.rms_envelope_db`)."""
    from nvp.vad import rms_envelope_db

    block_s = 0.02
    env = rms_envelope_db(audio, sample_rate, block_s)
    at = ((np.arange(num_frames) + 0.5) / fps / block_s).astype(int)
    return env[np.clip(at, 0, len(env) - 1)].astype(np.float64)
