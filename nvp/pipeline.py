"""What a user runs: ``fit`` a person from their footage, ``dub`` new audio onto them.

``fit``: target video → tracking → speech features → person style (closed-form map + rest expression) →
neural renderer training → ``PersonBundle`` (built in a ``.partial`` folder, resumable per stage,
published atomically).

``dub``: audio → expressions of the person (``nvp.person.predict_expressions``) → target frames played
forward then backward as long as the audio lasts (head pose, eyes and blinks from the footage) → mouth
from the audio → neural rendering composited into the footage → mp4 with the input audio, marked as
synthetic.
"""

from __future__ import annotations

import logging
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from nvp import __version__
from nvp.bundle import BundleBuilder, PersonBundle
from nvp.errors import MediaError, NvpError
from nvp.tracked import TrackedSequence

log = logging.getLogger(__name__)
SAMPLE_RATE = 16000


@dataclass(frozen=True)
class FitConfig:
    """Settings of ``nvp fit`` (saved in the bundle; resuming requires the same values)."""

    preset: str = "cpu"
    """Renderer preset (see ``renderer.presets``)."""
    budget_minutes: float | None = None
    """Wall-clock limit for renderer training; None = the preset's number of steps."""
    steps: int | None = None
    """Renderer training steps; None = the preset's default."""
    features: str = "phonemes"
    """Speech features of the person map (``phonemes`` or ``mel``)."""
    device: str = "cpu"
    """Torch device for renderer training (``cpu`` or ``cuda``)."""
    vgg_weights: str | None = None
    """Optional VGG-16 weights file for a perceptual renderer loss (see ``renderer.perceptual``)."""


def _stage(name: str) -> float:
    """Log the start of a ``fit`` stage; returns its start time."""
    log.info("fit: %s", name)
    return time.perf_counter()


def fit(
    video: str | Path,
    out: str | Path,
    cfg: FitConfig = FitConfig(),
    progress: bool = True,
    tracked: TrackedSequence | None = None,
) -> PersonBundle:
    """Build a person bundle from a talking-head video (1-3 minutes recommended).

    ``tracked``: the video's tracking when the caller already has it (skips the tracking stage)."""
    from nvp.media import probe_video

    video, out = Path(video), Path(out)
    info = probe_video(video)
    if not info.has_audio:
        raise MediaError(
            f"{video} has no audio track: nvp fit needs the person's speech to learn their style"
        )
    builder = BundleBuilder(out, {k: v for k, v in asdict(cfg).items() if k not in ("device", "vgg_weights")})

    if not builder.done("target"):
        t0 = _stage("copy target")
        tmp = builder.path("target").with_suffix(".tmp.mp4")
        shutil.copyfile(video, tmp)
        tmp.replace(builder.path("target"))
        builder.mark_done("target", source=str(video), seconds=round(time.perf_counter() - t0, 2))

    if not builder.done("track"):
        from tracking.track import track_video

        t0 = _stage("track")
        seq = tracked if tracked is not None else track_video(builder.path("target"), progress=progress)[0]
        seq.save(builder.path("tracked"))
        builder.mark_done(
            "track",
            frames=seq.num_frames,
            valid=int(seq.valid.sum()),
            seconds=round(time.perf_counter() - t0, 2),
        )

    if not builder.done("style"):
        from nvp.corpus import VideoSample, features_cached
        from nvp.face_model import default_face_model
        from nvp.person import default_audio2exp, style_from_sample

        t0 = _stage("person style")
        seq = TrackedSequence.load(builder.path("tracked"))
        windows = features_cached(
            builder.path("target"), builder.work / "cache", cfg.features, seq.fps, seq.num_frames
        )
        net, manifest = default_audio2exp(cfg.features)
        sample = VideoSample(name=video.name, windows=windows, tracked=seq)
        style_from_sample(net, manifest, sample, default_face_model()).save(builder.path("style"))
        builder.mark_done("style", seconds=round(time.perf_counter() - t0, 2))

    if not builder.done("renderer"):
        t0 = _stage("renderer")
        _train_renderer(builder, cfg, progress)
        builder.mark_done("renderer", seconds=round(time.perf_counter() - t0, 2))

    from nvp.face_model import default_face_model
    from nvp.person import PersonStyle

    style = PersonStyle.load(builder.path("style"))
    shutil.rmtree(builder.work / "cache", ignore_errors=True)
    return builder.publish(
        {
            "nvp_version": __version__,
            "face_model_sha256": default_face_model().sha256,
            "audio2exp_sha256": style.audio2exp_sha256,
            "feature_kind": style.feature_kind,
            "preset": cfg.preset,
            "target": {
                "source": str(video),
                "width": info.width,
                "height": info.height,
                "fps": info.fps,
                "frames": info.num_frames,
                "duration_s": info.duration_s,
            },
        }
    )


def _train_renderer(builder: BundleBuilder, cfg: FitConfig, progress: bool) -> None:
    """Cache the footage's crops once (``work/renderer_frames.npz``), then train (resumable)."""
    from nvp.face_model import default_face_model
    from renderer.data import FrameCache, build_cache, get_preset
    from renderer.train import TrainConfig, train_renderer

    preset = get_preset(cfg.preset)
    seq = TrackedSequence.load(builder.path("tracked"))
    frames_path = builder.work / "renderer_frames.npz"
    if frames_path.exists():
        cache = FrameCache.load(frames_path)
    else:
        model = default_face_model()
        cache = build_cache(builder.path("target"), seq, model, preset, np.flatnonzero(seq.valid), progress)
        cache.save(frames_path)
    budget = None if cfg.budget_minutes is None else cfg.budget_minutes * 60
    tcfg = TrainConfig(preset=cfg.preset, steps=cfg.steps, budget_s=budget, vgg_weights=cfg.vgg_weights)
    train_renderer(cache, tcfg, builder.path("renderer"), device=cfg.device, progress=progress)
    frames_path.unlink()
    (builder.path("renderer") / "checkpoint.pt").unlink(missing_ok=True)


def dubbed_vertices(
    model, seq, target_index: int, expression: np.ndarray, weights: np.ndarray, tracked_cam: np.ndarray
) -> np.ndarray:
    """``(V, 3)`` camera-frame vertices of a dubbed frame: pose, eyes and brows of target frame
    ``target_index`` (``tracked_cam``, its tracked camera-frame vertices, which the caller renders anyway),
    mouth and jaw of ``expression`` ``(K_exp,)``, blended per vertex by ``weights`` ``(V,)``
    (``model.mouth_weights()``, computed once per video). The pose is rigid, so blending in camera space
    equals blending in model space and posing."""
    w = weights[:, None]
    spoken = (
        model.vertices(seq.identity, expression) @ seq.rotation[target_index].T
        + seq.translation[target_index]
    )
    return (1 - w) * tracked_cam + w * spoken


def _frames_in_order(video: Path, indices: np.ndarray, fps: float, chunk: int = 48):
    """Yield the frames of ``video`` at ``indices`` (any order, e.g. ping-pong), decoding at most ``chunk``
    consecutive output frames' worth of source frames at a time (bounded memory)."""
    from nvp.media import iter_frames

    for c0 in range(0, len(indices), chunk):
        part = indices[c0 : c0 + chunk]
        lo, hi = int(part.min()), int(part.max())
        frames = list(iter_frames(video, fps=fps, start_frame=lo, max_frames=hi - lo + 1))
        if len(frames) < hi - lo + 1:
            raise MediaError(f"{video}: expected frames {lo}..{hi}, the file ended after {lo + len(frames)}")
        for i in part:
            yield frames[int(i) - lo]


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
) -> DubResult:
    """Make the person of ``bundle_dir`` say ``audio_path``; writes an mp4 as long as the audio (±1 frame),
    with the input audio at its own sample rate and channels."""
    from tqdm import tqdm

    from nvp.audio_features import num_video_frames, speech_activity
    from nvp.face_model import default_face_model
    from nvp.media import VideoWriter, audio_rate, read_audio
    from nvp.person import PersonStyle, default_audio2exp, predict_expressions
    from nvp.provenance import synthetic_mark
    from nvp.schedule import target_frame_indices
    from renderer.render import FrameRenderer

    t_start = time.perf_counter()
    bundle = PersonBundle.load(bundle_dir)
    rate = audio_rate(audio_path)
    original = read_audio(audio_path, None, mono=False)
    mono = original if original.ndim == 1 else original.mean(1)
    if len(mono) == 0 or not speech_activity(mono, rate):
        raise NvpError(f"{audio_path}: no speech found (the audio is silent or too quiet)")
    style = PersonStyle.load(bundle.path("style"))
    net, manifest = default_audio2exp(style.feature_kind)
    if manifest["sha256"] != style.audio2exp_sha256:
        raise NvpError(f"{bundle.root} was made with another Audio2ExpressionNet; run nvp fit again")
    seq = TrackedSequence.load(bundle.path("tracked"))
    model = default_face_model()
    duration = len(mono) / rate
    n_out = num_video_frames(duration, seq.fps)
    expression = predict_expressions(mono, rate, seq.fps, style, net, num_frames=n_out)
    order = target_frame_indices(n_out, seq.num_frames)
    weights = model.mouth_weights()
    tags = synthetic_mark(
        "dub", bundle=bundle.manifest.get("id", bundle.root.name), audio=Path(audio_path).name
    )
    out = Path(output)
    out.parent.mkdir(parents=True, exist_ok=True)
    bar = tqdm(total=n_out, desc="dub", unit="frame", disable=not progress)
    with (
        FrameRenderer(bundle.path("renderer"), model, seq, device) as fr,
        VideoWriter(
            out, seq.fps, seq.width, seq.height, audio=original, audio_rate=rate, metadata=tags
        ) as vw,
    ):
        for j, frame in enumerate(_frames_in_order(bundle.path("target"), order, seq.fps)):
            k = int(order[j])
            tracked = fr.tracked(k)
            cam = dubbed_vertices(model, seq, k, expression[j], weights, tracked)
            vw.write(fr.render(frame, k, cam, tracked))
            bar.update(1)
    bar.close()
    return DubResult(out, n_out, seq.fps, duration, time.perf_counter() - t_start, order, expression)
