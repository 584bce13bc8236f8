"""The training commands: ``nvp train-audio2exp``, ``train-opening``, ``pretrain-renderer``,
``train-renderer``."""

from __future__ import annotations

import argparse
from pathlib import Path

from nvp.app.cli.common import (
    add_corpus_split_args,
    add_device_arg,
    add_features_arg,
    add_preset_arg,
    add_renderer_training_args,
    augmentations,
    device,
)


def add_train_audio2exp(sub) -> None:
    p = sub.add_parser("train-audio2exp", help="train the generic Audio2ExpressionNet on a folder of videos")
    p.add_argument("corpus", type=Path, help="folder of talking-head videos with audio")
    p.add_argument("-o", "--output", type=Path, required=True, help="output folder (checkpoints, best model)")
    add_features_arg(p)
    add_corpus_split_args(p)
    p.add_argument("--steps", type=int, default=4000, help="optimisation steps")
    p.add_argument(
        "--val-every", type=int, default=250, help="steps between validations (the best model is kept)"
    )
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument(
        "--closure-weight",
        type=float,
        default=1.0,
        help="weight of the closure head's loss (0: no closure head)",
    )
    p.add_argument("--cache", type=Path, help="tracking/feature cache (default: OUTPUT/cache)")
    p.set_defaults(func=run_train_audio2exp)


def run_train_audio2exp(args: argparse.Namespace) -> int:
    from nvp.app.train_audio2exp import Audio2ExpTrainConfig, train_on_corpus

    cfg = Audio2ExpTrainConfig(
        kind=args.features,
        steps=args.steps,
        seed=args.seed,
        val_every=args.val_every,
        closure_weight=args.closure_weight,
        augments=augmentations(args),
    )
    result = train_on_corpus(
        args.corpus, args.output, cfg, args.val, args.exclude, args.cache, not args.quiet
    )
    if result is None:  # another process of torchrun's: the main one reports
        return 0
    print(
        f"best validation mouth error {result['best_mouth_error_iod']:.4f} IOD → "
        f"{Path(args.output) / 'best.json'}"
    )
    return 0


def add_train_opening(sub) -> None:
    from nvp.audio_features import FEATURE_KINDS

    # an opening model reads its features as extracted (mel is speaker-normalised only for the network)
    opening_kinds = tuple(k for k in FEATURE_KINDS if k != "mel")
    p = sub.add_parser(
        "train-opening", help="fit the generic mouth-opening model (closed form) on a folder of videos"
    )
    p.add_argument("corpus", type=Path, help="folder of talking-head videos with audio")
    p.add_argument("-o", "--output", type=Path, required=True, help="output model (.npz + .json)")
    add_corpus_split_args(p)
    p.add_argument("--cache", type=Path, help="tracking/feature cache (default: next to OUTPUT)")
    p.add_argument(
        "--features",
        choices=opening_kinds,
        help="speech features the model reads (default: those of the shipped model; whisper_base_lN: "
        "multilingual Whisper base after layer N)",
    )
    p.set_defaults(func=run_train_opening)


def run_train_opening(args: argparse.Namespace) -> int:
    from nvp.app.train_opening import train_opening_on_corpus

    summary, validation = train_opening_on_corpus(
        args.corpus,
        args.output,
        args.val,
        args.exclude,
        args.cache,
        args.features,
        not args.quiet,
        augmentations(args),
    )
    print(
        f"ridge {summary['ridge']:g}: validation correlation {summary['validation_corr']:.3f} on "
        f"{validation} videos, {summary['train_frames']} training frames → "
        f"{Path(args.output).with_suffix('.json')}"
    )
    return 0


def add_pretrain_renderer(sub) -> None:
    from nvp.app.pretrain_renderer import MAX_FRAMES

    p = sub.add_parser(
        "pretrain-renderer", help="pre-train a generic neural renderer on a folder of talking-head videos"
    )
    p.add_argument("corpus", type=Path, help="folder of talking-head videos")
    p.add_argument("-o", "--output", type=Path, required=True, help="output folder (renderer.json/.npz)")
    add_preset_arg(p)
    p.add_argument("--budget-minutes", type=float, default=45.0, help="training time (resumable)")
    p.add_argument("--steps", type=int, help="train this many steps instead of for a time")
    p.add_argument("--max-frames", type=int, default=MAX_FRAMES, help="frames kept per video (evenly spread)")
    p.add_argument("--exclude", nargs="*", help="file names to leave out")
    p.add_argument("--cache", type=Path, help="tracking/frame cache (default: next to OUTPUT)")
    add_device_arg(p)
    p.set_defaults(func=run_pretrain_renderer)


def run_pretrain_renderer(args: argparse.Namespace) -> int:
    from nvp.app.pretrain_renderer import corpus_videos, pretrain_renderer

    out = Path(args.output)
    cache = Path(args.cache) if args.cache else out.parent / ".nvp-cache"
    videos = corpus_videos(Path(args.corpus), args.exclude)
    info = pretrain_renderer(
        videos,
        out,
        cache,
        args.preset,
        args.budget_minutes,
        args.steps,
        args.max_frames,
        device(args.device),
        progress=not args.quiet,
    )
    print(
        f"generic {args.preset} renderer: {len(info['videos'])} videos, {info['train_frames']} frames, "
        f"{info['steps']} steps in {info['train_seconds'] / 60:.1f} min → {out / 'renderer.json'}"
    )
    return 0


def add_train_renderer(sub) -> None:
    p = sub.add_parser("train-renderer", help="train the neural renderer on a tracked video")
    p.add_argument("track_dir", type=Path, help="output of nvp track for the video")
    p.add_argument("video", type=Path, help="the tracked video")
    p.add_argument("-o", "--output", type=Path, required=True, help="output folder (renderer.json/.npz)")
    add_renderer_training_args(p)
    p.add_argument("--train-fraction", type=float, default=1.0, help="train on this first part of the video")
    add_device_arg(p)
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--vgg-weights", type=Path, help="VGG-16 weights (torchvision .pth) for a perceptual loss")
    p.set_defaults(func=run_train_renderer)


def run_train_renderer(args: argparse.Namespace) -> int:
    from nvp.app.train_renderer import train_renderer_on_video

    result = train_renderer_on_video(
        args.track_dir,
        args.video,
        args.output,
        args.preset,
        args.steps,
        args.budget_minutes,
        args.seed,
        args.vgg_weights,
        args.init,
        args.train_fraction,
        device(args.device),
        not args.quiet,
    )
    print(
        f"trained the {args.preset} renderer on {result['train_frames']} frames: {result['steps']} steps in "
        f"{result['train_seconds'] / 60:.1f} min → {Path(args.output) / 'renderer.json'}"
    )
    return 0
