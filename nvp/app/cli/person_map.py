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
    from dataclasses import replace

    from nvp.app.corpus import load_sample
    from nvp.audio2exp import default_audio2exp
    from nvp.face_model import default_face_model
    from nvp.opening import FEATURE_KIND, default_opening_model
    from nvp.person import style_from_sample, voiced_frames

    net, manifest = default_audio2exp(args.features)
    cache = Path(args.cache) if args.cache else Path(args.output).parent / ".nvp-cache"
    sample = load_sample(Path(args.video), cache, args.features, progress=not args.quiet)
    opening_windows = load_sample(Path(args.video), cache, FEATURE_KIND, progress=False).windows
    sample = replace(sample, opening_windows=opening_windows)
    voiced = voiced_frames(Path(args.video), sample.tracked.fps, sample.tracked.num_frames)
    opening = default_opening_model()
    style = style_from_sample(net, manifest, sample, default_face_model(), voiced=voiced, opening=opening)
    js = style.save(Path(args.output))
    print(f"person map from {int(sample.valid.sum())} frames → {js}")
    return 0
