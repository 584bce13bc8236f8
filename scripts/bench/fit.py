"""Benchmark ``nvp fit`` on long high-resolution footage: peak memory and the time of each stage.

    python -m scripts.bench.fit [--seconds 180] [--source CLIP.mp4] [--steps 50 | --default-training]

A ``--seconds`` video (default 3 minutes) is made by looping ``--source`` (default: the 1920×1080
``wav2lipgfpgan__kim_7s_raw.mp4`` of ../shared/data; video and audio packets copied, no re-encoding), and
``nvp fit`` runs on it in a fresh process with ``--steps`` renderer steps (the memory of training does not
grow with steps; the frame cache it trains from grows with the video), or with the preset's default
training (``--default-training``: a fit without flags, as a new user runs it). Prints the CPU, the peak
resident memory of that process (target: ≤ 4 GB), its wall time and the bundle's per-stage seconds.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from scripts.bench.tracking import DATA, loop_media


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=180.0)
    ap.add_argument("--source", type=Path, default=DATA / "wav2lipgfpgan__kim_7s_raw.mp4")
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--default-training", action="store_true", help="no --steps: the preset's default time")
    ap.add_argument("--preset", default="cpu")
    args = ap.parse_args(argv)
    if not args.source.exists():
        print(f"{args.source} not found: nothing to measure")
        return 0
    from nvp.media import probe_video
    from scripts.bench.dub import cpu_name

    print(f"# bench_fit ({cpu_name()}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f})")
    nvp = Path(sys.executable).parent / "nvp"
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        video = tmp / "long.mp4"
        loop_media(args.source, video, args.seconds)
        seconds = probe_video(video).duration_s  # whole copies of the source: at least --seconds
        cmd = [str(nvp), "--quiet", "fit", str(video), "-o", str(tmp / "person")]
        training = [] if args.default_training else ["--steps", str(args.steps)]
        cmd += [*training, "--preset", args.preset]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
        if proc.returncode != 0:
            print(proc.stderr.strip()[-2000:])
            return 1
        manifest = json.loads((tmp / "person" / "bundle.json").read_text())
    m = {
        "seconds": round(seconds, 1),
        "steps": None if args.default_training else args.steps,
        "preset": args.preset,
        "wall_s": wall,
        "peak_rss_mb": peak,
    }
    m["stages_s"] = {k: v.get("seconds") for k, v in manifest["stages"].items()}
    m["renderer_steps"] = manifest["stages"]["renderer"].get("steps")
    fit = " ".join(["nvp fit", *training, "--preset", args.preset])
    print(f"source {args.source.name} looped to {seconds:.0f} s; {fit}")
    print(f"renderer: {m['renderer_steps']} steps")
    print(f"wall {wall:.0f} s, peak RSS {peak:.0f} MB (target ≤ 4096 MB)")
    print("stages (s): " + ", ".join(f"{k} {v}" for k, v in m["stages_s"].items()))
    print("BENCH_JSON " + json.dumps(m))
    return 0


if __name__ == "__main__":
    sys.exit(main())
