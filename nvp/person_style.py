"""A person's talking style as data: :class:`PersonStyle` (person map, rest and closed mouth, pauses, the
opening calibration :class:`OpeningStyle`) with its file format, the footage it is learned from
(:class:`VideoSample`), and one style worn by another face (:func:`transferred_style`). Learning a style is
:mod:`nvp.person_fit`; predicting with one, :mod:`nvp.person`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from nvp.artifact import load_artifact, save_artifact
from nvp.audio2exp import (
    PersonMap,
)
from nvp.tracked import TrackedSequence
from nvp.upper_face import UpperFace

FORMAT_VERSION = 8
"""2: the person's closed mouth (``closed``) for the network's closure head; 3: the opening calibration
(:class:`OpeningStyle`); 4: the opening model corrected for the person (``OpeningStyle.adapted_weight``);
5: where the opening model's output closes their lips (``OpeningStyle.closed_below``); 6: how they hold the
mouth in pauses over time (``PersonStyle.pause_open`` / ``pause_close_after_s``); 7: how their lips round
(``PersonStyle.rounding``); 8: their blinks and brows (``PersonStyle.upper_face``). Older files load without
them."""


CLOSING_RAMP = (0.1, 0.5)
"""Standardised openings above :attr:`OpeningStyle.closed_below` (the person's closing level of the opening
model's output) where the blend towards their closed mouth is full and where it ends. With a closing level
the opening model, not the network's closure head, decides where the lips close: on the validation people
the model's output ranks the held-out closed frames better (ROC AUC per long clip 0.85-0.99, the head
0.60-0.82). Chosen there (``scripts/eval/lipsync.py --set validation``), closure F1 / opening correlation
with clean audio, 10 dB, 0 dB SNR:

    closure head   0.477 / 0.664   0.357 / 0.493   0.225 / 0.323
    (-0.1, 0.1)    0.501 / 0.703   0.277 / 0.522   0.204 / 0.431
    (0, 0.2)       0.485 / 0.698   0.300 / 0.511   0.260 / 0.439
    (0, 0.4)       0.490 / 0.696   0.327 / 0.507   0.292 / 0.451
    (0.1, 0.5)     0.476 / 0.692   0.370 / 0.506   0.354 / 0.439
    (0, 0.6)       0.477 / 0.695   0.371 / 0.509   0.350 / 0.437
    (0.2, 0.6)     0.456 / 0.685   0.399 / 0.501   0.363 / 0.424

(0.1, 0.5) and (0, 0.6) have the highest mean (0.473); the p/b/m frames closed at 10 dB rise 0.50 → 0.84."""


ROUNDED_APART = 2.0
"""How strongly a rounded vowel keeps the lips apart: where the recogniser hears a rounded vowel with
share ``r`` (:func:`nvp.rounding.rounded_share`), the blend towards the closed mouth is scaled by
``max(0, 1 - ROUNDED_APART r)``. The opening model's output is low on o / u (a rounded mouth is small), so
its closing level closed rounded lips that real mouths keep parted. Chosen on the validation people
(``scripts/eval/lipsync.py --set validation``, 5 folds, 231 rounded-vowel frames): share of those frames
closed 0.420 / 0.359 / 0.281 / 0.251 for 0 / 1 / 2 / 4 (real footage 0.195), closure F1 0.500 / 0.502 /
0.506 / 0.506 clean, 0.404 / 0.407 / 0.406 / 0.395 at 10 dB SNR, bilabial closures unchanged (0.924). A
veto by every vowel (spread ones too) did no better (F1 0.507 / 0.509 at 1 / 2, 10 dB 0.408 / 0.388)."""


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
        augmented: more ``(T, W, D)`` windows of the same frames, from copies of the audio (training
            augmentation, :mod:`nvp.augment`; may be empty).
        opening_windows: ``(T, W, D)`` windows of the opening model's features (``"whisper"``,
            :mod:`nvp.opening`) of the same frames, or None.
    """

    name: str
    windows: np.ndarray
    tracked: TrackedSequence
    augmented: tuple[np.ndarray, ...] = ()
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
        rounding: ``(K_exp,)`` how this person's lips round: the expression change per unit of the
            recogniser's rounded-vowel share above :attr:`rounding_mean` (:mod:`nvp.rounding`; it leaves
            the opening unchanged); None: no rounding beyond what the person map does.
        rounding_mean: the rounded share's mean over the person's speech.
        upper_face: their blinks and brows (:class:`nvp.upper_face.UpperFace`), for animations from audio
            alone; None: the upper face moves only as the person map moves it.
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
    rounding: np.ndarray | None = None
    rounding_mean: float = 0.0
    upper_face: UpperFace | None = None

    @property
    def hears_rounding(self) -> bool:
        """Whether the network's features are the recogniser's posteriors, from which the rounded-vowel share
        (:func:`nvp.rounding.rounded_share`) is read for :meth:`rounded` and :func:`apply_style`."""
        return self.feature_kind == "phonemes"

    def rounded(self, expression: np.ndarray, share: np.ndarray | None) -> np.ndarray:
        """Expressions ``(T, K_exp)`` with the person's rounding for the rounded share ``share`` ``(T,)``
        (:func:`nvp.rounding.rounded_share`); unchanged without a rounding or a share."""
        if self.rounding is None or share is None:
            return expression
        above = np.asarray(share, np.float32) - np.float32(self.rounding_mean)
        return (expression + above[:, None] * self.rounding).astype(np.float32)

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
        if self.rounding is not None:
            arrays["rounding"] = self.rounding
            fields["rounding_mean"] = self.rounding_mean
        if self.upper_face is not None:
            up = self.upper_face
            arrays |= {f"upper_{k}": getattr(up, k) for k in ("blink", "brow") if getattr(up, k) is not None}
            keys = ("blinks_per_min", "blink_s", "brow_low", "brow_rest", "brow_high")
            fields["upper_face"] = {k: getattr(up, k) for k in keys}
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
            a.get("rounding"),
            float(m.get("rounding_mean", 0.0)),
            UpperFace(a.get("upper_blink"), brow=a.get("upper_brow"), **m["upper_face"])
            if "upper_face" in m
            else None,
        )


def transferred_style(own: PersonStyle, other: PersonStyle) -> PersonStyle:
    """Person ``other``'s talking style on person ``own``'s face (speaking-style transfer).

    ``other``'s person map, closures and rounding decide how the mouth moves (how wide it opens, how often
    it closes, how it rounds, its asymmetries in motion), as offsets from their closed lips, put onto
    ``own``'s closed lips: ``e = e_other + (closed_own - closed_other)``, so a closure of ``other`` closes
    ``own``'s lips exactly; in pauses the mouth rests as ``own``'s does, and the eyes and brows are
    ``own``'s. Styles without a closed mouth (format 1) are anchored at their rest mouths instead. The two
    styles must come from the same network.
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
        other.rounding,
        other.rounding_mean,
        own.upper_face,  # the eyes and brows stay the face's own, as a dub keeps them from its footage
    )
