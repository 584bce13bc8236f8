"""Kill drill: ``kill -9`` an ``nvp fit`` at random moments, run the same command again each time, and check
that the bundle finally loads, ``nvp info`` passes and ``nvp dub`` works.

    python -m scripts.tools.drill_kill_fit [--video V] [--kills 10] [--steps 30] [--seed 0] \
        [--nvp .venv/bin/nvp]

Prints one row per kill: when it struck, which stage was running (from the partial bundle's
progress.json and the folders present) and whether the next run got past it. Reads ../shared/data.
"""

from __future__ import annotations

import argparse
import json
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from scripts.common import SHARED

DATA = SHARED


def stage_of(out: Path) -> str:
    """What the fit was doing, judged from what is on disk."""
    work = out.with_name(out.name + ".partial")
    if (out / "bundle.json").exists() and not work.exists():
        return "published"
    if not work.exists():
        return "starting"
    try:
        done = list(json.loads((work / "progress.json").read_text()).get("stages", {}))
    except (OSError, ValueError):
        return "publishing" if (work / "bundle.json").exists() else "starting"
    order = ["target", "track", "style", "renderer"]
    running = next((s for s in order if s not in done), "publish")
    return f"{running} (done: {','.join(done) or '-'})"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--video", type=Path, default=DATA / "video" / "videoretalking__face5.mp4")
    ap.add_argument("--audio", type=Path, default=DATA / "audio" / "videoretalking__1.wav")
    ap.add_argument("--kills", type=int, default=10)
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--nvp", default=str(Path(sys.executable).with_name("nvp")))
    args = ap.parse_args(argv)
    if not args.video.exists():
        print(f"no drill data: {args.video} does not exist")
        return 0
    rng = np.random.default_rng(args.seed)
    tmp = Path(tempfile.mkdtemp(prefix="nvp-drill-"))
    out = tmp / "person"
    cmd = [args.nvp, "-q", "fit", str(args.video), "-o", str(out), "--steps", str(args.steps)]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    full = time.perf_counter() - t0
    shutil.rmtree(out, ignore_errors=True)
    print(f"uninterrupted fit: {full:.1f} s (exit {proc.returncode})")
    rows, finished_first = [], 0
    while len(rows) < args.kills and finished_first < 5 * args.kills:
        at = float(rng.uniform(0.02, 0.95)) * full
        p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            p.wait(timeout=at)
            finished_first += 1  # too late to strike: not a kill, try again
            shutil.rmtree(out, ignore_errors=True)
            continue
        except subprocess.TimeoutExpired:
            stage = stage_of(out)
            p.send_signal(signal.SIGKILL)
            p.wait()
        rerun = subprocess.run(cmd, capture_output=True, text=True)
        err = rerun.stderr.strip().splitlines()[-1] if rerun.returncode else ""
        rows.append((len(rows), at, stage, rerun.returncode, err))
        if rerun.returncode == 0:
            shutil.rmtree(out)  # the next kill strikes a fresh fit
    # a final kill-free state: fit, info, dub
    final = subprocess.run(cmd, capture_output=True, text=True)
    info = subprocess.run([args.nvp, "info", str(out)], capture_output=True, text=True)
    dub = subprocess.run(
        [args.nvp, "-q", "dub", str(args.audio), "--person", str(out), "-o", str(tmp / "d.mp4")],
        capture_output=True,
        text=True,
    )
    print("| kill | at s | stage running | rerun exit | rerun error |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r[0]} | {r[1]:.1f} | {r[2]} | {r[3]} | {r[4] if len(r) > 4 else ''} |")
    good = sum(1 for r in rows if r[3] == 0)
    print(
        f"\n{good} of {len(rows)} reruns after a kill finished a bundle; final fit exit {final.returncode}, "
        f"info exit {info.returncode}, dub exit {dub.returncode}"
    )
    shutil.rmtree(tmp, ignore_errors=True)
    return 0 if good == len(rows) and final.returncode == info.returncode == dub.returncode == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
