"""``nvp pretrain-renderer``: a generic neural renderer from a corpus of talking-head videos.

Every video is tracked (cached), its crops are cut once (at most ``max_frames`` per video, evenly spread,
cached), and one renderer is trained on all of them: the networks are shared, each video has its own
texture (:func:`renderer.train.train_renderer` with many caches). The result, saved with the videos' mean
texture, is where a person's renderer training starts (``RendererTrainConfig.init``), so that ``nvp fit``
needs minutes instead of an hour.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from nvp.errors import FormatError, NvpError

log = logging.getLogger(__name__)

MAX_FRAMES = 250
"""Frames kept per video (evenly spread): 31 videos of 3-71 s take about 3 GB at the ``cpu`` preset's crop,
and neighbouring frames add little."""


def corpus_videos(folder: Path, exclude: list[str] | None = None) -> list[Path]:
    """The videos of ``folder`` (sorted by name) except the file names in ``exclude``."""
    from nvp.app.corpus import VIDEO_SUFFIXES

    videos = sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in VIDEO_SUFFIXES)
    videos = [v for v in videos if v.name not in set(exclude or [])]
    if not videos:
        raise NvpError(f"no videos ({', '.join(VIDEO_SUFFIXES)}) in {folder}")
    return videos


def video_frames(video: Path, cache: Path, preset_name: str, max_frames: int, progress: bool):
    """The renderer's training frames of one video (``renderer.train_data.FrameCache``), built once and
    kept in ``cache/renderer_frames``."""
    from nvp.app.corpus import cache_key, tracked_cached
    from nvp.face_model import default_face_model
    from renderer.preset import get_preset
    from renderer.train_data import FrameCache, build_cache, cache_frame_bytes

    preset, model = get_preset(preset_name), default_face_model()
    key = cache_key(video)
    path = cache / "renderer_frames" / f"{key}_{preset.name}_{max_frames}.json"
    source = {"video": key, "preset": preset.name, "max_frames": max_frames}
    try:
        return FrameCache.load(path, source)
    except FormatError:  # missing, damaged or made with other settings
        pass
    seq = tracked_cached(video, cache, progress)
    budget_mb = max_frames * cache_frame_bytes(preset.crop, model.num_vertices) / 2**20
    frames = build_cache(video, seq, model, preset, np.flatnonzero(seq.valid), progress, budget_mb)
    if len(frames.frames) == 0:
        raise NvpError(f"{video.name}: no frame with a tracked face")
    frames.save(path, source)
    return frames


def pretrain_renderer(
    videos: list[Path],
    out: Path,
    cache: Path,
    preset_name: str = "cpu",
    budget_minutes: float = 45.0,
    steps: int | None = None,
    max_frames: int = MAX_FRAMES,
    device: str = "cpu",
    progress: bool = True,
) -> dict:
    """Train the generic renderer on ``videos`` for ``budget_minutes`` (or ``steps``), resumable; writes
    ``out/renderer.{json,npz}`` (float16 weights: a starting point) and returns the training summary. A
    video without a usable face is skipped with a warning.

    Under ``torchrun`` every process computes a share of each batch (:func:`renderer.train.train_renderer`);
    the main process tracks the videos and cuts their frames first, the others then read them."""
    from nvp.app.distributed import process_group
    from renderer.networks import load_renderer, save_renderer
    from renderer.train import RendererTrainConfig, train_renderer

    group = process_group(device)
    caches, names = [], []
    for turn in (True, False):  # the main process first (it writes the caches), then the others
        if turn == group.main:
            for v in videos:
                try:
                    caches.append(video_frames(v, cache, preset_name, max_frames, progress and group.main))
                    names.append(v.name)
                except NvpError as e:
                    log.warning("skipping %s: %s", v.name, e)
        group.barrier()
    if len(caches) < 2:
        raise NvpError(f"a generic renderer needs at least 2 usable videos, found {len(caches)}")
    cfg = RendererTrainConfig(
        preset=preset_name,
        steps=steps,
        budget_s=None if steps else budget_minutes * 60,
        init=None,
        checkpoint_every=500,
        preview_every=2000,
    )
    info = train_renderer(caches, cfg, out, device=device, progress=progress, names=names, group=group)
    if group.main:
        net, preset, manifest = load_renderer(out)
        drop = ("format", "version", "arrays", "bytes", "sha256")
        keep = {k: v for k, v in manifest.items() if k not in drop}
        save_renderer(net, out, preset, {**keep, "max_frames_per_video": max_frames}, half=True)
    group.barrier()
    return info
