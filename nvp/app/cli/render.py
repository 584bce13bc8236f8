"""``nvp render``: re-render a tracked video with its trained renderer."""

from __future__ import annotations

import argparse
from pathlib import Path

from nvp.app.cli.common import add_device_arg, device


def add_parser(sub) -> None:
    p = sub.add_parser("render", help="re-render a tracked video with its trained renderer")
    p.add_argument("track_dir", type=Path, help="output of nvp track")
    p.add_argument("renderer_dir", type=Path, help="output of nvp train-renderer")
    p.add_argument("video", type=Path, help="the tracked video")
    p.add_argument("-o", "--output", type=Path, required=True, help="output mp4")
    p.add_argument("--start-frame", type=int, default=0, help="first frame to render")
    p.add_argument("--frames", type=int, help="number of frames (default: to the end)")
    add_device_arg(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from nvp.app.render import rerender

    n = rerender(
        args.track_dir,
        args.renderer_dir,
        args.video,
        args.output,
        args.start_frame,
        args.frames,
        device(args.device),
        not args.quiet,
    )
    print(f"rendered {n} frames → {args.output}")
    return 0
