"""A person's talking style (person map + rest mouth) and predicting their expressions from new audio.

``predict_expressions`` is the audio half of ``nvp dub``: speech features → generic network → person map
→ expression coefficients ``(T, K_exp)`` at the target's frame rate.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

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
from nvp.tracked import TrackedSequence

WINDOW_BLOCK = 2048
"""Video frames whose feature windows :func:`predict_expressions` builds at a time (25 MB for phonemes)."""

FORMAT_VERSION = 2
"""2: the person's closed mouth (``closed``) for the network's closure head; version 1 files load without
it."""


@dataclass(frozen=True)
class VideoSample:
    """One talking-head video ready for solving a person map, training or evaluation.

    Attributes:
        name: file name of the video.
        windows: ``(T, W, D)`` float32 speech-feature windows, one per video frame.
        tracked: the video's ``TrackedSequence`` (``T`` frames; expressions are the regression target).
        noisy: more ``(T, W, D)`` windows of the same frames, from the audio with noise mixed in (training
            augmentation; may be empty).
    """

    name: str
    windows: np.ndarray
    tracked: TrackedSequence
    noisy: tuple[np.ndarray, ...] = ()

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
            where the network's closure head is sure blend towards it; None without a closure head.
        feature_kind: the speech features the map was solved with.
        audio2exp_sha256: hash of the generic network's weights the map belongs to.
        info: provenance (video, frames).
    """

    person_map: PersonMap
    rest_expression: np.ndarray
    feature_kind: str
    audio2exp_sha256: str
    info: dict
    closed_expression: np.ndarray | None = None

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
        return save_artifact(path, "person_map", FORMAT_VERSION, arrays, fields)

    @classmethod
    def load(cls, path: Path) -> PersonStyle:
        art = load_artifact(path, "person_map", (1, FORMAT_VERSION))
        a, m = art.arrays, art.manifest
        pm = PersonMap(matrix=a["matrix"], bias=a["bias"])
        return cls(
            pm, a["rest"], m["feature_kind"], m["audio2exp_sha256"], m.get("info", {}), a.get("closed")
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


def pause_expression(expression: np.ndarray, voiced: np.ndarray, fps: float) -> np.ndarray | None:
    """``(K_exp,)`` median expression of the frames in pauses (runs of ``PAUSE_MIN_S`` without voice) of
    ``expression`` ``(T, K_exp)`` / ``voiced`` ``(T,)``: how this person holds the mouth between phrases;
    None with fewer than ``PAUSE_MIN_FRAMES`` such frames."""
    from nvp.metrics import pause_mask

    pauses = pause_mask(voiced, fps, PAUSE_MIN_S)
    if pauses.sum() < PAUSE_MIN_FRAMES:
        return None
    return np.median(expression[pauses], 0).astype(np.float32)


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
    from nvp.metrics import closed_level

    shut = gap <= closed_level(gap)
    if voiced is not None and np.sum(shut & voiced) >= 3:
        shut &= voiced
    if shut.sum() < 3:
        return rest_expression(expression, gap)
    return expression[shut].mean(0).astype(np.float32)


def style_from_sample(
    net: Audio2ExpressionNet,
    manifest: dict,
    sample: VideoSample,
    model: FaceModel,
    ridge: float = 10.0,
    voiced: np.ndarray | None = None,
    max_gain: float = RANGE_GAIN_MAX,
) -> PersonStyle:
    """A person's style from their tracked video.

    * person map: closed-form ridge map on all valid frames, widened so that the spread of its mouth
      openings on these frames matches the tracked one (:func:`range_calibrated` with ``max_gain``);
    * rest expression: the person's mouth in their pauses when ``voiced`` ``(T,)`` (see
      :func:`voiced_frames`) shows enough of them, else their most closed mouth. Measured on the
      validation people of ``scripts/data_split.json`` (``scripts/eval_lipsync.py``): pause frames at rest
      0.85 → 0.06 (real 0.09), opening correlation 0.40 → 0.49;
    * closed expression: their closed lips while speaking (:func:`closed_mouth`), when the network has a
      closure head.
    """
    ok = sample.valid
    identity = sample.tracked.identity
    audio_exp = audio_expressions(net, sample.windows)[ok]
    expression = sample.expression[ok]
    gap = model.inner_lip_gap(identity, expression)
    pmap = solve_person_map(audio_exp, expression, ridge)
    pmap, gain = range_calibrated(pmap, audio_exp, lambda e: model.inner_lip_gap(identity, e), gap, max_gain)
    rest, kind = rest_expression(expression, gap), "closed"
    if voiced is not None:
        in_pause = pause_expression(expression, voiced[ok], sample.tracked.fps)
        if in_pause is not None:
            rest, kind = in_pause, "pauses"
    closed = None
    if net.closure is not None:
        closed = closed_mouth(expression, gap, None if voiced is None else voiced[ok])
    info = {"video": sample.name, "frames": int(ok.sum()), "ridge": ridge, "rest": kind, "range_gain": gain}
    return PersonStyle(pmap, rest, manifest["feature_kind"], manifest["sha256"], info, closed)


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
    return PersonStyle(pmap, own.rest_expression, other.feature_kind, other.audio2exp_sha256, info, closed)


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
) -> np.ndarray:
    """Expression coefficients ``(T, K_exp)`` of a person from the generic network's outputs.

    Audio-expressions ``(T, A)`` → person map; where the closure head's probabilities ``closure`` ``(T,)``
    say the lips are closed, the mouth blends to the person's closed mouth (:func:`closure_weight` with
    ``ramp``); where
    ``voice`` ``(T,)`` in [0, 1] (see :func:`nvp.vad.voice_activity`) is low, it blends to their rest mouth.
    """
    expr = style.person_map.apply(audio_exp)
    if style.closed_expression is not None and closure is not None:
        w = closure_weight(closure, ramp)[:, None]
        expr = expr + w * (style.closed_expression - expr)
    if voice is not None:
        expr = style.rest_expression + np.asarray(voice)[:, None] * (expr - style.rest_expression)
    return expr.astype(np.float32)


def style_expressions(
    style: PersonStyle,
    net: Audio2ExpressionNet,
    windows: np.ndarray,
    voice: np.ndarray | None = None,
    ramp: tuple[float, float] = CLOSURE_RAMP,
) -> np.ndarray:
    """:func:`apply_style` for feature windows ``(T, W, D)`` held in memory (evaluations)."""
    return apply_style(style, *network_outputs(net, in_blocks(windows, WINDOW_BLOCK)), voice, ramp)


def predict_expressions(
    audio: np.ndarray,
    sample_rate: int,
    fps: float,
    style: PersonStyle,
    net: Audio2ExpressionNet,
    num_frames: int | None = None,
) -> np.ndarray:
    """Expression coefficients ``(T, K_exp)`` for mono audio, at ``fps`` video frames per second.

    Speech features → generic network → person map → closures (:func:`apply_style`); frames
    without voice (see :func:`nvp.vad.voice_activity`, a voice-activity detector) blend smoothly towards
    the person's rest expression, so pauses, silence, noise and music give a resting mouth.
    """
    from nvp.audio_features import extract_features, speaker_normalized
    from nvp.vad import voice_activity
    from nvp.windows import iter_frame_windows

    feats = speaker_normalized(extract_features(audio, sample_rate, kind=style.feature_kind))
    # windows are made block by block: all of them at once would be (T, 16, 191) float32, 37 MB a minute
    blocks = iter_frame_windows(feats, fps, num_frames, block=WINDOW_BLOCK)
    audio_exp, closure = network_outputs(net, blocks)
    voice = voice_activity(audio, sample_rate, fps, len(audio_exp))
    return apply_style(style, audio_exp, closure, voice)
