"""``nvp predict``: a person's expressions (and mesh, or a glTF animation) for new audio."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub) -> None:
    p = sub.add_parser("predict", help="predict a person's expressions (and mesh) for new audio")
    p.add_argument("audio", type=Path, help="speech (wav, flac, mp3, m4a, or a video's audio track)")
    p.add_argument(
        "--style",
        type=Path,
        required=True,
        help="person bundle folder (nvp fit) or person map (nvp person-map)",
    )
    p.add_argument("--fps", type=float, default=25.0, help="output frame rate")
    p.add_argument(
        "--mesh",
        type=Path,
        metavar="TRACK_DIR",
        help="face to animate (default: the bundle's, else the mean face)",
    )
    p.add_argument("-o", "--output", type=Path, help="output .npz (expression; vertices with a face)")
    p.add_argument("--export", type=Path, help="output glTF 2.0 animation (.glb): morph targets + weights")
    p.add_argument(
        "--gaze",
        default="camera",
        metavar="camera|FILE",
        help="where the export's eyes look: camera (straight ahead, the default) or a CSV / JSON file of "
        "time_s, yaw_deg, pitch_deg rows (see docs/commands.md)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from nvp.app.predict import predict

    frames, whose, outputs = predict(
        args.audio, args.style, args.fps, args.mesh, args.output, args.export, args.gaze
    )
    print(f"{frames} frames of expressions at {args.fps} fps ({whose}) → " + ", ".join(map(str, outputs)))
    return 0
