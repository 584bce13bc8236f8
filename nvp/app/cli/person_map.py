"""``nvp person-map``: a person's talking style (closed form) from their video."""

from __future__ import annotations

import argparse
from pathlib import Path

from nvp.app.cli.common import add_features_arg


def add_parser(sub) -> None:
    p = sub.add_parser("person-map", help="learn a person's talking style (closed form) from their video")
    p.add_argument("video", type=Path, help="the person talking (video with audio)")
    p.add_argument("-o", "--output", type=Path, required=True, help="output person map (.npz + .json)")
    add_features_arg(p)
    p.add_argument("--cache", type=Path, help="tracking/feature cache folder")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from nvp.app.person_map import person_map

    frames, js = person_map(args.video, args.output, args.features, args.cache, not args.quiet)
    print(f"person map from {frames} frames → {js}")
    return 0
