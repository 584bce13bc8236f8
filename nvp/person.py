"""Predicting a person's expressions from new audio with their talking style; the one place to import
person styles from.

``predict_expressions`` is the audio half of ``nvp dub``: speech features → generic network → person map
→ expression coefficients ``(T, K_exp)`` at the target's frame rate. The style itself (person map + rest
mouth, its file format) is :mod:`nvp.person_style`; learning it from the person's footage,
:mod:`nvp.person_fit`; both are re-exported here.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from nvp.audio2exp import (
    Audio2ExpressionNet,
    in_blocks,
    network_outputs,
)
from nvp.person_fit import (
    ADAPTED_OPENING_WEIGHT,
    OPENING_WEIGHT,
    PAUSE_MIN_FRAMES,
    PAUSE_MIN_S,
    PAUSE_REST_AFTER_MIN_S,
    PAUSE_TIMING_MIN_FRAMES,
    RANGE_GAIN_MAX,
    closed_mouth,
    opening_style,
    pause_rest,
    range_calibrated,
    rest_expression,
    style_from_sample,
    voiced_frames,
)
from nvp.person_style import (
    CLOSING_RAMP,
    FORMAT_VERSION,
    ROUNDED_APART,
    OpeningStyle,
    PersonStyle,
    VideoSample,
    transferred_style,
)
from nvp.rounding import rounded_share

if TYPE_CHECKING:
    from nvp.audio_features import AudioFeatures
    from nvp.opening import OpeningModel

__all__ = [  # the style's data and learning live in nvp.person_style and nvp.person_fit; one place to import
    "ADAPTED_OPENING_WEIGHT",
    "CLOSING_RAMP",
    "CLOSURE_RAMP",
    "FORMAT_VERSION",
    "OPENING_WEIGHT",
    "PAUSE_MIN_FRAMES",
    "PAUSE_MIN_S",
    "PAUSE_REST_AFTER_MIN_S",
    "PAUSE_TIMING_MIN_FRAMES",
    "RANGE_GAIN_MAX",
    "ROUNDED_APART",
    "WINDOW_BLOCK",
    "OpeningStyle",
    "PersonStyle",
    "VideoSample",
    "apply_style",
    "closed_mouth",
    "closure_weight",
    "network_features",
    "opening_features",
    "opening_outputs",
    "opening_style",
    "pause_rest",
    "predict_expressions",
    "range_calibrated",
    "rest_expression",
    "rounding_tap",
    "speech_features",
    "style_expressions",
    "style_from_sample",
    "style_opening_model",
    "transferred_style",
    "voiced_frames",
]

WINDOW_BLOCK = 512
"""Video frames whose feature windows :func:`predict_expressions` builds at a time: 6 MB for phonemes,
12.5 MB for Whisper's states, and a few times that while they are made and read (2048 frames took up to
200 MB on top of long audio's features; the outputs are the same)."""

CLOSURE_RAMP = (0.5, 0.8)
"""Closure probabilities (the network's closure head) mapped linearly to blend weights 0 … 1 towards the
person's closed mouth (see :func:`apply_style`). Chosen on the validation people: closure F1 0.42 / 0.45 /
0.45 and opening correlation 0.54 / 0.56 / 0.57 for (0.4, 0.7) / (0.5, 0.8) / (0.6, 0.9); (0.5, 0.8) kept
its closures better at 10 dB SNR (F1 0.32 vs 0.30)."""


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
    rounded: np.ndarray | None = None,
) -> np.ndarray:
    """Expression coefficients ``(T, K_exp)`` of a person from the generic network's outputs.

    Audio-expressions ``(T, A)`` → person map; the opening model's standardised openings ``opening``
    ``(T,)`` blend into the mouth opening (:class:`OpeningStyle`; required when the style has one); the
    lips round as the person's do for the recogniser's rounded-vowel share ``rounded`` ``(T,)``
    (:func:`nvp.rounding.rounded_share`, :meth:`PersonStyle.rounded`; required when the style has a
    rounding); where
    the opening model says the lips close (:meth:`OpeningStyle.closing`; for a style without a closing
    level: where the closure head's probabilities ``closure`` ``(T,)`` do, :func:`closure_weight` with
    ``ramp``), the mouth blends to the person's closed mouth, less where a rounded vowel is heard
    (:data:`ROUNDED_APART`); where ``voice`` ``(T,)`` in [0, 1] (see
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
    if style.rounding is not None:
        if rounded is None:
            raise ValueError("this person's style rounds the lips: pass the rounded-vowel share")
        expr = style.rounded(expr, rounded)
    if style.closed_expression is not None:
        w = None if style.opening is None else style.opening.closing(opening)
        if w is None and closure is not None:  # a style without a closing level: the closure head decides
            w = closure_weight(closure, ramp)
        if w is not None and rounded is not None:  # rounded lips are parted (ROUNDED_APART)
            w = w * np.clip(1.0 - ROUNDED_APART * np.asarray(rounded, np.float64), 0.0, 1.0)
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
    audio_exp, closure = network_outputs(net, in_blocks(windows, WINDOW_BLOCK))
    rounded = rounded_share(windows) if style.hears_rounding else None
    return apply_style(style, audio_exp, closure, voice, ramp, z, fps=fps, rounded=rounded)


def predict_expressions(
    audio: np.ndarray,
    sample_rate: int,
    fps: float,
    style: PersonStyle,
    net: Audio2ExpressionNet,
    num_frames: int | None = None,
    transcript: tuple[str, str] | None = None,
    upper_face: bool = False,
) -> np.ndarray:
    """Expression coefficients ``(T, K_exp)`` for mono audio, at ``fps`` video frames per second.

    Speech features → generic network → person map → opening model blend → closures
    (:func:`apply_style`); frames without voice (see :func:`nvp.vad.voice_activity`, a voice-activity
    detector) blend smoothly towards the person's rest expression, so pauses, silence, noise and music give
    a resting mouth. ``transcript``: ``(text, language)`` of what the audio says (an espeak-ng language,
    :mod:`nvp.transcript`): its p, b and m close the lips where they are aligned, its rounded vowels round
    them (as a rounded-vowel share of 1, :func:`nvp.transcript.rounded_weights`). ``upper_face``: the eyes
    blink and the brows move as the person's do (:func:`nvp.upper_face.upper_face_motion`, the same blinks
    for the same audio), for animations from audio alone; a dub keeps its footage's.
    """
    from nvp.vad import voice_activity
    from nvp.windows import iter_frame_windows

    posteriors = None  # the recogniser's one pass, shared by the network's features and the alignment
    if transcript is not None and style.feature_kind == "phonemes":
        from nvp.audio_features import extract_features

        posteriors = extract_features(audio, sample_rate, kind="phonemes")
    # one kind of features held at a time, each only as long as it is read (long audio's memory: the
    # recogniser's 2.3 MB a minute, Whisper's states 4.6 MB)
    feats, opening_feats = network_features(audio, sample_rate, style, posteriors)
    # windows are made block by block: all of them at once would be (T, 16, 191) float32, 37 MB a minute
    shares: list[np.ndarray] = []  # the rounded share, read from each block as the network reads it
    blocks = iter_frame_windows(feats, fps, num_frames, block=WINDOW_BLOCK)
    audio_exp, closure = network_outputs(net, rounding_tap(style, blocks, shares))
    del feats, blocks
    rounded = np.concatenate([np.zeros(0, np.float32), *shares]) if style.hears_rounding else None
    if opening_feats is None:
        opening_feats, _ = opening_features(audio, sample_rate, style)
    z = opening_outputs(style, opening_feats, fps, len(audio_exp))
    del opening_feats
    voice = voice_activity(audio, sample_rate, fps, len(audio_exp))
    text_closure = None
    if transcript is not None:
        from nvp.transcript import align_transcript, bilabial_weights, rounded_weights

        alignment = align_transcript(transcript[0], audio, sample_rate, transcript[1], posteriors)
        text_closure = bilabial_weights(alignment, fps, len(audio_exp))
        if rounded is not None:  # the text's rounded vowels round the lips and keep them apart
            rounded = np.maximum(rounded, rounded_weights(alignment, fps, len(audio_exp)))
    expr = apply_style(
        style, audio_exp, closure, voice, opening=z, text_closure=text_closure, fps=fps, rounded=rounded
    )
    if upper_face and style.upper_face is not None:
        import hashlib

        from nvp.upper_face import upper_face_motion

        seed = int.from_bytes(hashlib.sha256(np.ascontiguousarray(audio).tobytes()).digest()[:4], "little")
        expr = expr + upper_face_motion(style.upper_face, audio, sample_rate, voice, fps, seed)
    return expr


def rounding_tap(style: PersonStyle, blocks: Iterable[np.ndarray], shares: list) -> Iterator[np.ndarray]:
    """The feature-window blocks ``blocks`` unchanged; for a style whose features are the recogniser's
    (:attr:`PersonStyle.hears_rounding`), each block's rounded share (:func:`nvp.rounding.rounded_share`) is
    appended to ``shares`` as it passes."""
    for block in blocks:
        if style.hears_rounding:
            shares.append(rounded_share(block))
        yield block


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
    feats, phonetic = network_features(audio, sample_rate, style, posteriors)
    if phonetic is not None:
        return feats, phonetic, 0
    return feats, *opening_features(audio, sample_rate, style, opening_from)


def network_features(
    audio: np.ndarray, sample_rate: int, style: PersonStyle, posteriors: AudioFeatures | None = None
) -> tuple[AudioFeatures, AudioFeatures | None]:
    """The network's features of mono audio ``(S,)`` for a style (speaker-normalised, see
    :func:`speech_features`), and the opening model's when they come from the same pass (the
    ``"phonetic"`` ones of people fitted before; else None, :func:`opening_features` makes them)."""
    from nvp.audio_features import extract_features, recogniser_features, speaker_normalized

    model = style_opening_model(style)
    if model is not None and style.feature_kind == "phonemes" and model.feature_kind == "phonetic":
        feats, phonetic = recogniser_features(audio, sample_rate)
        return speaker_normalized(feats), phonetic
    if posteriors is None or style.feature_kind != "phonemes":
        posteriors = extract_features(audio, sample_rate, kind=style.feature_kind)
    return speaker_normalized(posteriors), None


def opening_features(
    audio: np.ndarray, sample_rate: int, style: PersonStyle, opening_from: int = 0
) -> tuple[AudioFeatures | None, int]:
    """The features of the opening model of a style whose model has a pass of its own (see
    :func:`speech_features`), read from ``audio[opening_from:]``, and ``opening_from``; None and 0 for a
    style without an opening model."""
    from nvp.audio_features import extract_features

    model = style_opening_model(style)
    if model is None:
        return None, 0
    return extract_features(audio[opening_from:], sample_rate, kind=model.feature_kind), opening_from
