"""``nvp fit``: learn a person from their footage.

target video → tracking → speech features → person style (closed-form map + rest expression) → neural
renderer training → ``PersonBundle`` (built in a ``.partial`` folder, resumable per stage, published
atomically).
"""

from __future__ import annotations

import contextlib
import logging
import shutil
import sys
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from nvp import __version__
from nvp.artifact import DiskFullError, atomic_path
from nvp.bundle import BundleBuilder, PersonBundle
from nvp.errors import MediaError, NoFaceError, NvpError
from nvp.tracked import TrackedSequence

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FitConfig:
    """Settings of ``nvp fit`` (saved in the bundle; resuming requires the same values)."""

    preset: str = "cpu"
    """Renderer preset (see ``renderer.preset.PRESETS``)."""
    budget_minutes: float | None = None
    """Renderer training time (the steps it takes, unless ``steps`` is given too); None = the preset's
    steps (on a CPU at most the preset's time)."""
    steps: int | None = None
    """Renderer training steps; None = the preset's default (or as many as ``budget_minutes`` allows)."""
    features: str = "phonemes"
    """Speech features of the person map (``phonemes`` or ``mel``)."""
    device: str = "cpu"
    """Torch device for renderer training (``cpu`` or ``cuda``)."""
    vgg_weights: str | None = None
    """Optional VGG-16 weights file for a perceptual renderer loss (see ``renderer.perceptual``)."""
    renderer_init: str = "generic"
    """Where renderer training starts: ``generic`` (the renderer pre-trained on many people that ships
    with nvp, when the preset has one), ``scratch``, or a renderer folder."""
    min_seconds: float = 1.0
    """Shortest target video accepted; below ``warn_seconds`` nvp warns (1-3 minutes of speech are
    recommended: the style and the renderer learn from every frame)."""
    warn_seconds: float = 20.0
    """Targets shorter than this fit, with a warning that the result will be poor."""


GOOD_TARGET = "a good target shows one person facing the camera, talking for 1-3 minutes, with sound"


@contextlib.contextmanager
def _as_users_file(copy: Path, video: Path) -> Iterator[None]:
    """Errors and log messages about nvp's copy of the target (``<out>.partial/target.mp4``) name the
    user's ``video`` instead: the copy is an internal detail, the user knows their file."""
    names = sorted({str(copy), str(copy.resolve())}, key=len, reverse=True)

    def renamed(text: str) -> str:
        for name in names:
            text = text.replace(name, str(video))
        return text

    make = logging.getLogRecordFactory()

    def factory(*args, **kwargs) -> logging.LogRecord:
        record = make(*args, **kwargs)
        try:
            message = record.getMessage()
        except Exception:  # a malformed record is logging's to report
            return record
        if any(name in message for name in names):
            record.msg, record.args = renamed(message), ()
        return record

    logging.setLogRecordFactory(factory)
    try:
        yield
    except NvpError as e:
        if not isinstance(e, DiskFullError):  # that one is about writing the copy: it names the copy
            e.args = tuple(renamed(a) if isinstance(a, str) else a for a in e.args)
        raise
    finally:
        logging.setLogRecordFactory(make)


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
    force: bool = False,
) -> PersonBundle:
    """Build a person bundle from a talking-head video (1-3 minutes recommended).

    ``tracked``: the video's tracking when the caller already has it (skips the tracking stage);
    ``force``: replace a finished bundle of another video at ``out`` (refused otherwise)."""
    from nvp.bundle import check_output_folder, check_replacing, finished_bundle, input_hash, recover
    from nvp.media import probe_video
    from nvp.provenance import code_version

    video, out = Path(video), Path(out)
    check_output_folder(out, inputs=(video,))
    info = probe_video(video)
    if not info.has_audio:
        raise MediaError(f"{video} has no audio track: nvp fit needs the person's speech ({GOOD_TARGET})")
    if info.duration_s < cfg.min_seconds:
        raise NvpError(f"{video} lasts only {info.duration_s:.1f} s; {GOOD_TARGET}")
    if info.duration_s < cfg.warn_seconds:
        log.warning("%s lasts only %.1f s: expect a poor person (%s)", video, info.duration_s, GOOD_TARGET)
    _check_speech(video)
    config = {
        k: v
        for k, v in asdict(cfg).items()
        if k not in ("vgg_weights", "min_seconds", "warn_seconds")  # the device stays: it shapes the renderer
    }
    if cfg.vgg_weights is not None:  # the perceptual loss's weights shape the renderer: their content counts
        if not Path(cfg.vgg_weights).is_file():
            raise NvpError(f"the VGG-16 weights {cfg.vgg_weights} do not exist (--vgg-weights)")
        config["perceptual"] = input_hash(Path(cfg.vgg_weights))
    sha = input_hash(video)
    recover(out)  # finish a publish that was interrupted
    done = finished_bundle(out, config, sha)
    if done is not None:
        log.warning("%s is already fitted from %s with these settings; reusing it", out, video.name)
        return done
    if not force:
        check_replacing(out, sha)
    builder = BundleBuilder(out, config, sha, version=code_version())
    if progress:
        total, parts = expected_minutes(cfg, info.num_frames)
        print(
            f"nvp fit: expect {about_minutes(total)} ({parts}); an interrupted fit resumes",
            file=sys.stderr,
        )
    if builder.restarted:
        log.warning("%s held an interrupted fit %s; starting again", builder.work, builder.restarted)
    if builder.progress.get("stages"):  # every resumed run says so
        ckpt = builder.path("renderer") / "checkpoint.pt"
        training = not builder.done("renderer") and ckpt.exists()
        if training:  # one error line, before a resume line that would promise to go on from it
            from nvp.artifact import load_checkpoint

            load_checkpoint(ckpt)
        more = "; renderer training goes on from its last checkpoint" if training else ""
        if not builder.done("track") and tracked is None:
            more = _tracking_resumes(builder)
        done = ", ".join(builder.progress["stages"])
        print(f"nvp fit: resuming the interrupted fit in {builder.work} ({done} done{more})", file=sys.stderr)

    try:
        with _as_users_file(builder.path("target"), video):
            _stages(builder, video, cfg, progress, tracked)
    except (NoFaceError, MediaError):
        if not builder.done("track"):  # footage that cannot be tracked fails again: leave nothing behind
            shutil.rmtree(builder.work, ignore_errors=True)
        raise

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


def _stages(
    builder: BundleBuilder, video: Path, cfg: FitConfig, progress: bool, tracked: TrackedSequence | None
) -> None:
    """The stages of :func:`fit` that are not done yet, each marked done in ``builder`` when it is."""
    if not builder.done("target"):
        t0 = _stage("copy target")
        with atomic_path(builder.path("target")) as tmp:
            shutil.copyfile(video, tmp)
        builder.mark_done("target", source=str(video), seconds=round(time.perf_counter() - t0, 2))

    if not builder.done("track"):
        from tracking.detect import count_faces
        from tracking.track import track_video

        t0 = _stage("track")
        faces = count_faces(builder.path("target"))
        if faces > 1:
            log.warning(
                "%s shows %d faces in some frames; nvp fits the largest one (%s)",
                video.name,
                faces,
                GOOD_TARGET,
            )
        saves = builder.work / TRACKING_SAVES
        if tracked is None:
            seq = track_video(builder.path("target"), progress=progress, saves=saves)[0]
        else:
            seq = tracked
        seq.save(builder.path("tracked"))
        builder.mark_done(
            "track",
            frames=seq.num_frames,
            valid=int(seq.valid.sum()),
            seconds=round(time.perf_counter() - t0, 2),
        )

    shutil.rmtree(builder.work / TRACKING_SAVES, ignore_errors=True)
    _warn_about_faces(TrackedSequence.load(builder.path("tracked")), video, cfg.preset)

    if not builder.done("style"):
        from nvp.app.corpus import features_cached
        from nvp.audio2exp import default_audio2exp
        from nvp.face_model import default_face_model
        from nvp.opening import FEATURE_KIND, default_opening_model
        from nvp.person import VideoSample, style_from_sample, voiced_frames

        t0 = _stage("person style")
        seq = TrackedSequence.load(builder.path("tracked"))
        cache = builder.work / "cache"
        windows = features_cached(builder.path("target"), cache, cfg.features, seq.fps, seq.num_frames)
        opening_windows = features_cached(
            builder.path("target"), cache, FEATURE_KIND, seq.fps, seq.num_frames
        )
        net, manifest = default_audio2exp(cfg.features)
        sample = VideoSample(name=video.name, windows=windows, tracked=seq, opening_windows=opening_windows)
        voiced = voiced_frames(builder.path("target"), seq.fps, seq.num_frames)
        style = style_from_sample(
            net, manifest, sample, default_face_model(), voiced=voiced, opening=default_opening_model()
        )
        style.save(builder.path("style"))
        builder.mark_done("style", seconds=round(time.perf_counter() - t0, 2))

    if not builder.done("renderer"):
        t0 = _stage("renderer")
        trained = _train_renderer(builder, cfg, progress)
        builder.mark_done(
            "renderer",
            seconds=round(time.perf_counter() - t0, 2),
            steps=trained["steps"],
            start=trained["init"],
        )

    if not builder.done("register"):
        t0 = _stage("register")
        moved = _register(builder, cfg, progress)
        builder.mark_done("register", **moved, seconds=round(time.perf_counter() - t0, 2))
    shutil.rmtree(builder.work / UNREGISTERED, ignore_errors=True)

    from nvp.face_model import default_face_model

    if not builder.done("mouths"):
        from renderer.mouths import build_mouth_bank

        t0 = _stage("mouth bank")
        seq = TrackedSequence.load(builder.path("tracked"))
        bank = build_mouth_bank(builder.path("target"), seq, default_face_model())
        if bank is not None:
            bank.save(builder.path("renderer") / "mouths")
        n = 0 if bank is None else len(bank)
        builder.mark_done("mouths", entries=n, seconds=round(time.perf_counter() - t0, 2))


TRACKING_SAVES = "tracking"
"""The folder of the work folder where tracking saves its landmarks as it goes (removed once tracked)."""


def _tracking_resumes(builder: BundleBuilder) -> str:
    """What the resume line says about tracking: how far an interrupted tracking got (its saved frames)."""
    from tracking.track import saved_frames

    saves = builder.work / TRACKING_SAVES
    if not saves.is_dir():
        return ""
    done, total = saved_frames(builder.path("target"), saves)
    if done >= total:
        return f"; tracking's landmarks are all saved ({total} frames), the face model is fitted again"
    return f"; tracking goes on from frame {done} of {total}" if done else ""


TRACK_S_PER_FRAME = 0.02
"""Rough tracking time per frame on a 2-core CPU (for the estimate :func:`fit` prints at the start; AMD EPYC,
idle, two segments detected side by side: 17 ms at 512², 21 ms at 1080p)."""


def renderer_minutes(cfg: FitConfig, varied: bool = False) -> float | None:
    """The renderer's training time limit: ``--budget-minutes``, else (on a CPU, without ``--steps``) the
    preset's default time (longer for footage in several lights, ``varied``), so that a fit without flags
    ends on its own; None: steps only."""
    from renderer.preset import get_preset

    if cfg.budget_minutes is not None:
        return cfg.budget_minutes
    if cfg.steps is None and not cfg.device.startswith("cuda"):
        preset = get_preset(cfg.preset)
        return preset.varied_minutes if varied and preset.varied_minutes else preset.minutes
    return None


def renderer_steps(cfg: FitConfig) -> int | None:
    """The renderer's training steps: ``--steps``, else (with ``--budget-minutes`` alone) as many as the time
    allows (None), else the preset's."""
    from renderer.preset import get_preset

    if cfg.steps is not None:
        return cfg.steps
    return None if cfg.budget_minutes is not None else get_preset(cfg.preset).steps


def renderer_init(name: str) -> str | None:
    """``RendererTrainConfig.init`` for the ``--init`` option (``scratch`` → None)."""
    return None if name == "scratch" else name


def about_minutes(minutes: float) -> str:
    """``minutes`` as a fit announces them: "about 12 min", "under a minute" (half a minute rounds up:
    Python's rounding to even made 0.5 "about 0 min")."""
    return f"about {int(minutes + 0.5)} min" if minutes >= 0.5 else "under a minute"


def expected_minutes(cfg: FitConfig, frames: int) -> tuple[float, str]:
    """Rough wall time of a fit of ``frames`` frames and what it is made of (printed at the start)."""
    from renderer.preset import get_preset

    track = frames * TRACK_S_PER_FRAME / 60
    tracking = f"tracking {about_minutes(track)}"
    register = frames * REGISTER_S_PER_FRAME / 60
    train, steps = renderer_minutes(cfg), renderer_steps(cfg)
    per_step = None if cfg.device.startswith("cuda") else get_preset(cfg.preset).step_seconds
    if steps is not None and per_step is not None and (train is None or steps * per_step / 60 < train):
        limit = "" if train is None else f", at most {train:.0f} min"
        train = steps * per_step / 60
        return (
            track + train + register + 1,
            f"{tracking}, renderer training {about_minutes(train)} ({steps:,} steps{limit})",
        )
    if train is None:
        return track + register, f"{tracking}, then renderer training for {steps:,} steps"
    varied = renderer_minutes(cfg, varied=True)
    more = f", {varied:.0f} if the footage shows the face in several lights" if varied != train else ""
    return track + train + register + 1, f"{tracking}, renderer training {train:.0f} min{more}"


UNREGISTERED = "tracked_unregistered"
"""The tracker's own output, kept in the work folder while the registration stage rewrites ``tracked``."""

REGISTER_S_PER_FRAME = 0.02
"""Rough registration time per frame on a 2-core CPU (the face network on the mesh and an optical flow, two
frames side by side; AMD EPYC, idle: 16 ms a frame in a 5-minute fit of a 60 s 512² clip, about 21 ms at
1080p)."""


def _register(builder: BundleBuilder, cfg: FitConfig, progress: bool) -> dict:
    """Move every frame's tracked head to where the trained renderer sees it (:mod:`renderer.register`)
    and save that as the bundle's tracking; the tracker's own output is kept until the stage is done, so
    an interrupted stage starts again from it. Returns the offsets' summary."""
    from nvp.errors import FormatError
    from nvp.face_model import default_face_model
    from renderer.register import registered, registration_offsets

    raw = builder.work / UNREGISTERED
    try:
        seq = TrackedSequence.load(raw)
    except FormatError:  # the first attempt, or one interrupted while keeping it: tracked is untouched
        seq = TrackedSequence.load(builder.path("tracked"))
        seq.save(raw)
    offsets = registration_offsets(
        builder.path("renderer"),
        builder.path("target"),
        seq,
        np.arange(seq.num_frames),
        cfg.device,
        progress,
    )
    out = registered(seq, default_face_model(), offsets)
    out.save(builder.path("tracked"))
    return out.info["registration"]


NO_FACE_WARN_S = 1.0
"""Stretches of the target this long or longer without a face are reported (with their times)."""


def _warn_about_faces(seq: TrackedSequence, video: Path, preset: str) -> None:
    """Warn, before the renderer trains, about a face too small for ``preset`` (a renderer crop is 1.6
    face sizes: a face under ``crop / 3.2`` pixels is enlarged more than twice, and its landmarks are too
    coarse for a steady mouth) and about stretches of :data:`NO_FACE_WARN_S` or more without a face (a
    dub replays them with a guessed face)."""
    from renderer.preset import get_preset

    crop = get_preset(preset).crop
    found = ~np.isnan(seq.landmarks[..., 0]).all(1)
    if found.any():
        pts = seq.landmarks[found]
        size = float(np.median((np.nanmax(pts, 1) - np.nanmin(pts, 1)).max(1)))
        least = crop / 3.2
        if size < least:
            log.warning(
                "the face in %s is only about %.0f px across; the %s preset renders it in %d px crops and "
                "needs a face of %.0f px or more: expect a blurry, unsteady mouth (film closer or at a "
                "higher resolution; %s)",
                video,
                size,
                preset,
                crop,
                least,
                GOOD_TARGET,
            )
    edges = np.diff(np.concatenate([[0], (~found).astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    long = [(a, b) for a, b in zip(starts, ends, strict=True) if (b - a) / seq.fps >= NO_FACE_WARN_S]
    if long:
        times = ", ".join(f"{a / seq.fps:.1f}-{b / seq.fps:.1f} s" for a, b in long[:5])
        more = f" and {len(long) - 5} more" if len(long) > 5 else ""
        log.warning(
            "no face in %s at %s%s (%.0f s in all): a dub replays those frames with a guessed face; cut "
            "them out for a better person",
            video,
            times,
            more,
            sum(b - a for a, b in long) / seq.fps,
        )


def _check_speech(video: Path) -> None:
    """Refuse a target whose soundtrack holds no speech (a style solved from silence is meaningless)."""
    from nvp.media import read_audio
    from nvp.vad import speech_activity

    audio = read_audio(video, 16000)
    if len(audio) == 0 or not speech_activity(audio, 16000):
        raise NvpError(f"{video}: no speech found in its soundtrack; {GOOD_TARGET}")


def _train_renderer(builder: BundleBuilder, cfg: FitConfig, progress: bool) -> dict:
    """Cache the footage's crops once (``work/renderer_frames``), then train (resumable); returns the
    training summary (``renderer.train.train_renderer``)."""
    from nvp.errors import FormatError
    from nvp.face_model import default_face_model
    from renderer.preset import get_preset
    from renderer.train import RendererTrainConfig, train_renderer
    from renderer.train_data import CACHE_BUDGET_MB, VARIED_LIGHT_SHARE, FrameCache, build_cache, varied_light

    preset = get_preset(cfg.preset)
    seq = TrackedSequence.load(builder.path("tracked"))
    frames_path = builder.work / "renderer_frames.json"
    source = {"preset": cfg.preset, "frames": seq.num_frames, "budget_mb": CACHE_BUDGET_MB}
    try:
        cache = FrameCache.load(frames_path, source)
    except FormatError:  # missing, damaged or stale: rebuild
        model = default_face_model()
        cache = build_cache(builder.path("target"), seq, model, preset, np.flatnonzero(seq.valid), progress)
        cache.save(frames_path, source)
    minutes, longer = renderer_minutes(cfg), renderer_minutes(cfg, varied=True)
    if longer != minutes:
        share = varied_light(cache)
        if share >= VARIED_LIGHT_SHARE:
            log.warning(
                "%.0f %% of the footage shows the face in another light than the rest (other takes): the "
                "renderer trains %.0f minutes instead of %.0f to learn every light (--budget-minutes sets "
                "the time)",
                100 * share,
                longer,
                minutes,
            )
            minutes = longer
    budget = None if minutes is None else minutes * 60
    tcfg = RendererTrainConfig(
        preset=cfg.preset,
        steps=renderer_steps(cfg),
        budget_s=budget,
        vgg_weights=cfg.vgg_weights,
        init=renderer_init(cfg.renderer_init),
    )
    info = train_renderer(  # the fit's resume line has said that training goes on
        cache, tcfg, builder.path("renderer"), device=cfg.device, progress=progress, say_resume=False
    )
    for name in ("renderer_frames.json", "renderer_frames.npz"):
        (builder.work / name).unlink(missing_ok=True)
    (builder.path("renderer") / "checkpoint.pt").unlink(missing_ok=True)
    return info
