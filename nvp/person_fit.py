"""Learning a person's talking style from their own footage (:func:`style_from_sample`, closed form): the
person map, their rest and closed mouth, how they hold the mouth in pauses, and the calibration of the mouth
opening against the generic opening model.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from nvp.audio2exp import (
    Audio2ExpressionNet,
    PersonMap,
    audio_expressions,
    solve_person_map,
)
from nvp.face_model import FaceModel
from nvp.metrics import closed_level
from nvp.person_style import OpeningStyle, PersonStyle, VideoSample
from nvp.rounding import is_recogniser_output, rounded_share, rounding_direction
from nvp.upper_face import learn_upper_face

if TYPE_CHECKING:
    from nvp.opening import OpeningModel

OPENING_WEIGHT = 0.75
"""Share of the generic opening model (:mod:`nvp.opening`) in the mouth opening, against the person map's
0.25 (see :class:`OpeningStyle`). Chosen on the validation people of ``scripts/data_split.json``
(``scripts/eval/lipsync.py --set validation --opening-weight W``); re-checked for the Whisper model: 0.5 /
0.65 / 0.75 / 0.85 / 1.0 gave opening correlation 0.636 / 0.643 / 0.644 / 0.642 / 0.637 (1.0: padded
features) and closure F1 0.447 / 0.438 / 0.447 / 0.446 / 0.419."""

ADAPTED_OPENING_WEIGHT = 1.0
"""The same share when the opening model was corrected on the person's own footage
(:func:`nvp.opening.adapted_opening_model`): then it alone decides the opening. On the four validation
clips long enough to be corrected, 0.75 / 0.9 / 1.0 gave opening correlation 0.727 / 0.739 / 0.742,
closure F1 0.499 / 0.530 / 0.589 and jitter ratio 0.71 / 0.73 / 0.75 (means over the clips; real 1.0)."""


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
every pause (their median pause mouth). Chosen on the validation people (``scripts/eval/lipsync.py --set
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


ROUNDING_MIN_FRAMES = 25
"""Speaking frames (1 s at 25 fps) from which a person's rounding is learned (:mod:`nvp.rounding`)."""


RANGE_GAIN_MAX = 2.0
"""Largest gain that widens the person map's predictions (see :func:`range_calibrated`). On the
validation people (``scripts/eval/lipsync.py --set validation``, the earlier network): opening range
0.90 → 1.09, closure F1 0.09 → 0.26, opening correlation unchanged (0.49)."""


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
      Measured on the validation people of ``scripts/data_split.json`` (``scripts/eval/lipsync.py``): pause
      frames at rest 0.85 → 0.06 (real 0.09), opening correlation 0.40 → 0.49;
    * closed expression: their closed lips while speaking (:func:`closed_mouth`), when the network has a
      closure head;
    * opening: with an ``opening`` model and the sample's ``opening_windows`` (of that model's features),
      the model corrected on the person's own footage when it is long enough
      (:func:`nvp.opening.adapted_opening_model`) and how its predictions blend into the mouth
      (:func:`opening_style`, ``opening_weight``);
    * rounding: for the ``"phonemes"`` network, how their lips round on the rounded vowels the recogniser
      hears (:func:`nvp.rounding.rounding_direction` on their speaking frames, or every frame without
      ``voiced``, of what the person map and opening leave unexplained; none on fewer than 25 such frames).
      Measured on the validation people (5 folds): mouth-width correlation 0.276 → 0.295, width on rounded /
      spread vowels 0.965 → 0.950 (real 0.959), opening correlation and closure F1 unchanged;
    * upper face: their blinks (how, how often, how long) and brows (how they move, their range) for
      animations from audio alone (:func:`nvp.upper_face.learn_upper_face`).
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
    rounding = None
    if manifest["feature_kind"] == "phonemes" and is_recogniser_output(sample.windows):
        speaking = np.ones(len(expression), bool) if voiced is None else voiced[ok]
        if speaking.sum() >= ROUNDING_MIN_FRAMES:
            predicted = pmap.apply(audio_exp)
            if calibration is not None:
                predicted = calibration.apply(predicted, z)
            rounding = rounding_direction(
                (expression - predicted)[speaking],
                rounded_share(sample.windows[ok])[speaking],
                None if calibration is None else calibration.gap_weights,
            )
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
        *(rounding or (None, 0.0)),
        learn_upper_face(
            model.vertices(identity, expression)[:, model.landmark_vertices],
            expression,
            ok[ok],
            sample.tracked.fps,
        ),
    )
