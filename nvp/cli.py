"""The one nvp command line. Heavy modules are imported inside the command that needs them."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from nvp import __version__


def _cmd_track(args: argparse.Namespace) -> int:
    from tracking.fit import FitConfig
    from tracking.preview import write_preview
    from tracking.track import track_video

    seq, det = track_video(args.video, progress=not args.quiet, cfg=FitConfig())
    out = seq.save(args.output)
    if args.save_detections:
        det.save(Path(args.output) / "detections.npz")
    valid = int(seq.valid.sum())
    print(
        f"tracked {seq.num_frames} frames ({valid} valid, {seq.num_frames - valid} bridged) "
        f"in {seq.info['total_seconds']:.1f} s; median fit error {_nanmedian(seq.fit_error):.2f} px → {out}"
    )
    if args.preview:
        write_preview(args.video, seq, args.preview, progress=not args.quiet)
        print(f"preview → {args.preview}")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from nvp.demo import run_demo

    result = run_demo(Path(args.output), progress=not args.quiet)
    print(result)
    return 0


def _nanmedian(x):
    import numpy as np

    return float(np.nanmedian(x)) if np.isfinite(x).any() else float("nan")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="nvp", description="Neural Voice Puppetry: audio-driven facial reenactment."
    )
    ap.add_argument("--version", action="version", version=f"nvp {__version__}")
    ap.add_argument("-v", "--verbose", action="store_true", help="log details")
    ap.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("track", help="track a talking-head video with the face model")
    p.add_argument("video", type=Path, help="input video (mp4, mov, mkv, ...)")
    p.add_argument("-o", "--output", type=Path, required=True, help="output directory for tracked.json/.npz")
    p.add_argument("--preview", type=Path, help="also write an mp4 with the fitted mesh over the footage")
    p.add_argument(
        "--save-detections", action="store_true", help="also keep the raw landmarks (detections.npz)"
    )
    p.set_defaults(func=_cmd_track)

    p = sub.add_parser("demo", help="make the shipped demo clip and run the pipeline on it")
    p.add_argument("-o", "--output", type=Path, default=Path("nvp-demo"), help="output directory")
    p.set_defaults(func=_cmd_demo)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(message)s"
    )
    from nvp.errors import NvpError

    try:
        return args.func(args)
    except NvpError as e:
        print(f"nvp {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"nvp {args.command}: interrupted", file=sys.stderr)
        return 130
    except OSError as e:  # disk full, permissions, ...
        print(f"nvp {args.command}: error: {e.strerror or e} ({e.filename or ''})", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
