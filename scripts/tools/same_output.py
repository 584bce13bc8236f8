"""Same outputs before and after a refactor: a fixed-seed fit + dub at two commits, frames compared.

    python -m scripts.tools.same_output BEFORE [AFTER] [--steps 20] [--keep DIR]

Each commit is exported (``git archive``, so uncommitted work in the tree plays no part) and runs, in a
fresh process with its own code first on the path: the synthetic demo clip (2 s, 256², seed 0),
``nvp fit --steps N`` on it and ``nvp dub`` of its own audio. PyTorch runs on one thread
(``NVP_THREADS=1``): with more, renderer training follows the machine's load (``nvp.threads``), and a
different thread count sums in another order. Prints the largest difference of the dubbed frames (levels of
255), whether each array of the two person bundles and the two mp4 files are identical; exit 0 when the
frames are.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from scripts.common import ROOT

RUN = """
import sys
from pathlib import Path
import numpy as np
from nvp.app.cli import main
from nvp.app.demo_clip import make_demo_clip
from nvp.media import iter_frames, probe_video

out, steps = Path(sys.argv[1]), sys.argv[2]
out.mkdir(parents=True)
clip = make_demo_clip(out / "clip.mp4", seconds=2.0, size=256)
assert main(["-q", "fit", str(clip.path), "-o", str(out / "person"), "--steps", steps]) == 0
assert main(["-q", "dub", str(clip.path), "--person", str(out / "person"), "-o", str(out / "dub.mp4")]) == 0
info = probe_video(out / "dub.mp4")
np.save(out / "frames.npy", np.stack(list(iter_frames(out / "dub.mp4", info.fps, 0, info.num_frames))))
"""


def run_at(commit: str, work: Path, steps: int) -> Path:
    """Fit and dub with the code of ``commit``: the folder with ``frames.npy``, ``person/``, ``dub.mp4``."""
    tree, out = work / f"tree-{commit}", work / f"out-{commit}"
    tree.mkdir(parents=True)
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", commit], capture_output=True, check=True)
    subprocess.run(["tar", "-x", "-C", str(tree)], input=archive.stdout, check=True)
    env = dict(os.environ, NVP_THREADS="1", OMP_NUM_THREADS="1", PYTHONPATH=str(tree))
    subprocess.run([sys.executable, "-c", RUN, str(out), str(steps)], cwd=tree, env=env, check=True)
    return out


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("before", help="commit before the change")
    ap.add_argument("after", nargs="?", default="HEAD", help="commit after it (default: HEAD)")
    ap.add_argument("--steps", type=int, default=20, help="renderer training steps of the fit")
    ap.add_argument("--keep", type=Path, help="keep the runs in this folder (default: a temporary one)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep or Path(tmp)
        a, b = (run_at(c, work, args.steps) for c in (args.before, args.after))
        fa, fb = np.load(a / "frames.npy").astype(int), np.load(b / "frames.npy").astype(int)
        same_shape = fa.shape == fb.shape
        delta = int(np.abs(fa - fb).max()) if same_shape else None
        print(f"{args.before} → {args.after}: {len(fa)} / {len(fb)} frames, max |Δ| = {delta}")
        pairs = [(f, b / f.relative_to(a)) for f in sorted((a / "person").rglob("*.npz"))]
        for f, g in [*pairs, (a / "dub.mp4", b / "dub.mp4")]:
            print(f"  {f.relative_to(a)}: {'identical' if digest(f) == digest(g) else 'DIFFERENT'}")
    return 0 if delta == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
