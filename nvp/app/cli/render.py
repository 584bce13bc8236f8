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
    import numpy as np

    from nvp.artifact import check_output_file
    from nvp.face_model import default_face_model
    from nvp.media import VideoWriter, audio_rate, has_audio, iter_frames, read_audio
    from nvp.provenance import synthetic_mark
    from nvp.tracked import TrackedSequence
    from renderer.loop import render_frames
    from renderer.render import FrameRenderer

    check_output_file(args.output, inputs=(args.video,))
    seq = TrackedSequence.load(args.track_dir)
    start = args.start_frame
    n = seq.num_frames - start if args.frames is None else min(args.frames, seq.num_frames - start)
    audio, rate = None, 48000
    if has_audio(args.video):
        rate = audio_rate(args.video)
        audio = read_audio(args.video, None, mono=False)[int(start / seq.fps * rate) :]
    tags = synthetic_mark("render", renderer=str(args.renderer_dir))
    with (
        FrameRenderer(args.renderer_dir, default_face_model(), seq, device(args.device)) as fr,
        VideoWriter(args.output, seq.fps, seq.width, seq.height, audio, rate, metadata=tags) as vw,
    ):
        frames = iter_frames(args.video, seq.fps, start, n)
        for _, made in render_frames(
            fr, frames, np.arange(start, start + n), {"render": None}, not args.quiet
        ):
            vw.write(made["render"])
    print(f"rendered {n} frames → {args.output}")
    return 0
