"""``nvp train-renderer``: the neural renderer trained on one tracked video."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nvp.app.fit import renderer_init
from nvp.errors import NvpError
from nvp.face_model import default_face_model
from nvp.media import probe_video
from nvp.tracked import TrackedSequence


def train_renderer_on_video(
    track_dir: Path,
    video: Path,
    output: Path,
    preset: str = "cpu",
    steps: int | None = None,
    budget_minutes: float | None = None,
    seed: int = 0,
    vgg_weights: Path | None = None,
    init: str = "generic",
    train_fraction: float = 1.0,
    device: str = "cpu",
    progress: bool = True,
) -> dict:
    """Train the ``preset`` renderer on the first ``train_fraction`` of ``video`` (tracked in
    ``track_dir``) into ``output`` (``renderer.json`` / ``.npz``); the other arguments as
    :class:`renderer.train.RendererTrainConfig` takes them (``init``: ``generic``, ``scratch`` or a renderer
    folder). Returns the training's summary."""
    from renderer.preset import get_preset
    from renderer.train import RendererTrainConfig, train_renderer
    from renderer.train_data import build_cache

    seq = TrackedSequence.load(track_dir)
    info = probe_video(video)
    if (info.width, info.height) != (seq.width, seq.height) or abs(info.num_frames - seq.num_frames) > 1:
        raise NvpError(
            f"{video} ({info.width}x{info.height}, {info.num_frames} frames) is not the video "
            f"tracked in {track_dir} ({seq.width}x{seq.height}, {seq.num_frames} frames)"
        )
    split = int(round(seq.num_frames * train_fraction))
    cache = build_cache(video, seq, default_face_model(), get_preset(preset), np.arange(split), progress)
    cfg = RendererTrainConfig(
        preset=preset,
        steps=steps,
        budget_s=None if budget_minutes is None else budget_minutes * 60,
        seed=seed,
        vgg_weights=str(vgg_weights) if vgg_weights else None,
        init=renderer_init(init),
    )
    return train_renderer(cache, cfg, Path(output), device=device, progress=progress)
