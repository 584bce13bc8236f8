"""``nvp dub``: make a fitted person say new audio (one file, several, or a list)."""

from __future__ import annotations

import argparse
from pathlib import Path

from nvp.app.cli.common import add_device_arg, add_gaze_arg, add_style_arg, device, run_each
from nvp.app.cluster import add_cluster_arg


def add_parser(sub) -> None:
    p = sub.add_parser("dub", help="make a fitted person say new audio")
    p.add_argument(
        "audio",
        type=Path,
        nargs="*",
        help="speech: wav, flac, mp3, m4a (or a video's audio track); several ok",
    )
    p.add_argument("--list", type=Path, help="a text file naming more audio files, one per line")
    p.add_argument("--person", type=Path, required=True, help="person bundle from nvp fit")
    p.add_argument(
        "--transcript",
        type=Path,
        help="UTF-8 text file: what the audio says; its p, b and m close the lips (needs the tts extra)",
    )
    p.add_argument(
        "--language",
        default="en-us",
        help="the transcript's language, an espeak-ng voice name (en-us, fr, de, es, it, pt, hi, cmn, ...)",
    )
    p.add_argument(
        "-o", "--output", type=Path, required=True, help="output mp4 (a folder for several: <audio name>.mp4)"
    )
    add_gaze_arg(p)
    add_style_arg(p)
    add_device_arg(p)
    add_cluster_arg(p)
    p.set_defaults(func=run)


def _audio_files(args: argparse.Namespace) -> list[Path]:
    """The audio named on the command line, then those of ``--list`` (relative to the list's folder)."""
    from nvp.errors import NvpError

    audios = [Path(a) for a in args.audio]
    if args.list:
        try:
            lines = Path(args.list).read_text().splitlines()
        except (OSError, UnicodeDecodeError) as e:
            raise NvpError(f"cannot read the list {args.list}: {e}") from e
        base = Path(args.list).parent
        audios += [base / x.strip() for x in lines if x.strip() and not x.lstrip().startswith("#")]
    if not audios:
        raise NvpError("give the audio to dub (files, or --list FILE with one per line)")
    return audios


def _on_cluster(args: argparse.Namespace, audios: list[Path], address: str) -> int:
    from nvp.app.cluster import absolute, run_inputs
    from nvp.gaze import gaze_file

    def argv_of(audio: Path) -> list[str]:
        argv = ["dub", absolute(audio), "--person", absolute(args.person), "--device", args.device]
        argv += ["-o", absolute(Path(args.output) / f"{audio.stem}.mp4")]
        argv += ["--gaze", args.gaze if gaze_file(args.gaze) is None else absolute(gaze_file(args.gaze))]
        return argv + (["--style", absolute(args.style)] if args.style else [])

    code, _ = run_inputs("dub", audios, argv_of, address, args.output, "dubbed", progress=not args.quiet)
    return code


def run(args: argparse.Namespace) -> int:
    from nvp.app.cluster import head_address
    from nvp.app.dub import dub
    from nvp.errors import NvpError

    audios = _audio_files(args)
    several = len(audios) > 1
    transcript = None
    if args.transcript is not None:
        if several:
            raise NvpError("--transcript is the text of one audio file; dub the files one by one")
        try:
            transcript = (Path(args.transcript).read_text(encoding="utf-8"), args.language)
        except (OSError, UnicodeDecodeError) as e:
            raise NvpError(f"cannot read the transcript {args.transcript}: {e}") from e
    if several:
        if Path(args.output).suffix.lower() == ".mp4" or Path(args.output).is_file():
            raise NvpError(
                f"several audio files are dubbed into a folder: -o {Path(args.output).with_suffix('')}/"
            )
        stems = [a.stem for a in audios]
        twice = sorted({x for x in stems if stems.count(x) > 1})
        if twice:
            raise NvpError(f"two audio files would both be written as {twice[0]}.mp4; rename one")
    from nvp.bundle import check_output_place

    for audio in audios:  # before any work: no output over an input, none inside a person bundle
        out = Path(args.output) / f"{audio.stem}.mp4" if several else Path(args.output)
        check_output_place(out, (*audios, args.list, args.person, args.style))
    if several and head_address(args.cluster):  # one job per file on the cluster's workers
        return _on_cluster(args, audios, head_address(args.cluster))

    def dub_one(i: int, audio: Path) -> None:
        out = Path(args.output) / f"{audio.stem}.mp4" if several else Path(args.output)
        r = dub(
            audio,
            args.person,
            out,
            device=device(args.device),
            progress=not args.quiet,
            style=args.style,
            transcript=transcript,
            gaze=args.gaze,
        )
        print(
            (f"[{i + 1}/{len(audios)}] " if several else "")
            + f"{r.frames} frames ({r.frames / r.fps:.2f} s for {r.audio_seconds:.2f} s of audio) in "
            f"{r.seconds:.1f} s ({r.rendered / r.seconds:.1f} frames/s"
            + ("" if r.rendered == r.frames else f"; resumed, {r.rendered} rendered now")
            + f") → {r.output}"
        )

    failed = run_each(audios, dub_one, lambda audio, e: f"nvp dub: {audio}: error: {e}")
    if several:
        print(
            f"{len(audios) - failed} of {len(audios)} dubbed → {args.output}"
            + (f"; {failed} failed" if failed else "")
        )
    return 2 if failed else 0
