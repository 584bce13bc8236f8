"""``nvp live``: dub audio as it arrives (a file in real time, or raw PCM on stdin)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from nvp.app.cli.common import add_device_arg, add_gaze_arg, add_style_arg, device


def add_parser(sub) -> None:
    p = sub.add_parser("live", help="dub audio as it arrives (a file in real time, or raw PCM on stdin)")
    p.add_argument(
        "source", help="audio/video file played in real time, or - for raw s16le mono PCM on stdin"
    )
    p.add_argument("--person", type=Path, required=True, help="person bundle from nvp fit")
    p.add_argument("-o", "--output", type=Path, help="fragmented mp4, written as the frames are made")
    p.add_argument("--raw", action="store_true", help="raw RGB24 frames on stdout (for a player or a pipe)")
    p.add_argument("--rate", type=int, default=16000, help="sample rate of the PCM on stdin")
    p.add_argument(
        "--realtime",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="play a file at its real pace (--no-realtime: as fast as it can, every frame rendered)",
    )
    p.add_argument(
        "--max-lag", type=float, default=1.0, help="seconds behind the audio after which frames are dropped"
    )
    p.add_argument(
        "--fps",
        type=float,
        help="frames per second of the stream, at most the person's (default): a lower rate for a machine "
        "that drops frames",
    )
    add_gaze_arg(p)
    add_style_arg(p)
    add_device_arg(p)
    p.set_defaults(func=run)


def slower_hint(r) -> str:
    """When ``r`` (a :class:`nvp.app.live.LiveResult`) dropped frames: the stream rate this machine
    rendered, as a ``--fps`` to try (after 5 s of audio at least: before, the start-up weighs too much)."""
    if r.dropped <= 0.02 * r.frames or r.seconds <= 0 or r.audio_seconds < 5:
        return ""
    rendered = (r.frames - r.dropped) / r.seconds
    return f"; this machine rendered {rendered:.1f} frames/s: try --fps {max(1, int(rendered * 0.9))}"


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from nvp.app.live import live

    def status(text: str) -> None:
        if not args.quiet:
            print(f"\rnvp live: {text}   ", end="", file=sys.stderr, flush=True)

    raw = sys.stdout.buffer if args.raw else None
    if raw is not None and not args.quiet:
        from nvp.bundle import PersonBundle

        t = PersonBundle.load(args.person, verify=False).manifest["target"]  # live() checks it in full
        size, fps = f"{t['width']}x{t['height']}", f"{args.fps or t['fps']:.3f}"
        print(
            f"nvp live: raw RGB24 {size} at {fps} fps on stdout, e.g. | ffplay -f rawvideo "
            f"-pixel_format rgb24 -video_size {size} -framerate {fps} -",
            file=sys.stderr,
        )
    r = live(
        args.source,
        args.person,
        args.output,
        raw,
        device=device(args.device),
        realtime=args.realtime,
        rate=args.rate,
        style=args.style,
        gaze=args.gaze,
        max_lag_s=args.max_lag,
        status=status,
        fps=args.fps,
    )
    lat = r.latency_s[r.latency_s.size // 10 :] if r.latency_s.size > 10 else r.latency_s  # after warm-up
    print(
        ("\n" if not args.quiet else "")
        + f"{r.frames} frames for {r.audio_seconds:.1f} s of audio in {r.seconds:.1f} s; latency median "
        f"{np.median(lat):.2f} s, 95th percentile {np.percentile(lat, 95):.2f} s "
        f"(look-ahead {r.lookahead_s:.2f} s included); "
        f"{r.dropped} frames dropped ({r.dropped / max(r.frames, 1):.0%})"
        + (f" → {args.output}" if args.output else "")
        + slower_hint(r),
        file=sys.stderr if args.raw else sys.stdout,
    )
    return 0
