"""``nvp dub``: make a fitted person say new audio.

audio → expressions of the person (``nvp.person.predict_expressions``, in blocks of long audio:
``nvp.long_audio``) → target frames played forward then
backward as long as the audio lasts (head pose, eyes and blinks from the footage) → mouth from the audio
→ neural rendering composited into the footage (``renderer.loop.render_frames``) → mp4 with the input
audio, marked as synthetic.

The video is encoded in parts of :data:`PART_FRAMES` frames, kept beside the output
(``.<output name>.nvp-parts/``) until the dub is done and then joined without encoding again: a dub that
is interrupted (even by ``kill -9``) resumes at its first unfinished part when the same command runs
again, if the audio, the person bundle and the style are the same (else it starts again). A dub that fails
on its input removes them (it would fail the same way again).
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from nvp.bundle import PersonBundle, check_output_place
from nvp.errors import NvpError
from nvp.face_model import FaceModel
from nvp.gaze import gaze_file
from nvp.geometry import posed
from nvp.tracked import TrackedSequence

if TYPE_CHECKING:
    from collections.abc import Iterator

    from nvp.audio2exp import Audio2ExpressionNet
    from nvp.person import PersonStyle

log = logging.getLogger(__name__)

PART_FRAMES = 250
"""Frames per resumable part of a dub's video (10 s at 25 frames/s, x264's own keyframe interval, so the
parts add few keyframes a single file would not have). Work lost to an interruption is at most one part."""


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
    rendered: int
    """Frames rendered by this call (fewer than ``frames`` when it resumed an interrupted dub)."""


def dub(
    audio_path: str | Path,
    bundle_dir: str | Path,
    output: str | Path,
    device: str = "cpu",
    progress: bool = True,
    style: str | Path | None = None,
    details: dict[str, str] | None = None,
    transcript: tuple[str, str] | None = None,
    gaze: str | Path = "footage",
) -> DubResult:
    """Make the person of ``bundle_dir`` say ``audio_path``; writes an mp4 as long as the audio (±1 frame),
    with the input audio at its own sample rate and channels. ``style``: another person's bundle or style
    file whose talking style drives the mouth (:func:`nvp.person.transferred_style`); ``details``: more
    provenance tags for the output (e.g. how its speech was made); ``transcript``: ``(text, language)`` of
    what the audio says, whose p, b and m then close the lips (:mod:`nvp.transcript`); ``gaze``: where the
    eyes look, ``"footage"`` (where they look in the footage), ``"camera"`` (into the lens) or a gaze file
    (:mod:`nvp.gaze`, angles in the face's frame), the footage's eyes turned (:mod:`renderer.eyes`)."""
    from nvp.artifact import check_output_file
    from nvp.media import frames_at
    from nvp.provenance import synthetic_mark
    from nvp.schedule import target_frame_indices
    from renderer.loop import render_frames
    from renderer.render import FrameRenderer

    t_start = time.perf_counter()
    check_output_place(
        check_output_file(output, inputs=(audio_path,)), (audio_path, bundle_dir, style, gaze_file(gaze))
    )
    bundle = PersonBundle.load(bundle_dir)
    person = load_person(bundle, style)
    seq, model = person.tracked, person.model
    # each block's temporaries are given back as it is made (nvp.long_audio): none kept for the rendering
    expression, duration = speech_expressions(audio_path, person, transcript, progress)
    n_out = len(expression)
    looks = eye_requests(gaze, seq, n_out)
    order = target_frame_indices(n_out, seq.num_frames)
    weights = model.mouth_weights()
    extra = {**(details or {}), **person.mark, **gaze_mark(gaze)}
    tags = synthetic_mark(
        "dub", bundle=bundle.manifest.get("id", bundle.root.name), audio=Path(audio_path).name, **extra
    )
    out = Path(output)
    out.parent.mkdir(parents=True, exist_ok=True)
    parts = DubParts(out, _resume_key(audio_path, bundle, style, n_out, transcript, device, gaze))
    first = parts.finished * PART_FRAMES
    if parts.finished:  # every resumed run says so
        where = f"at frame {first} of {n_out}" if first < n_out else f"all {n_out} frames rendered, joining"
        print(f"nvp dub: resuming {out.name} ({where})", file=sys.stderr)

    def spoken(j: int, k: int, tracked: np.ndarray) -> np.ndarray:  # j: from the first frame rendered now
        return dubbed_vertices(model, seq, k, expression[first + j], weights, tracked)

    if first < n_out:
        with FrameRenderer(bundle.path("renderer"), model, seq, device) as fr:
            rest = order[first:]
            frames = frames_at(bundle.path("target"), rest, seq.fps)
            decided: list[dict[str, int | None]] = []
            made_frames = render_frames(
                fr,
                frames,
                rest,
                {"dub": spoken},
                progress,
                "dub",
                start_entries=parts.entries,
                decided=decided,
                finish=None if looks is None else _eyes_turned(model, seq, first, looks),
            )
            parts.write(made_frames, decided, seq)
    parts.join(out, seq, audio_file=audio_path, metadata=tags)  # streamed from the file, at AAC's rates
    seconds = time.perf_counter() - t_start
    return DubResult(out, n_out, seq.fps, duration, seconds, order, expression, n_out - first)


def speech_expressions(
    audio_path: str | Path, person: Person, transcript: tuple[str, str] | None, progress: bool
) -> tuple[np.ndarray, float]:
    """The person's expressions ``(T, K_exp)`` for the speech of ``audio_path``, one per frame of the dub,
    and the audio's duration in seconds at its own rate (``len(read_audio(audio_path, None)) /
    audio_rate(audio_path)``, which sets the dub's length). The audio is decoded as mono 16 kHz and predicted
    block by block (:class:`nvp.long_audio.BlockedExpressions`): neither the track nor its 16 kHz copy is
    held whole (the join reads the file again, :class:`DubParts`). NvpError when it holds no speech."""
    from tqdm import tqdm

    from nvp.audio_features import SAMPLE_RATE
    from nvp.long_audio import BlockedExpressions
    from nvp.media import AudioBlocks
    from nvp.windows import num_video_frames

    AudioBlocks(audio_path, None, mono=False).close()  # as the join reads it: fails now, not after rendering
    fps = person.tracked.fps
    stream = BlockedExpressions(person.style, person.net, fps, transcript)
    with AudioBlocks(audio_path, SAMPLE_RATE) as blocks:
        stated = blocks.stated_seconds
        total = None if stated is None else num_video_frames(stated, fps)
        with tqdm(total=total, desc="dub: speech", unit="frame", disable=not progress) as bar:
            for block in blocks:
                stream.push(block)
                bar.update(stream.done - bar.n)
            duration = blocks.source_samples / blocks.source_rate
            n_out = num_video_frames(duration, fps)
            if stream.received:
                expression = stream.finish(n_out)
                bar.update(stream.done - bar.n)
    if not stream.received or not stream.has_speech():
        raise NvpError(f"{audio_path}: no speech found (silence, noise or music only, or too quiet)")
    return expression, duration


def eye_requests(gaze: str | Path, seq: TrackedSequence, frames: int) -> np.ndarray | None:
    """Where the eyes of each of ``frames`` output frames should look: None for the footage's own gaze,
    else ``(T, 2)`` yaw and pitch (a gaze file) or NaN (into the lens). Raises NvpError for a bad gaze file
    or a person tracked before nvp measured the iris (:func:`check_gaze`)."""
    from nvp.gaze import gaze_track

    if str(gaze) == "footage":
        return None
    check_gaze(seq)
    if str(gaze) == "camera":
        return np.full((frames, 2), np.nan, np.float32)
    return gaze_track(gaze, frames, seq.fps)


def gaze_mark(gaze: str | Path) -> dict[str, str]:
    """The output's provenance tag of a gaze request: none for the footage's own gaze."""
    return {} if str(gaze) == "footage" else {"gaze": Path(gaze).name}


def check_gaze(seq: TrackedSequence) -> None:
    """Before a dub whose eyes are turned: its person's tracking holds the iris (else NvpError), and a
    warning when the footage's eyes are too small to turn (:data:`renderer.eyes.MIN_IRIS_PX`)."""
    from nvp.gaze import iris_size
    from renderer.eyes import MIN_IRIS_PX

    if seq.iris is None:
        raise NvpError("this person was tracked before nvp measured gaze; run nvp fit again for --gaze")
    radius = iris_size(seq)
    if radius < MIN_IRIS_PX:
        log.warning(
            "the eyes are small in this footage (iris %.1f px, %.0f needed to turn them): --gaze leaves "
            "most of them as they are",
            radius,
            MIN_IRIS_PX,
        )


def _eyes_turned(model: FaceModel, seq: TrackedSequence, first: int, looks: np.ndarray):
    """The render loop's last step (``finish``) for a dub rendered from output frame ``first`` on: the eyes
    turned as ``looks`` (:func:`eye_requests`) asks (:func:`renderer.eyes.turn_eyes`)."""
    from renderer.eyes import turn_eyes

    def finish(j: int, index: int, image: np.ndarray) -> np.ndarray:
        look = looks[first + j]
        return turn_eyes(model, seq, image, index, None if np.isnan(look).any() else look)

    return finish


def _resume_key(
    audio_path: str | Path,
    bundle: PersonBundle,
    style: str | Path | None,
    frames: int,
    transcript: tuple[str, str] | None = None,
    device: str = "cpu",
    gaze: str | Path = "footage",
) -> dict:
    """What a resumed dub must share with the interrupted one: nvp's version and commit
    (:func:`nvp.provenance.code_version`), the device and precision it renders with, the audio's, the
    style's, the transcript's and the gaze file's content, the person bundle's manifest (its input,
    settings and stages) and the parts' length."""
    from nvp.artifact import file_sha256
    from nvp.provenance import code_version
    from renderer.networks import fast_bf16

    def manifest_sha(b: PersonBundle) -> str:
        return hashlib.sha256(json.dumps(b.manifest, sort_keys=True).encode()).hexdigest()

    if style is None:
        style_sha = None
    elif Path(style).is_dir():
        style_sha = manifest_sha(PersonBundle.load(style))
    else:
        style_sha = file_sha256(Path(style))
    return {
        "nvp": code_version(),
        "device": device,
        "bf16": fast_bf16(device),
        "audio_sha256": file_sha256(Path(audio_path)),
        "person_sha256": manifest_sha(bundle),
        "style_sha256": style_sha,
        "transcript_sha256": None
        if transcript is None
        else hashlib.sha256(json.dumps(list(transcript)).encode()).hexdigest(),
        "gaze": str(gaze) if gaze_file(gaze) is None else file_sha256(gaze_file(gaze)),
        "frames": frames,
        "part_frames": PART_FRAMES,
    }


def parts_folder(output: Path) -> Path:
    """Where the finished parts of a dub to ``output`` wait until it is done."""
    return output.with_name(f".{output.name}.nvp-parts")


class DubParts:
    """The finished parts of a dub to ``output`` of ``frames`` frames, in ``.<output name>.nvp-parts/``
    beside it: ``key.json`` (:func:`_resume_key`), ``part-NNNNN.mp4`` and ``part-NNNNN.json`` (the
    mouth-bank entries of the part's last frame, where the next part's choice goes on). Parts made for
    another key are discarded; ``finished`` parts are there, ``entries`` those the next part starts from."""

    def __init__(self, output: Path, key: dict) -> None:
        self.root, self.key, self.frames = parts_folder(output), key, int(key["frames"])
        self.finished, self.entries = 0, None
        key_file = self.root / "key.json"
        if self.root.exists() and not key_file.exists():
            if any(not f.name.startswith(".") for f in self.root.iterdir()):
                raise NvpError(f"{self.root} exists and was not made by nvp dub; move it away first")
            shutil.rmtree(self.root)  # a dub killed while it wrote its key left a temporary file only
        if key_file.exists():
            try:
                same = json.loads(key_file.read_text()) == key
            except (OSError, ValueError):
                same = False
            if not same:
                log.warning("%s held an interrupted dub of other input; starting again", output)
                shutil.rmtree(self.root)
        while self._video(self.finished).exists() and self._notes(self.finished).exists():
            self.finished += 1
        if self.finished:
            self.entries = json.loads(self._notes(self.finished - 1).read_text())["entries"]

    def _video(self, part: int) -> Path:
        return self.root / f"part-{part:05d}.mp4"

    def _notes(self, part: int) -> Path:
        return self.root / f"part-{part:05d}.json"

    def write(
        self,
        made: Iterator[tuple[np.ndarray, dict[str, np.ndarray]]],
        decided: list[dict[str, int | None]],
        seq: TrackedSequence,
    ) -> None:
        """Encodes the frames after the finished parts (``made`` by :func:`renderer.loop.render_frames`,
        which fills ``decided`` with their entries; those of finished parts are taken out of it) part after
        part; a part is finished once its video is complete and its last frame's entries are recorded."""
        from nvp.allocator import release_freed_memory
        from nvp.artifact import write_json
        from nvp.media import VideoWriter

        if not (self.root / "key.json").exists():  # made only now: a dub that fails before leaves nothing
            write_json(self.root / "key.json", self.key)
        first, writer = self.finished * PART_FRAMES, None
        try:
            for j, (_, made_frame) in enumerate(made, start=first):
                if writer is None:
                    writer = VideoWriter(self._video(j // PART_FRAMES), seq.fps, seq.width, seq.height)
                writer.write(made_frame["dub"])
                if (j + 1) % PART_FRAMES == 0 or j + 1 == self.frames:
                    writer.close()
                    writer = None
                    write_json(self._notes(j // PART_FRAMES), {"entries": decided[j - first]})
                    del decided[: j + 1 - first]  # not held for the whole dub: a long one's would grow
                    first = j + 1
                    # the frames' freed arrays, of varying sizes, fragment the heap a little more every
                    # part (+1 MB a minute of a dub); given back here, a long dub's memory stays flat
                    release_freed_memory()
        except NvpError as e:
            self._discard_after(e)
            raise
        finally:
            if writer is not None:
                writer.abort()

    def _discard_after(self, error: NvpError) -> None:
        """A dub that failed on its input (unreadable footage or audio, an encoder refusing it) would fail
        the same way again: its parts go, nothing is left beside the output. Parts stay for a resume after
        an interruption and a full disk."""
        from nvp.artifact import DiskFullError

        if not isinstance(error, DiskFullError):
            shutil.rmtree(self.root, ignore_errors=True)

    def join(self, output: Path, seq: TrackedSequence, audio_file: str | Path, **tags) -> None:
        """Writes ``output`` (atomically): the parts' video, copied, with the track of ``audio_file`` read
        from it block by block (it must still be the file the dub heard) and the tags
        (:class:`nvp.media.VideoWriter`'s ``metadata``); then the parts go."""
        from nvp.media import VideoWriter

        self._check_audio(Path(audio_file))
        videos = [self._video(i) for i in range(-(-self.frames // PART_FRAMES))]
        try:
            with VideoWriter(
                output, seq.fps, seq.width, seq.height, template=videos[0], audio_file=audio_file, **tags
            ) as vw:
                for video in videos:
                    vw.append(video)
        except NvpError as e:
            self._discard_after(e)
            raise
        shutil.rmtree(self.root, ignore_errors=True)

    def _check_audio(self, audio_file: Path) -> None:
        """NvpError when ``audio_file`` is gone or is no longer the audio of the key (moved or changed while
        it was dubbed); the parts stay, for a resume with the same audio."""
        from nvp.artifact import file_sha256

        if not audio_file.is_file() or file_sha256(audio_file) != self.key["audio_sha256"]:
            raise NvpError(
                f"{audio_file} was moved or changed while it was dubbed: the finished parts are kept in "
                f"{self.root} for the same audio; run the dub again"
            )
