"""``nvp dub``: make a fitted person say new audio.

audio → expressions of the person (``nvp.person.predict_expressions``) → target frames played forward then
backward as long as the audio lasts (head pose, eyes and blinks from the footage) → mouth from the audio
→ neural rendering composited into the footage (``renderer.render.render_frames``) → mp4 with the input
audio, marked as synthetic.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from nvp.bundle import PersonBundle
from nvp.errors import NvpError
from nvp.face_model import FaceModel
from nvp.geometry import posed
from nvp.tracked import TrackedSequence

if TYPE_CHECKING:
    from nvp.audio2exp import Audio2ExpressionNet
    from nvp.person import PersonStyle

log = logging.getLogger(__name__)


def dubbed_vertices(
    model: FaceModel,
    seq: TrackedSequence,
    target_index: int,
    expression: np.ndarray,
    weights: np.ndarray,
    tracked_cam: np.ndarray,
) -> np.ndarray:
    """``(V, 3)`` camera-frame vertices of a dubbed frame: pose, eyes and brows of target frame
    ``target_index`` (``tracked_cam``, its tracked camera-frame vertices, which the caller renders anyway),
    mouth and jaw of ``expression`` ``(K_exp,)``, blended per vertex by ``weights`` ``(V,)``
    (``model.mouth_weights()``, computed once per video). The pose is rigid, so blending in camera space
    equals blending in model space and posing."""
    w = weights[:, None]
    k = target_index
    spoken = posed(model.vertices(seq.identity, expression), seq.rotation[k], seq.translation[k])
    return (1 - w) * tracked_cam + w * spoken


def load_style(path: str | Path):
    """A person's talking style from their bundle folder (``nvp fit``) or a style file (``nvp person-map``,
    its ``.json`` or ``.npz``)."""
    from nvp.person import PersonStyle

    path = Path(path)
    if path.is_dir():
        return PersonStyle.load(PersonBundle.load(path).path("style"))
    if not path.exists():
        raise NvpError(f"style {path} not found (give a person bundle folder or a person-map .json)")
    return PersonStyle.load(path)


@dataclass(frozen=True)
class Person:
    """What dubbing a fitted person needs besides the audio (see :func:`load_person`)."""

    bundle: PersonBundle
    style: PersonStyle
    """The style that drives the mouth (the person's own, or transferred)."""
    net: Audio2ExpressionNet
    """The generic network the style belongs to."""
    tracked: TrackedSequence
    model: FaceModel
    mark: dict[str, str]
    """Provenance tags of the style (which person's style, when another one's)."""


def load_person(bundle: PersonBundle, style: str | Path | None = None) -> Person:
    """The person of a loaded ``bundle``, talking in their own style or in ``style``'s (another person's
    bundle folder or style file, :func:`nvp.person.transferred_style`); checks that the style and the
    shipped network belong together."""
    from nvp.audio2exp import default_audio2exp
    from nvp.face_model import default_face_model
    from nvp.person import PersonStyle, transferred_style

    own = PersonStyle.load(bundle.path("style"))
    chosen = own if style is None else transferred_style(own, load_style(style))
    if chosen.feature_kind == "phonemes" and chosen.opening is None and "opening" not in chosen.info:
        log.warning(
            "%s was fitted before nvp's mouth-opening model; a new nvp fit (into another folder) adds it",
            bundle.root,
        )
    net, manifest = default_audio2exp(chosen.feature_kind)
    if manifest["sha256"] != chosen.audio2exp_sha256:
        raise NvpError(f"{bundle.root} was made with another Audio2ExpressionNet; run nvp fit again")
    mark = {} if style is None else {"style": str(chosen.info.get("style_of"))}
    seq = TrackedSequence.load(bundle.path("tracked"))
    return Person(bundle, chosen, net, seq, default_face_model(), mark)


@dataclass(frozen=True)
class DubResult:
    """What ``dub`` wrote and measured."""

    output: Path
    frames: int
    fps: float
    audio_seconds: float
    seconds: float
    target_frames: np.ndarray
    """``(T,)`` index of the target frame behind each output frame."""
    expression: np.ndarray
    """``(T, K_exp)`` expressions predicted from the audio."""


def dub(
    audio_path: str | Path,
    bundle_dir: str | Path,
    output: str | Path,
    device: str = "cpu",
    progress: bool = True,
    style: str | Path | None = None,
    details: dict[str, str] | None = None,
) -> DubResult:
    """Make the person of ``bundle_dir`` say ``audio_path``; writes an mp4 as long as the audio (±1 frame),
    with the input audio at its own sample rate and channels. ``style``: another person's bundle or style
    file whose talking style drives the mouth (:func:`nvp.person.transferred_style`); ``details``: more
    provenance tags for the output (e.g. how its speech was made)."""
    from nvp.artifact import check_output_file
    from nvp.media import VideoWriter, audio_rate, frames_at, read_audio
    from nvp.person import predict_expressions
    from nvp.provenance import synthetic_mark
    from nvp.schedule import target_frame_indices
    from nvp.vad import speech_activity
    from nvp.windows import num_video_frames
    from renderer.render import FrameRenderer, render_frames

    t_start = time.perf_counter()
    check_output_file(output, inputs=(audio_path,))
    bundle = PersonBundle.load(bundle_dir)
    rate = audio_rate(audio_path)
    original = read_audio(audio_path, None, mono=False)
    mono = original if original.ndim == 1 else original.mean(1)
    if len(mono) == 0 or not speech_activity(mono, rate):
        raise NvpError(f"{audio_path}: no speech found (silence, noise or music only, or too quiet)")
    person = load_person(bundle, style)
    style, net, seq, model = person.style, person.net, person.tracked, person.model
    duration = len(mono) / rate
    n_out = num_video_frames(duration, seq.fps)
    expression = predict_expressions(mono, rate, seq.fps, style, net, num_frames=n_out)
    order = target_frame_indices(n_out, seq.num_frames)
    weights = model.mouth_weights()

    def spoken(j: int, k: int, tracked: np.ndarray) -> np.ndarray:
        return dubbed_vertices(model, seq, k, expression[j], weights, tracked)

    extra = {**(details or {}), **person.mark}
    tags = synthetic_mark(
        "dub", bundle=bundle.manifest.get("id", bundle.root.name), audio=Path(audio_path).name, **extra
    )
    out = Path(output)
    out.parent.mkdir(parents=True, exist_ok=True)
    with (
        FrameRenderer(bundle.path("renderer"), model, seq, device) as fr,
        VideoWriter(
            out, seq.fps, seq.width, seq.height, audio=original, audio_rate=rate, metadata=tags
        ) as vw,
    ):
        frames = frames_at(bundle.path("target"), order, seq.fps)
        for _, made in render_frames(fr, frames, order, {"dub": spoken}, progress, "dub"):
            vw.write(made["dub"])
    return DubResult(out, n_out, seq.fps, duration, time.perf_counter() - t_start, order, expression)
