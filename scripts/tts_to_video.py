"""Text to video: speak a text with offline text to speech, then dub a fitted person with it.

    python scripts/tts_to_video.py "Hello there." --person person/ -o out.mp4 [--slower 1.1]

Needs the optional ``tts`` extra (``bash scripts/setup.sh tts``: piper + its bundled English voice, no
download at run time). Bad input ends with one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("text", help="what the person says (English)")
    ap.add_argument("--person", type=Path, required=True, help="person bundle from nvp fit")
    ap.add_argument("-o", "--output", type=Path, required=True, help="output mp4")
    ap.add_argument("--slower", type=float, default=1.0, help="speaking slowness (>1 slower, <1 faster)")
    ap.add_argument("--wav", type=Path, help="also keep the synthesized speech here")
    ap.add_argument("--device", default="cpu", help="torch device (cpu, cuda)")
    args = ap.parse_args(argv)
    import soundfile as sf

    from nvp.app.dub import dub
    from nvp.errors import NvpError
    from nvp.tts import synthesize

    try:
        audio, rate = synthesize(args.text, length_scale=args.slower)
        with tempfile.TemporaryDirectory() as tmp:
            wav = args.wav or Path(tmp) / "speech.wav"
            sf.write(wav, audio, rate)
            r = dub(wav, args.person, args.output, device=args.device)
    except NvpError as e:
        print(f"tts_to_video: error: {e}", file=sys.stderr)
        return 2
    print(f"{len(audio) / rate:.1f} s of speech, {r.frames} frames in {r.seconds:.1f} s → {r.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
