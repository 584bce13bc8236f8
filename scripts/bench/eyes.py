"""Speed of eye contact (``nvp dub --gaze camera``): milliseconds a frame to turn the eyes of real footage.

    python -m scripts.bench.eyes [--videos V ...] [--frames 60] [--cache /tmp/nvp-cache]

For each clip of ``../shared/data/video`` (tracked once into ``--cache``), the first ``--frames`` frames are
decoded, then timed through :func:`renderer.eyes.turn_eyes` (into the lens), one thread, as each render
worker runs it. Prints the CPU, the frame size, the iris radius and ms per frame.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from nvp.app.corpus import tracked_cached
from nvp.face_model import default_face_model
from nvp.media import iter_frames
from renderer.eyes import turn_eyes
from scripts.bench.dub import cpu_name
from scripts.common import VIDEOS, data_missing

DEFAULT = ("cantolip__icable_10075_0.mp4", "mimictalk__Trump_10s.mp4", "multivsr__hxn8clTtMTo-00001.mp4")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--videos", nargs="*", default=list(DEFAULT))
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/nvp-cache"))
    args = ap.parse_args(argv)
    if data_missing(VIDEOS):
        return 0
    import torch

    torch.set_num_threads(1)
    model = default_face_model()
    print(f"# bench_eyes ({cpu_name()}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f})")
    for name in args.videos:
        seq = tracked_cached(VIDEOS / name, args.cache, progress=False)
        frames = list(iter_frames(VIDEOS / name, seq.fps, max_frames=args.frames))
        t = time.perf_counter()
        for k, frame in enumerate(frames):
            turn_eyes(model, seq, frame, k)
        ms = (time.perf_counter() - t) / len(frames) * 1000
        radius = float(np.nanmedian(seq.iris[..., 2]))
        print(f"{name}: {seq.width}x{seq.height}, iris {radius:.1f} px: {ms:.1f} ms a frame")
    return 0


if __name__ == "__main__":
    sys.exit(main())
