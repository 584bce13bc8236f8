"""``nvp say``: make a fitted person say a text (offline text to speech, then dub)."""

from __future__ import annotations

import argparse
from pathlib import Path

from nvp.app.cli.common import add_device_arg, add_gaze_arg, add_style_arg, device


def add_parser(sub) -> None:
    p = sub.add_parser("say", help="make a fitted person say a text (offline text to speech, then dub)")
    p.add_argument("text", nargs="?", help="what the person says")
    p.add_argument("--person", type=Path, help="person bundle from nvp fit")
    p.add_argument("-o", "--output", type=Path, help="output mp4")
    p.add_argument(
        "--voice", help="piper voice: an installed voice's name (see --list-voices) or a .onnx voice file"
    )
    p.add_argument(
        "--engine",
        choices=("auto", "piper", "espeak-ng"),
        default="auto",
        help="speech engine (auto: piper when installed, else espeak-ng)",
    )
    p.add_argument("--slower", type=float, default=1.0, help="speaking slowness (>1 slower, <1 faster)")
    p.add_argument("--wav", type=Path, help="also keep the speech here")
    p.add_argument("--list-voices", action="store_true", help="list the installed piper voices and exit")
    add_gaze_arg(p)
    add_style_arg(p)
    add_device_arg(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from nvp.tts import installed_voices

    if args.list_voices:
        voices = installed_voices()
        for name, (model, _) in sorted(voices.items()):
            print(f"{name}\t{model}")
        if not voices:
            print("no piper voice installed (pip install 'nvp[tts]')")
        return 0
    if args.text is None or args.person is None or args.output is None:
        from nvp.errors import NvpError

        raise NvpError("give the text, --person and -o (or --list-voices)")
    from nvp.app.say import say

    speech, r = say(
        args.text,
        args.person,
        args.output,
        args.wav,
        args.voice,
        args.engine,
        args.slower,
        device(args.device),
        not args.quiet,
        args.style,
        args.gaze,
    )
    print(
        f"{speech.seconds:.1f} s of speech ({speech.engine}, voice {speech.voice}), {r.frames} frames in "
        f"{r.seconds:.1f} s → {r.output}" + (f"; speech → {args.wav}" if args.wav else "")
    )
    return 0
