"""A person's talking style (person map + rest mouth) and predicting their expressions from new audio.

``predict_expressions`` is the audio half of ``nvp dub``: speech features → generic network → person map
→ expression coefficients ``(T, K_exp)`` at the target's frame rate.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from nvp.artifact import load_artifact, save_artifact
from nvp.audio2exp import (
    Audio2ExpressionNet,
    PersonMap,
    audio_expressions,
    in_blocks,
    network_outputs,
    solve_person_map,
)
from nvp.face_model import FaceModel
from nvp.metrics import closed_level
from nvp.tracked import TrackedSequence

if TYPE_CHECKING:
    from nvp.audio_features import AudioFeatures
    from nvp.opening import OpeningModel

WINDOW_BLOCK = 2048
"""Video frames whose feature windows :func:`predict_expressions` builds at a time (25 MB for phonemes)."""

FORMAT_VERSION = 6
"""2: the person's closed mouth (``closed``) for the network's closure head; 3: the opening calibration
(:class:`OpeningStyle`); 4: the opening model corrected for the person (``OpeningStyle.adapted_weight``);
5: where the opening model's output closes their lips (``OpeningStyle.closed_below``); 6: how they hold the
mouth in pauses over time (``PersonStyle.pause_open`` / ``pause_close_after_s``). Older files load without
them."""

OPENING_WEIGHT = 0.75
"""Share of the generic opening model (:mod:`nvp.opening`) in the mouth opening, against the person map's
0.25 (see :class:`OpeningStyle`). Chosen on the validation people of ``scripts/data_split.json``
(``scripts/eval_lipsync.py --set validation --opening-weight W``); re-checked for the Whisper model: 0.5 /
0.65 / 0.75 / 0.85 / 1.0 gave opening correlation 0.636 / 0.643 / 0.644 / 0.642 / 0.637 (1.0: padded
features) and closure F1 0.447 / 0.438 / 0.447 / 0.446 / 0.419."""

ADAPTED_OPENING_WEIGHT = 1.0
"""The same share when the opening model was corrected on the person's own footage
(:func:`nvp.opening.adapted_opening_model`): then it alone decides the opening. On the four validation
clips long enough to be corrected, 0.75 / 0.9 / 1.0 gave opening correlation 0.727 / 0.739 / 0.742,
closure F1 0.499 / 0.530 / 0.589 and jitter ratio 0.71 / 0.73 / 0.75 (means over the clips; real 1.0)."""


CLOSING_RAMP = (0.1, 0.5)
"""Standardised openings above :attr:`OpeningStyle.closed_below` (the person's closing level of the opening
model's output) where the blend towards their closed mouth is full and where it ends. With a closing level
the opening model, not the network's closure head, decides where the lips close: on the validation people
the model's output ranks the held-out closed frames better (ROC AUC per long clip 0.85-0.99, the head
0.60-0.82). Chosen there (``scripts/eval_lipsync.py --set validation``), closure F1 / opening correlation
with clean audio, 10 dB, 0 dB SNR:

    closure head   0.477 / 0.664   0.357 / 0.493   0.225 / 0.323
    (-0.1, 0.1)    0.501 / 0.703   0.277 / 0.522   0.204 / 0.431
    (0, 0.2)       0.485 / 0.698   0.300 / 0.511   0.260 / 0.439
    (0, 0.4)       0.490 / 0.696   0.327 / 0.507   0.292 / 0.451
    (0.1, 0.5)     0.476 / 0.692   0.370 / 0.506   0.354 / 0.439
    (0, 0.6)       0.477 / 0.695   0.371 / 0.509   0.350 / 0.437
    (0.2, 0.6)     0.456 / 0.685   0.399 / 0.501   0.363 / 0.424

(0.1, 0.5) and (0, 0.6) have the highest mean (0.473); the p/b/m frames closed at 10 dB rise 0.50 → 0.84."""


@dataclass(frozen=True)
class OpeningStyle:
    """How the generic opening model's prediction becomes this person's mouth opening.

    The opening is measured linearly: ``o(e) = e @ gap_weights + gap_offset`` (cm) is the distance of the
    person's inner-lip midpoints along their average opening direction for expression coefficients ``e``
    (the inner-lip gap while the lips are apart). For the person map's expressions ``e`` and the opening
    model's standardised openings ``z`` the target is ``o* = map_weight o(e) + opening_weight z + offset``
    (see :func:`opening_style`), and ``e`` moves along ``direction`` (how this person's expression changes
    as their mouth opens, with ``direction @ gap_weights = 1``) until ``o(e) = o*``.

    Attributes:
        gap_weights: ``(K_exp,)`` cm per expression coefficient; gap_offset: cm.
        direction: ``(K_exp,)`` expression change per cm of opening.
        map_weight, opening_weight, offset: the blend.
        model_sha256: the opening model it was calibrated for.
        adapted_weight, adapted_bias: that model's weights and bias corrected on the person's own footage
            (:func:`nvp.opening.adapted_opening_model`), None for the model as it ships.
        closed_below: the model's output (standardised opening) at or below which this person's lips are
            closed: its quantile over their own frames at the share of those frames whose lips are closed
            (:func:`nvp.metrics.closed_level`); see :meth:`closing`. None: the closure head decides.
    """

    gap_weights: np.ndarray
    gap_offset: float
    direction: np.ndarray
    map_weight: float
    opening_weight: float
    offset: float
    model_sha256: str
    adapted_weight: np.ndarray | None = None
    adapted_bias: float = 0.0
    closed_below: float | None = None

    def opening_of(self, expression: np.ndarray) -> np.ndarray:
        """``(T,)`` linear opening ``o(e)`` in cm of expressions ``(T, K_exp)``."""
        return expression @ self.gap_weights + self.gap_offset

    def apply(self, expression: np.ndarray, opening: np.ndarray) -> np.ndarray:
        """Expressions ``(T, K_exp)`` with their openings moved to the blend with ``opening`` ``(T,)``."""
        o = self.opening_of(expression)
        target = self.map_weight * o + self.opening_weight * np.asarray(opening) + self.offset
        return (expression + (target - o)[:, None] * self.direction).astype(np.float32)

    def closing(self, opening: np.ndarray) -> np.ndarray | None:
        """``(T,)`` blend weights towards the person's closed mouth for the opening model's outputs
        ``opening`` ``(T,)``: 1 up to :data:`CLOSING_RAMP` ``[0]`` above :attr:`closed_below`, 0 from
        ``[1]`` above it, linear between; None without a closing level."""
        if self.closed_below is None:
            return None
        lo, hi = CLOSING_RAMP
        return np.clip((self.closed_below + hi - np.asarray(opening, np.float64)) / (hi - lo), 0.0, 1.0)

    def shifted(self, shift: np.ndarray) -> OpeningStyle:
        """The same opening motion for expressions moved by ``shift`` ``(K_exp,)`` (style transfer)."""
        moved = float(shift @ self.gap_weights) * (1 - self.map_weight)
        return replace(self, offset=self.offset + moved)


@dataclass(frozen=True)
class VideoSample:
    """One talking-head video ready for solving a person map, training or evaluation.

    Attributes:
        name: file name of the video.
        windows: ``(T, W, D)`` float32 speech-feature windows, one per video frame.
        tracked: the video's ``TrackedSequence`` (``T`` frames; expressions are the regression target).
        noisy: more ``(T, W, D)`` windows of the same frames, from the audio with noise mixed in (training
            augmentation; may be empty).
        opening_windows: ``(T, W, D)`` windows of the opening model's features (``"whisper"``,
            :mod:`nvp.opening`) of the same frames, or None.
    """

    name: str
    windows: np.ndarray
    tracked: TrackedSequence
    noisy: tuple[np.ndarray, ...] = ()
    opening_windows: np.ndarray | None = None

    @property
    def expression(self) -> np.ndarray:
        return self.tracked.expression

    @property
    def valid(self) -> np.ndarray:
        return self.tracked.valid


@dataclass(frozen=True)
class PersonStyle:
    """A person's talking style: their map from the generic audio-expression space to their expression
    coefficients, their mouth at rest, and what it was made with.

    Attributes:
        person_map: ``(K_exp, A)`` matrix and ``(K_exp,)`` bias.
        rest_expression: ``(K_exp,)`` the person's mouth at rest: how they hold it in the pauses of their
            footage (or, without enough pauses, their most closed mouth); silence in new audio blends
            towards it (see :func:`predict_expressions`).
        closed_expression: ``(K_exp,)`` the person's closed lips while speaking (p, b, m, ...): frames
            where the opening model (or, without a closing level, the network's closure head) says the lips
            close blend towards it (:func:`apply_style`); None without a closure head.
        feature_kind: the speech features the map was solved with.
        audio2exp_sha256: hash of the generic network's weights the map belongs to.
        info: provenance (video, frames).
        opening: how the generic opening model's predictions enter (:class:`OpeningStyle`); None: the
            person map alone decides the opening.
        pause_open: ``(K_exp,)`` the mouth early in a pause, before the lips rest (their pause frames above
            the resting level, never wider than their speech); None: pauses rest at ``rest_expression``
            throughout.
        pause_close_after_s: seconds into a pause after which the lips rest at ``rest_expression`` (inf:
            this person does not close them in pauses); see :func:`pause_rest`.
    """

    person_map: PersonMap
    rest_expression: np.ndarray
    feature_kind: str
    audio2exp_sha256: str
    info: dict
    closed_expression: np.ndarray | None = None
    opening: OpeningStyle | None = None
    pause_open: np.ndarray | None = None
    pause_close_after_s: float = 0.0

    def sealed_lips(self) -> np.ndarray:
        """``(K_exp,)`` the person's lips pressed together, as for p, b and m: their closed mouth moved along
        their opening direction until the inner lips touch (opening 0, :class:`OpeningStyle`); the closed
        mouth itself for a style without an opening calibration. The closed mouth is the mean of their
        frames at or below their closed level, so its lips are a little apart (measured on one person:
        tracked gap 0.14 cm, 7th percentile of their frames; sealed 0.03 cm)."""
        closed = self.closed_expression
        if self.opening is None:
            return closed
        apart = max(float(self.opening.opening_of(closed[None])[0]), 0.0)
        return (closed - apart * self.opening.direction).astype(np.float32)

    def rest_track(self, voice: np.ndarray, fps: float) -> np.ndarray:
        """``(T, K_exp)`` the mouth each frame rests towards, for voice activity ``voice`` ``(T,)``: the rest
        mouth, or with :attr:`pause_open` that mouth until :attr:`pause_close_after_s` into each run of
        unvoiced frames (``voice < 0.5``; causal, so a stream can use it) and the rest mouth after it,
        with a two-frame ramp between."""
        if self.pause_open is None:
            return np.broadcast_to(self.rest_expression, (len(voice), len(self.rest_expression)))
        since = np.zeros(len(voice))  # frames since the current unvoiced run began (0 while voiced)
        run = 0
        for t, v in enumerate(np.asarray(voice) < 0.5):
            run = run + 1 if v else 0
            since[t] = run
        closing = np.clip((since - self.pause_close_after_s * fps) / 2.0, 0.0, 1.0)[:, None]
        return (self.pause_open + closing * (self.rest_expression - self.pause_open)).astype(np.float32)

    def save(self, path: Path) -> Path:
        """Write ``path`` (.npz) and its ``.json`` manifest (:mod:`nvp.artifact`); returns the manifest."""
        arrays = {
            "matrix": self.person_map.matrix,
            "bias": self.person_map.bias,
            "rest": self.rest_expression,
        }
        if self.closed_expression is not None:
            arrays["closed"] = self.closed_expression
        fields = {
            "feature_kind": self.feature_kind,
            "audio2exp_sha256": self.audio2exp_sha256,
            "info": self.info,
        }
        if self.opening is not None:
            op = self.opening
            arrays |= {"opening_gap_weights": op.gap_weights, "opening_direction": op.direction}
            keys = ("gap_offset", "map_weight", "opening_weight", "offset", "model_sha256", "adapted_bias")
            keys += ("closed_below",) if op.closed_below is not None else ()
            fields["opening"] = {k: getattr(op, k) for k in keys}
            if op.adapted_weight is not None:
                arrays["opening_adapted_weight"] = op.adapted_weight
        if self.pause_open is not None:
            arrays["pause_open"] = self.pause_open
            fields["pause_close_after_s"] = self.pause_close_after_s  # JSON: Infinity for never
        return save_artifact(path, "person_map", FORMAT_VERSION, arrays, fields)

    @classmethod
    def load(cls, path: Path) -> PersonStyle:
        art = load_artifact(path, "person_map", tuple(range(1, FORMAT_VERSION + 1)))
        a, m = art.arrays, art.manifest
        pm = PersonMap(matrix=a["matrix"], bias=a["bias"])
        opening = None
        if "opening" in m:
            opening = OpeningStyle(
                gap_weights=a["opening_gap_weights"],
                direction=a["opening_direction"],
                adapted_weight=a.get("opening_adapted_weight"),
                **m["opening"],
            )
        return cls(
            pm,
            a["rest"],
            m["feature_kind"],
            m["audio2exp_sha256"],
            m.get("info", {}),
            a.get("closed"),
            opening,
            a.get("pause_open"),
            float(m.get("pause_close_after_s", 0.0)),
        )


def rest_expression(expression: np.ndarray, gap: np.ndarray, fraction: float = 0.1) -> np.ndarray:
    """``(K_exp,)`` mean of the expressions ``(T, K_exp)`` whose inner-lip gap ``(T,)`` is in the lowest
    ``fraction`` (the person's closed, relaxed mouth)."""
    n = max(1, int(round(fraction * len(gap))))
    return expression[np.argsort(gap)[:n]].mean(0).astype(np.float32)


PAUSE_MIN_S = 0.3
"""Shortest run of unvoiced frames that counts as a pause."""
PAUSE_MIN_FRAMES = 5
"""Pause frames needed to take the person's mouth in pauses from them (else: their most closed mouth)."""


def voiced_frames(video: Path, fps: float, num_frames: int) -> np.ndarray:
    """``(T,)`` bool: video frames whose audio the voice-activity detector calls speech."""
    from nvp.media import read_audio
    from nvp.vad import frame_speech_probability

    audio = read_audio(video, 16000)
    return frame_speech_probability(audio, 16000, fps, num_frames) >= 0.5


PAUSE_REST_AFTER_MIN_S = 0.3
"""The lips come to rest no sooner than this into a run of unvoiced frames: a shorter run is a gap between
words, not a pause (:data:`PAUSE_MIN_S`), and a mouth does not close in it."""
PAUSE_TIMING_MIN_FRAMES = 10
"""Pause frames (0.4 s at 25 fps) from which the footage's pauses decide *when* the lips rest in a pause
(:attr:`PersonStyle.pause_open`, :attr:`PersonStyle.pause_close_after_s`); with fewer, one mouth holds
every pause (their median pause mouth). Chosen on the validation people (``scripts/eval_lipsync.py --set
validation --pause-timing-min-frames N``, clean audio; pause frames closed, real 0.094 / opening
correlation): one mouth always 0.071 / 0.685 (before: 0.071 / 0.689), N = 20, 50, 100 0.153 / 0.683,
N = 5, 10 0.082 / 0.691; see docs/experiments/lip-sync.md."""


def pause_rest(
    expression: np.ndarray,
    gap: np.ndarray,
    voiced: np.ndarray,
    fps: float,
    gap_of,
    timing_min_frames: int = PAUSE_TIMING_MIN_FRAMES,
) -> tuple[np.ndarray, np.ndarray | None, float] | None:
    """How this person holds the mouth in the pauses of their footage: ``(rest, open, close_after_s)``.

    With at least ``timing_min_frames`` pause frames: ``rest`` ``(K_exp,)`` is the mean of their pause
    frames whose inner-lip gap is at or below their resting level (:func:`nvp.metrics.closed_level` at
    0.3), or their closed lips when fewer than 3 are; ``open`` ``(K_exp,)`` the median of their other pause
    frames (``rest`` when fewer than 3); ``close_after_s`` the delay into a pause after which the lips rest,
    chosen so that their pauses, resting from that delay on, would rest as often as they do (inf when they
    never rest in a pause, 0 when they always do). With fewer: ``rest`` is the median of their pause frames,
    ``open`` None. Either mouth is moved towards their closed lips until it is no wider than their median
    speaking gap. None with fewer than ``PAUSE_MIN_FRAMES`` pause frames. Args: ``expression``
    ``(T, K_exp)``, ``gap`` ``(T,)``, ``voiced`` ``(T,)`` bool, ``gap_of``: inner-lip gaps ``(N,)`` of
    expressions ``(N, K_exp)``.
    """
    from nvp.metrics import pause_mask

    pauses = pause_mask(voiced, fps, PAUSE_MIN_S)
    if pauses.sum() < PAUSE_MIN_FRAMES:
        return None
    speaking = np.median(gap[voiced & ~pauses] if np.any(voiced & ~pauses) else gap)
    closed = closed_mouth(expression, gap)

    def no_wider(mouth: np.ndarray, towards: np.ndarray) -> np.ndarray:
        """The widest point on the way from ``towards`` to ``mouth`` that is no wider than their speech."""
        steps = np.linspace(0.0, 1.0, 65)[:, None]
        along = gap_of((towards + steps * (mouth - towards)).astype(np.float32))
        fits = np.flatnonzero(along <= speaking)
        return (towards + steps[fits[-1] if len(fits) else 0] * (mouth - towards)).astype(np.float32)

    if pauses.sum() < timing_min_frames:
        return no_wider(np.median(expression[pauses], 0), closed), None, 0.0
    resting = gap <= closed_level(gap, 0.3)
    shut, apart = pauses & resting, pauses & ~resting
    rest = no_wider(expression[shut].mean(0), closed) if shut.sum() >= 3 else closed
    open_ = no_wider(np.median(expression[apart], 0), rest) if apart.sum() >= 3 else rest
    # pause lengths in frames; the delay d rests sum(max(L - d, 0)) frames: match the resting share
    edges = np.diff(np.concatenate([[0], pauses.astype(np.int8), [0]]))
    lengths = np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)
    target = shut.sum()
    if target == 0:
        delay = float("inf")
    else:
        ds = np.arange(int(lengths.max()) + 1)
        rested = np.maximum(lengths[None] - ds[:, None], 0).sum(1)
        delay = max(float(ds[np.argmin(np.abs(rested - target))]) / fps, PAUSE_REST_AFTER_MIN_S)
    return rest, open_, delay


RANGE_GAIN_MAX = 2.0
"""Largest gain that widens the person map's predictions (see :func:`range_calibrated`). On the
validation people (``scripts/eval_lipsync.py --set validation``, the earlier network): opening range
0.90 → 1.09, closure F1 0.09 → 0.26, opening correlation unchanged (0.49)."""
CLOSURE_RAMP = (0.5, 0.8)
"""Closure probabilities (the network's closure head) mapped linearly to blend weights 0 … 1 towards the
person's closed mouth (see :func:`apply_style`). Chosen on the validation people: closure F1 0.42 / 0.45 /
0.45 and opening correlation 0.54 / 0.56 / 0.57 for (0.4, 0.7) / (0.5, 0.8) / (0.6, 0.9); (0.5, 0.8) kept
its closures better at 10 dB SNR (F1 0.32 vs 0.30)."""


def range_calibrated(
    pmap: PersonMap, audio_exp: np.ndarray, gap_of, real_gap: np.ndarray, max_gain: float = RANGE_GAIN_MAX
) -> tuple[PersonMap, float]:
    """The person map with its predictions widened around their mean so that the spread (5th to 95th
    percentile) of the predicted inner-lip gap on the person's own frames matches the tracked one.

    A least-squares map predicts the mean of what the audio allows, so its openings are compressed towards
    the person's average mouth. Args: ``audio_exp`` ``(T, A)`` the network's outputs on the person's
    frames, ``gap_of`` a function from expressions ``(T, K_exp)`` to inner-lip gaps ``(T,)``, ``real_gap``
    ``(T,)`` their tracked gaps. The gain is kept within 1 … ``max_gain`` (1: no widening); returns it too.
    """
    pred = pmap.apply(audio_exp)
    spread = np.percentile(gap_of(pred), 95) - np.percentile(gap_of(pred), 5)
    real = np.percentile(real_gap, 95) - np.percentile(real_gap, 5)
    gain = float(np.clip(real / spread, 1.0, max_gain)) if spread > 1e-9 else 1.0
    mean = pred.mean(0)
    matrix = (gain * pmap.matrix).astype(np.float32)
    bias = (gain * pmap.bias + (1 - gain) * mean).astype(np.float32)
    return PersonMap(matrix=matrix, bias=bias), gain


def closed_mouth(expression: np.ndarray, gap: np.ndarray, voiced: np.ndarray | None = None) -> np.ndarray:
    """``(K_exp,)`` the person's closed lips while speaking: mean expression of the frames ``(T, K_exp)``
    whose inner-lip gap ``(T,)`` is at or below their closed level (:func:`nvp.metrics.closed_level`),
    among the voiced ones ``(T,)`` when given; their most closed mouth when fewer than 3 such frames."""
    shut = gap <= closed_level(gap)
    if voiced is not None and np.sum(shut & voiced) >= 3:
        shut &= voiced
    if shut.sum() < 3:
        return rest_expression(expression, gap)
    return expression[shut].mean(0).astype(np.float32)


def _spread(x: np.ndarray) -> float:
    return float(np.percentile(x, 95) - np.percentile(x, 5))


def opening_style(
    model: FaceModel,
    identity: np.ndarray,
    expression: np.ndarray,
    predicted: np.ndarray,
    opening: np.ndarray,
    model_sha256: str,
    weight: float = OPENING_WEIGHT,
    max_gain: float = RANGE_GAIN_MAX,
) -> OpeningStyle | None:
    """The person's :class:`OpeningStyle` from their frames: tracked ``expression`` ``(T, K_exp)``, the
    person map's ``predicted`` expressions ``(T, K_exp)`` and the opening model's ``opening`` ``(T,)`` for
    the same frames.

    The opening model's output is put on the person's scale (its 5th-95th percentile spread and its mean
    made those of their tracked opening), blended with the map's opening (``weight`` for the model), and
    the blend is widened around its mean until its spread matches the tracked one (gain 1 … ``max_gain``,
    as :func:`range_calibrated`). None when the footage shows no opening motion to calibrate on.
    """
    lips = model.vertices(identity)[[13, 14]].astype(np.float64)  # (2, 3) neutral inner-lip midpoints
    basis = model.exp_basis[:, [13, 14]].astype(np.float64)  # (K_exp, 2, 3)
    e = np.asarray(expression, np.float64)
    axis = (lips[0] - lips[1]) + e.mean(0) @ (basis[:, 0] - basis[:, 1])
    if len(e) < 3 or np.linalg.norm(axis) < 1e-9:
        return None
    axis /= np.linalg.norm(axis)
    gw, g0 = (basis[:, 0] - basis[:, 1]) @ axis, float((lips[0] - lips[1]) @ axis)
    real = e @ gw + g0
    centred = real - real.mean()
    if _spread(real) < 1e-6 or _spread(opening) < 1e-9:
        return None
    direction = (e - e.mean(0)).T @ centred / (centred @ centred)
    if abs(direction @ gw) < 1e-9:
        return None
    scale = _spread(real) / _spread(opening)
    head_offset = real.mean() - scale * float(np.mean(opening))
    mapped = np.asarray(predicted, np.float64) @ gw + g0
    blend = (1 - weight) * mapped + weight * (scale * opening + head_offset)
    gain = float(np.clip(_spread(real) / max(_spread(blend), 1e-9), 1.0, max_gain))
    return OpeningStyle(
        gap_weights=gw.astype(np.float32),
        gap_offset=g0,
        direction=(direction / (direction @ gw)).astype(np.float32),
        map_weight=gain * (1 - weight),
        opening_weight=gain * weight * scale,
        offset=gain * weight * head_offset + (1 - gain) * float(blend.mean()),
        model_sha256=model_sha256,
    )


def style_from_sample(
    net: Audio2ExpressionNet,
    manifest: dict,
    sample: VideoSample,
    model: FaceModel,
    ridge: float = 10.0,
    voiced: np.ndarray | None = None,
    max_gain: float = RANGE_GAIN_MAX,
    opening: OpeningModel | None = None,
    opening_weight: float = OPENING_WEIGHT,
    pause_timing_min_frames: int = PAUSE_TIMING_MIN_FRAMES,
) -> PersonStyle:
    """A person's style from their tracked video.

    * person map: closed-form ridge map on all valid frames, widened so that the spread of its mouth
      openings on these frames matches the tracked one (:func:`range_calibrated` with ``max_gain``);
    * rest expression: the person's mouth in their pauses when ``voiced`` ``(T,)`` (see
      :func:`voiced_frames`) shows enough of them (:func:`pause_rest`; with ``pause_timing_min_frames``
      pause frames or more, also when in a pause their lips come to rest), else their most closed mouth.
      Measured on the validation people of ``scripts/data_split.json`` (``scripts/eval_lipsync.py``): pause
      frames at rest 0.85 → 0.06 (real 0.09), opening correlation 0.40 → 0.49;
    * closed expression: their closed lips while speaking (:func:`closed_mouth`), when the network has a
      closure head;
    * opening: with an ``opening`` model and the sample's ``opening_windows`` (of that model's features),
      the model corrected on the person's own footage when it is long enough
      (:func:`nvp.opening.adapted_opening_model`) and how its predictions blend into the mouth
      (:func:`opening_style`, ``opening_weight``).
    """
    ok = sample.valid
    identity = sample.tracked.identity
    audio_exp = audio_expressions(net, sample.windows)[ok]
    expression = sample.expression[ok]
    gap = model.inner_lip_gap(identity, expression)
    pmap = solve_person_map(audio_exp, expression, ridge)
    gap_of = lambda e: model.inner_lip_gap(identity, e)  # noqa: E731
    pmap, gain = range_calibrated(pmap, audio_exp, gap_of, gap, max_gain)
    rest, kind = rest_expression(expression, gap), "closed"
    pause_open, close_after = None, 0.0
    if voiced is not None:
        fps = sample.tracked.fps
        in_pause = pause_rest(expression, gap, voiced[ok], fps, gap_of, pause_timing_min_frames)
        if in_pause is not None:
            (rest, pause_open, close_after), kind = in_pause, "pauses"
    closed = None
    if net.closure is not None:
        closed = closed_mouth(expression, gap, None if voiced is None else voiced[ok])
    calibration, adaptation = None, None
    if opening is not None and sample.opening_windows is not None and opening_weight > 0:
        from nvp.opening import adapted_opening_model

        fps = sample.tracked.fps
        own, adaptation = adapted_opening_model(opening, sample.opening_windows[ok], gap, fps)
        predicted, z = pmap.apply(audio_exp), own.predict(sample.opening_windows, fps)[ok]
        weight = opening_weight if own is opening else max(opening_weight, ADAPTED_OPENING_WEIGHT)
        sha = opening.sha256
        calibration = opening_style(model, identity, expression, predicted, z, sha, weight, max_gain)
        if calibration is not None and own is not opening:
            calibration = replace(calibration, adapted_weight=own.weight, adapted_bias=own.bias)
        if calibration is not None:  # the model closes the lips as often as the person does
            shut = float(np.mean(gap <= closed_level(gap)))
            calibration = replace(calibration, closed_below=float(np.quantile(z, shut)))
    info = {"video": sample.name, "frames": int(ok.sum()), "ridge": ridge, "rest": kind, "range_gain": gain}
    if pause_open is not None:
        info["pause_close_after_s"] = round(close_after, 3) if np.isfinite(close_after) else "never"
    if opening is not None:
        info["opening"] = "calibrated" if calibration is not None else "not used: no opening motion"
        if adaptation is not None:
            info["opening_adapted"] = adaptation
    return PersonStyle(
        pmap,
        rest,
        manifest["feature_kind"],
        manifest["sha256"],
        info,
        closed,
        calibration,
        pause_open,
        close_after,
    )


def transferred_style(own: PersonStyle, other: PersonStyle) -> PersonStyle:
    """Person ``other``'s talking style on person ``own``'s face (speaking-style transfer).

    ``other``'s person map and closures decide how the mouth moves (how wide it opens, how often it closes,
    its asymmetries in motion), as offsets from their closed lips, put onto ``own``'s closed lips:
    ``e = e_other + (closed_own - closed_other)``, so a closure of ``other`` closes ``own``'s lips exactly;
    in pauses the mouth rests as ``own``'s does. Styles without a closed mouth (format 1) are anchored at
    their rest mouths instead. The two styles must come from the same network.
    """
    from nvp.errors import NvpError

    if (own.feature_kind, own.audio2exp_sha256) != (other.feature_kind, other.audio2exp_sha256):
        raise NvpError("the two people's styles were made with different Audio2ExpressionNets; refit one")
    if own.closed_expression is not None and other.closed_expression is not None:
        shift = own.closed_expression - other.closed_expression
    else:
        shift = own.rest_expression - other.rest_expression
    closed = None if other.closed_expression is None else (other.closed_expression + shift).astype(np.float32)
    pmap = PersonMap(matrix=other.person_map.matrix, bias=(other.person_map.bias + shift).astype(np.float32))
    info = {**other.info, "style_of": other.info.get("video"), "face_of": own.info.get("video")}
    opening = None if other.opening is None else other.opening.shifted(shift)
    return PersonStyle(
        pmap,
        own.rest_expression,
        other.feature_kind,
        other.audio2exp_sha256,
        info,
        closed,
        opening,
        own.pause_open,
        own.pause_close_after_s,
    )


def closure_weight(probability: np.ndarray, ramp: tuple[float, float] = CLOSURE_RAMP) -> np.ndarray:
    """``(T,)`` blend weights towards the closed mouth for closure probabilities ``(T,)``: 0 at ``ramp[0]``
    and below, 1 at ``ramp[1]`` and above, linear between (:data:`CLOSURE_RAMP`)."""
    lo, hi = ramp
    return np.clip((np.asarray(probability, np.float64) - lo) / (hi - lo), 0.0, 1.0)


def apply_style(
    style: PersonStyle,
    audio_exp: np.ndarray,
    closure: np.ndarray | None,
    voice: np.ndarray | None,
    ramp: tuple[float, float] = CLOSURE_RAMP,
    opening: np.ndarray | None = None,
    text_closure: np.ndarray | None = None,
    fps: float | None = None,
) -> np.ndarray:
    """Expression coefficients ``(T, K_exp)`` of a person from the generic network's outputs.

    Audio-expressions ``(T, A)`` → person map; the opening model's standardised openings ``opening``
    ``(T,)`` blend into the mouth opening (:class:`OpeningStyle`; required when the style has one); where
    the opening model says the lips close (:meth:`OpeningStyle.closing`; for a style without a closing
    level: where the closure head's probabilities ``closure`` ``(T,)`` do, :func:`closure_weight` with
    ``ramp``), the mouth blends to the person's closed mouth; where ``voice`` ``(T,)`` in [0, 1] (see
    :func:`nvp.vad.voice_activity`) is low, it blends to their rest mouth as they hold it in pauses
    (:meth:`PersonStyle.rest_track`, which needs the video frame rate ``fps``). ``text_closure`` ``(T,)`` in
    [0, 1]: where a transcript says the lips close (:func:`nvp.transcript.bilabial_weights`); the mouth
    blends to the closed mouth at least that much.
    """
    expr = style.person_map.apply(audio_exp)
    if style.opening is not None:
        if opening is None:
            raise ValueError("this person's style blends in the opening model: pass its openings")
        expr = style.opening.apply(expr, opening)
    if style.closed_expression is not None:
        w = None if style.opening is None else style.opening.closing(opening)
        if w is None and closure is not None:  # a style without a closing level: the closure head decides
            w = closure_weight(closure, ramp)
        if w is not None:
            expr = expr + w[:, None] * (style.closed_expression - expr)
        if text_closure is not None:  # the text's p, b and m: lips sealed, not only closed
            sealed = style.sealed_lips()
            expr = expr + np.asarray(text_closure, np.float32)[:, None] * (sealed - expr)
    if voice is not None:
        rest = style.rest_expression
        if style.pause_open is not None:
            if fps is None:
                raise ValueError(
                    "this person's style rests the mouth over time in pauses: pass the frame rate"
                )
            rest = style.rest_track(np.asarray(voice), fps)
        expr = rest + np.asarray(voice)[:, None] * (expr - rest)
    return expr.astype(np.float32)


def style_opening_model(style: PersonStyle, base: OpeningModel | None = None) -> OpeningModel | None:
    """The opening model a style was calibrated for (``base``, by default the shipped model with the
    style's hash) with the person's own correction when the style has one; None for a style without."""
    if style.opening is None:
        return None
    from nvp.errors import NvpError
    from nvp.opening import shipped_opening_model

    model = base or shipped_opening_model(style.opening.model_sha256)
    if model is None:
        raise NvpError(
            "this person was fitted with a mouth-opening model nvp no longer ships; run nvp fit again"
        )
    if style.opening.adapted_weight is not None:  # corrected on the person's own footage
        return replace(model, weight=style.opening.adapted_weight, bias=style.opening.adapted_bias)
    return model


def style_expressions(
    style: PersonStyle,
    net: Audio2ExpressionNet,
    windows: np.ndarray,
    voice: np.ndarray | None = None,
    ramp: tuple[float, float] = CLOSURE_RAMP,
    opening_windows: tuple[np.ndarray, float] | None = None,
    opening: OpeningModel | None = None,
) -> np.ndarray:
    """:func:`apply_style` for feature windows ``(T, W, D)`` held in memory (evaluations);
    ``opening_windows``: ``(T, W, D')`` windows of the ``opening`` model's features (default model: the
    style's, :func:`style_opening_model`) and the video frame rate, needed when the style has an opening
    calibration."""
    z = None
    if style.opening is not None:
        if opening_windows is None:
            raise ValueError("this person's style needs the opening model's feature windows")
        model = style_opening_model(style, opening)
        z = model.predict(in_blocks(opening_windows[0], WINDOW_BLOCK), opening_windows[1])
    fps = None if opening_windows is None else opening_windows[1]
    return apply_style(
        style, *network_outputs(net, in_blocks(windows, WINDOW_BLOCK)), voice, ramp, z, fps=fps
    )


def predict_expressions(
    audio: np.ndarray,
    sample_rate: int,
    fps: float,
    style: PersonStyle,
    net: Audio2ExpressionNet,
    num_frames: int | None = None,
    transcript: tuple[str, str] | None = None,
) -> np.ndarray:
    """Expression coefficients ``(T, K_exp)`` for mono audio, at ``fps`` video frames per second.

    Speech features → generic network → person map → opening model blend → closures
    (:func:`apply_style`); frames without voice (see :func:`nvp.vad.voice_activity`, a voice-activity
    detector) blend smoothly towards the person's rest expression, so pauses, silence, noise and music give
    a resting mouth. ``transcript``: ``(text, language)`` of what the audio says (an espeak-ng language,
    :mod:`nvp.transcript`): its p, b and m close the lips where they are aligned.
    """
    from nvp.vad import voice_activity
    from nvp.windows import iter_frame_windows

    posteriors = None  # the recogniser's one pass, shared by the network's features and the alignment
    if transcript is not None and style.feature_kind == "phonemes":
        from nvp.audio_features import extract_features

        posteriors = extract_features(audio, sample_rate, kind="phonemes")
    feats, opening_feats, _ = speech_features(audio, sample_rate, style, posteriors=posteriors)
    # windows are made block by block: all of them at once would be (T, 16, 191) float32, 37 MB a minute
    blocks = iter_frame_windows(feats, fps, num_frames, block=WINDOW_BLOCK)
    audio_exp, closure = network_outputs(net, blocks)
    z = opening_outputs(style, opening_feats, fps, len(audio_exp))
    voice = voice_activity(audio, sample_rate, fps, len(audio_exp))
    text_closure = None
    if transcript is not None:
        from nvp.transcript import align_transcript, bilabial_weights

        alignment = align_transcript(transcript[0], audio, sample_rate, transcript[1], posteriors)
        text_closure = bilabial_weights(alignment, fps, len(audio_exp))
    return apply_style(style, audio_exp, closure, voice, opening=z, text_closure=text_closure, fps=fps)


def opening_outputs(
    style: PersonStyle, features: AudioFeatures | None, fps: float, num_frames: int, first: int = 0
) -> np.ndarray | None:
    """``(num_frames,)`` the style's opening model's predictions from its features (see
    :func:`speech_features`) at ``fps``, the features starting at video frame ``first`` (frames before it
    get 0: a stream that reads less audio for them never returns those); None for a style without an
    opening calibration."""
    if style.opening is None:
        return None
    from nvp.windows import iter_frame_windows

    blocks = iter_frame_windows(features, fps, num_frames - first, block=WINDOW_BLOCK)
    return np.concatenate([np.zeros(first, np.float32), style_opening_model(style).predict(blocks, fps)])


def speech_features(
    audio: np.ndarray,
    sample_rate: int,
    style: PersonStyle,
    opening_from: int = 0,
    posteriors: AudioFeatures | None = None,
) -> tuple[AudioFeatures, AudioFeatures | None, int]:
    """The network's features of mono audio ``(S,)`` for a style (speaker-normalised), the features of the
    opening model it was calibrated on (None without one), and the sample of ``audio`` where those start.
    ``posteriors``: the recogniser's ``"phonemes"`` features of ``audio`` when already made (not made again).

    An opening model with a pass of its own (``"whisper"``) reads ``audio[opening_from:]`` (a stream needs
    less context for it than for the network); the ``"phonetic"`` one (people fitted before) comes from
    the recogniser's one pass over all of ``audio``, so its features start at 0."""
    from nvp.audio_features import extract_features, recogniser_features, speaker_normalized

    model = style_opening_model(style)
    if model is not None and style.feature_kind == "phonemes" and model.feature_kind == "phonetic":
        feats, phonetic = recogniser_features(audio, sample_rate)
        return speaker_normalized(feats), phonetic, 0
    if posteriors is None or style.feature_kind != "phonemes":
        posteriors = extract_features(audio, sample_rate, kind=style.feature_kind)
    feats = speaker_normalized(posteriors)
    if model is None:
        return feats, None, 0
    return feats, extract_features(audio[opening_from:], sample_rate, kind=model.feature_kind), opening_from
