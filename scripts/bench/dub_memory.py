"""Peak memory of ``nvp dub`` against the audio's length (issue 48: flat from 1 to 30 minutes).

    python -m scripts.bench.dub_memory [--minutes 1 10 30] [--person PERSON_DIR | --size 256]
                                       [--rate 48000] [--channels 2]

Each length is dubbed in a fresh process (``scripts.bench.dub``'s child: its peak RSS is its own) from a
broadcast-like track: ``--rate`` Hz, ``--channels`` channels, 20 s of nvp's synthetic voice repeated.
Without ``--person``, a bundle is made from nvp's demo target (a ``--size``² talking astronaut, renderer
trained for 2 steps): what grows with the audio's length (its samples, features, expressions, the frame
order) does not depend on the frame size, and a small face keeps a 30-minute run short. Prints the CPU, and
per length the frames, the wall time and the peak RSS, then the growth against the shortest.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

from scripts.bench.dub import cpu_name, demo_person, run_child


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--minutes", type=float, nargs="+", default=[1.0, 10.0, 30.0])
    ap.add_argument("--person", type=Path)
    ap.add_argument("--size", type=int, default=256, help="demo target's frame size without --person")
    ap.add_argument("--rate", type=int, default=48000)
    ap.add_argument("--channels", type=int, default=2)
    args = ap.parse_args(argv)
    import numpy as np
    import soundfile as sf

    from nvp.app.demo_voice import speech_script, synth_voice

    print(f"# bench_dub_memory ({cpu_name()}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f})")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        person = args.person or demo_person(tmp, args.size)
        rng = np.random.default_rng(3)
        block = synth_voice(speech_script(20.0, rng), 20.0, rng, args.rate).astype(np.float32)
        for minutes in args.minutes:
            wav = tmp / "speech.wav"
            samples = np.tile(block, int(np.ceil(minutes * 60 / 20.0)))[: int(minutes * 60 * args.rate)]
            sf.write(wav, np.repeat(samples[:, None], args.channels, 1), args.rate, subtype="PCM_16")
            m = run_child(wav, person, tmp / "d.mp4")
            rows.append((minutes, m))
            print(
                f"{minutes:g} min of {args.rate} Hz x{args.channels} audio: {m['frames']} frames in "
                f"{m['wall_s']:.0f} s, peak RSS {m['peak_rss_mb']:.0f} MB",
                flush=True,
            )
            wav.unlink()
    first = rows[0][1]["peak_rss_mb"]
    for minutes, m in rows[1:]:
        print(f"peak RSS at {minutes:g} min: {m['peak_rss_mb'] / first - 1:+.1%} against {rows[0][0]:g} min")
    return 0


if __name__ == "__main__":
    sys.exit(main())
