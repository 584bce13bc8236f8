"""``nvp say``: make a fitted person say a text (offline text to speech, then dub)."""

from __future__ import annotations

import argparse
from pathlib import Path

from nvp.app.cli.common import add_device_arg, add_style_arg, device


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
    add_style_arg(p)
    add_device_arg(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import tempfile

    import soundfile as sf

    from nvp.app.dub import dub
    from nvp.artifact import check_output_file
    from nvp.tts import have_piper, installed_voices, synthesize

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
    check_output_file(args.output)
    if args.wav is not None:
        check_output_file(args.wav)
    from nvp.bundle import check_output_place
    from nvp.errors import NvpError

    for out in (args.output, args.wav):  # never over an input, nor inside a person bundle
        if out is not None:
            check_output_place(out, (args.person, args.style))
    if args.wav is not None and Path(args.wav).resolve() == Path(args.output).resolve():
        raise NvpError(f"-o and --wav both name {args.output}; give the speech another name")
    speech = synthesize(args.text, length_scale=args.slower, voice=args.voice, engine=args.engine)
    with tempfile.TemporaryDirectory() as tmp:
        wav = Path(tmp) / "speech.wav"
        sf.write(wav, speech.audio, speech.rate)
        r = dub(
            wav,
            args.person,
            args.output,
            device=device(args.device),
            progress=not args.quiet,
            style=args.style,
            details={"speech": f"text to speech ({speech.engine}, voice {speech.voice})"},
            transcript=(args.text, speech.language) if have_piper() else None,  # its phonemizer aligns
        )
        if args.wav is not None:
            import shutil

            shutil.copyfile(wav, args.wav)
    print(
        f"{speech.seconds:.1f} s of speech ({speech.engine}, voice {speech.voice}), {r.frames} frames in "
        f"{r.seconds:.1f} s → {r.output}" + (f"; speech → {args.wav}" if args.wav else "")
    )
    return 0
