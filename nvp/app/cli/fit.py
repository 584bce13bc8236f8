"""``nvp fit``: learn a person from 1-3 minutes of their talking video."""

from __future__ import annotations

import argparse
from pathlib import Path

from nvp.app.cli.common import (
    add_device_arg,
    add_features_arg,
    add_renderer_training_args,
    renderer_training_options,
)


def add_parser(sub) -> None:
    p = sub.add_parser("fit", help="learn a person from 1-3 minutes of their talking video")
    p.add_argument("video", type=Path, help="the person talking (video with audio)")
    p.add_argument("-o", "--output", type=Path, required=True, help="person bundle folder")
    add_renderer_training_args(p)
    add_features_arg(p)
    add_device_arg(p)
    p.add_argument("--vgg-weights", type=Path, help="VGG-16 weights (torchvision .pth) for a perceptual loss")
    p.add_argument(
        "--force", action="store_true", help="replace a finished person bundle of another video at -o"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from nvp.app.fit import FitConfig, fit

    cfg = FitConfig(
        **renderer_training_options(args),
        features=args.features,
        vgg_weights=str(args.vgg_weights) if args.vgg_weights else None,
    )
    bundle = fit(args.video, args.output, cfg, progress=not args.quiet, force=args.force)
    st = bundle.manifest["stages"]
    total = sum(v.get("seconds", 0) for v in st.values())
    print(f"person bundle → {bundle.root} (fit took {total / 60:.1f} min)")
    return 0
