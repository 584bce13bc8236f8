"""``nvp track``: track a talking-head video with the face model."""

from __future__ import annotations

import argparse
from pathlib import Path

from nvp.app.cli.common import nanmedian


def add_parser(sub) -> None:
    p = sub.add_parser("track", help="track a talking-head video with the face model")
    p.add_argument("video", type=Path, help="input video (mp4, mov, mkv, ...)")
    p.add_argument("-o", "--output", type=Path, required=True, help="output directory for tracked.json/.npz")
    p.add_argument("--preview", type=Path, help="also write an mp4 with the fitted mesh over the footage")
    p.add_argument(
        "--save-detections", action="store_true", help="also keep the raw landmarks (detections.npz)"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tracking.fit import TrackingConfig
    from tracking.preview import write_preview
    from tracking.track import track_video

    seq, det = track_video(args.video, progress=not args.quiet, cfg=TrackingConfig())
    out = seq.save(args.output)
    if args.save_detections:
        det.save(Path(args.output) / "detections.npz")
    valid = int(seq.valid.sum())
    print(
        f"tracked {seq.num_frames} frames ({valid} valid, {seq.num_frames - valid} bridged) "
        f"in {seq.info['total_seconds']:.1f} s; median fit error {nanmedian(seq.fit_error):.2f} px → {out}"
    )
    if args.preview:
        write_preview(args.video, seq, args.preview, progress=not args.quiet)
        print(f"preview → {args.preview}")
    return 0
