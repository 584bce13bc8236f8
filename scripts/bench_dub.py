"""Benchmark ``nvp dub``: frames/s and peak memory of the whole per-frame path on a person bundle.

    python scripts/bench_dub.py [--seconds 10] [--person PERSON_DIR]

Without ``--person``, a bundle is made from nvp's demo target (a 384×384 talking astronaut, renderer
trained for 2 steps: speed does not depend on training). The driving audio is ``--seconds`` of a
synthetic voice; the dub runs in a fresh process so its peak RSS is its own.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def child(audio: str, person: str, out: str) -> None:
    from nvp.app.dub import dub

    t0 = time.perf_counter()
    r = dub(audio, person, out, progress=False)
    wall = time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"frames": r.frames, "audio_s": r.audio_seconds, "wall_s": wall, "peak_rss_mb": rss}))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--person", type=Path)
    ap.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(*args.child)
        return 0
    import numpy as np
    import soundfile as sf

    from nvp.app.demo_clip import make_demo_clip
    from nvp.app.demo_voice import AUDIO_RATE, speech_script, synth_voice
    from nvp.app.fit import FitConfig, fit

    print(f"# bench_dub ({platform.machine()}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f})")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        person = args.person
        if person is None:
            clip = make_demo_clip(tmp / "target.mp4", seconds=4.0, size=384)
            person = fit(clip.path, tmp / "person", FitConfig(steps=2), progress=False).root
        rng = np.random.default_rng(3)
        wav = tmp / "speech.wav"
        sf.write(wav, synth_voice(speech_script(args.seconds, rng), args.seconds, rng), AUDIO_RATE)
        proc = subprocess.run(
            [sys.executable, __file__, "--child", str(wav), str(person), str(tmp / "dub.mp4")],
            capture_output=True,
            text=True,
            check=True,
        )
        m = json.loads(proc.stdout.strip().splitlines()[-1])
    m["fps"] = m["frames"] / m["wall_s"]
    m["x_realtime"] = m["audio_s"] / m["wall_s"]
    print(f"person: {person if args.person else 'demo target, 384x384'}")
    print(
        f"dub of {m['audio_s']:.1f} s: {m['frames']} frames in {m['wall_s']:.1f} s = {m['fps']:.1f} frames/s "
        f"({m['x_realtime']:.2f}x real time), peak RSS {m['peak_rss_mb']:.0f} MB"
    )
    print("BENCH_JSON " + json.dumps(m))
    return 0


if __name__ == "__main__":
    sys.exit(main())
