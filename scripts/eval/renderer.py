"""Self-reenactment with visual tracking: train the renderer on the first 80 % of a video, re-render the
last 20 % from its tracked geometry, compare with the real frames.

    python -m scripts.eval.renderer [--videos A.mp4 ...] [--preset cpu] [--budget-minutes 45]

Per video: training (``renderer.train.train_renderer`` with a wall-clock budget; resumes if interrupted),
then PSNR / SSIM on the full frame and on the face crop (the stabilised crop box, at the footage's
resolution) over every held-out frame, training time and steps, render frames/s. Writes results.{md,json}
and side-by-side PNGs (real | rendered) of the held-out frames with the mouth most open, most closed and
the head turned furthest.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from scripts.common import VIDEOS, data_missing

SHARED = VIDEOS
DEFAULT_VIDEOS = ["dfrf__cnn2_25fps.mp4", "mimictalk__German_20s.mp4", "styletalk__Obama_clip2_av.mp4"]


def evaluate(
    video: Path,
    out: Path,
    preset: str,
    budget_min: float,
    cache_dir: Path,
    steps: int | None = None,
    source_input: bool | None = None,
    detail_weight: float = 0.0,
    source_gap_s: tuple[float, float] | None = None,
    adversarial_weight: float = 0.0,
    init: str = "generic",
    train_options: dict | None = None,
) -> dict:
    from nvp.app.corpus import tracked_cached
    from nvp.app.fit import renderer_init
    from nvp.errors import FormatError
    from nvp.face_model import default_face_model
    from nvp.media import iter_frames
    from nvp.metrics import psnr, ssim
    from renderer.crop import box_slices
    from renderer.loop import render_frames
    from renderer.preset import get_preset
    from renderer.render import FrameRenderer
    from renderer.train import RendererTrainConfig, train_renderer
    from renderer.train_data import FrameCache, build_cache

    chosen = get_preset(preset)
    if source_input is not None:
        chosen = replace(chosen, source_input=source_input)

    model = default_face_model()
    seq = tracked_cached(video, cache_dir, progress=False)
    split = int(round(seq.num_frames * 0.8))
    out.mkdir(parents=True, exist_ok=True)
    # trains, or resumes an interrupted training, or returns at once when the budget is already spent
    cp, source = out / "train_cache.json", {"video": video.name, "preset": preset, "frames": split}
    try:
        cache = FrameCache.load(cp, source)
    except FormatError:  # missing, damaged or made from other settings
        cache = build_cache(video, seq, model, chosen, np.arange(split))
        cache.save(cp, source)
    settings = {
        "preset": preset,
        "steps": steps,
        "budget_s": None if steps else budget_min * 60,
        "detail_weight": detail_weight,
        "adversarial_weight": adversarial_weight,
        "init": renderer_init(init),
        **({"source_gap_s": tuple(source_gap_s)} if source_gap_s else {}),
    }
    cfg = RendererTrainConfig(**settings | (train_options or {}))  # --train's fields over the others
    train_renderer(cache, cfg, out, preset=chosen)
    manifest = json.loads((out / "renderer.json").read_text())
    test = np.arange(split, seq.num_frames)
    rows, t_render = [], 0.0
    keep = {}
    gap = model.inner_lip_gap(seq.identity, seq.expression)
    yaw = np.abs(np.degrees(np.arctan2(seq.rotation[:, 0, 2], seq.rotation[:, 2, 2])))
    picks = {
        "mouth_open": int(test[np.argmax(gap[test])]),
        "mouth_closed": int(test[np.argmin(gap[test])]),
        "head_turned": int(test[np.argmax(yaw[test])]),
    }
    with FrameRenderer(out, model, seq) as fr:
        frames = iter_frames(video, fps=seq.fps, start_frame=split)
        t0 = time.perf_counter()
        for t, (frame, made) in zip(test, render_frames(fr, frames, test, {"re": None}, False), strict=False):
            t_render += time.perf_counter() - t0
            img = made["re"]
            ys, xs = box_slices(fr.boxes[t], *frame.shape[:2])
            crop, img_crop = frame[ys, xs], img[ys, xs]
            rows.append((psnr(frame, img), ssim(frame, img), psnr(crop, img_crop), ssim(crop, img_crop)))
            if t in picks.values():
                keep[int(t)] = np.concatenate([frame[ys, xs], img[ys, xs]], 1)
            t0 = time.perf_counter()
    from PIL import Image

    for name, t in picks.items():
        if t in keep:
            Image.fromarray(keep[t]).save(out / f"side_{name}_{t}.png")
    r = np.array(rows)
    return {
        "video": video.name,
        "size": f"{seq.width}x{seq.height}",
        "train_frames": manifest["train_frames"],
        "test_frames": len(rows),
        "preset": manifest["preset"]["name"],
        "init": manifest.get("init", "scratch").split(":")[0],
        "steps": manifest["steps"],
        "train_minutes": round(manifest["train_seconds"] / 60, 1),
        "psnr_full": float(r[:, 0].mean()),
        "ssim_full": float(r[:, 1].mean()),
        "psnr_crop": float(r[:, 2].mean()),
        "ssim_crop": float(r[:, 3].mean()),
        "render_fps": len(rows) / t_render,
    }


def add_variant_arguments(ap: argparse.ArgumentParser) -> None:
    """Options that train a variant of the preset (for comparing it with the shipped one)."""
    ap.add_argument(
        "--source-input",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="feed the face network the footage's moved pixels (Preset.source_input; default: the preset's)",
    )
    ap.add_argument(
        "--detail-weight",
        type=float,
        default=0.0,
        help="weight of the high-frequency loss (RendererTrainConfig)",
    )
    ap.add_argument(
        "--source-gap",
        type=float,
        nargs=2,
        metavar=("LO", "HI"),
        help="seconds between a training crop and its moved source frame (RendererTrainConfig.source_gap_s)",
    )
    ap.add_argument(
        "--adversarial-weight", type=float, default=0.0, help="weight of the patch-adversarial loss"
    )
    ap.add_argument(
        "--train",
        nargs="+",
        default=[],
        metavar="FIELD=VALUE",
        help="other RendererTrainConfig fields (numbers), e.g. lr=2e-3 lr_final=0.1",
    )
    ap.add_argument(
        "--init",
        default="generic",
        help="start of the training: generic (the shipped pre-trained renderer), scratch, or a folder",
    )


def train_options(pairs: list[str]) -> dict:
    """``--train FIELD=VALUE ...`` as RendererTrainConfig keyword arguments (a bad one: one clear error)."""
    from dataclasses import fields

    from renderer.train import RendererTrainConfig

    known = {f.name for f in fields(RendererTrainConfig)}
    out = {}
    for pair in pairs:
        key, _, value = pair.partition("=")
        try:
            number = float(value)
        except ValueError:
            number = None
        if key not in known or number is None:
            raise SystemExit(f"--train {pair}: expected FIELD=NUMBER with FIELD one of {sorted(known)}")
        out[key] = int(number) if value.lstrip("-").isdigit() else number
    return out


def main(argv: list[str] | None = None) -> int:
    from nvp.app.report import write_results

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--videos", nargs="+", default=DEFAULT_VIDEOS)
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--budget-minutes", type=float, default=45.0)
    ap.add_argument("--steps", type=int, help="train this many steps instead of for a time budget")
    ap.add_argument("--cache", type=Path, default=Path("out/a2e/cache"), help="tracking cache")
    ap.add_argument("--out", type=Path, default=Path("out/eval_renderer"))
    add_variant_arguments(ap)
    args = ap.parse_args(argv)
    if data_missing(SHARED):
        return 0
    rows = [
        evaluate(
            SHARED / v,
            args.out / Path(v).stem,
            args.preset,
            args.budget_minutes,
            args.cache,
            args.steps,
            args.source_input,
            args.detail_weight,
            args.source_gap,
            args.adversarial_weight,
            args.init,
            train_options(args.train),
        )
        for v in args.videos
    ]
    print(write_results(rows, args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
