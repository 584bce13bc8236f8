"""The frames of one dub made by two versions of nvp: mouth-box PSNR and whole-frame max |Δ| (issue 48).

    python -m scripts.tools.compare_dub --person PERSON_DIR BEFORE [AFTER] [--seconds 5] [--audio WAV]
        [--before-env NVP_PRECISION=fp32] [--after-env K=V] [--keep DIR]

BEFORE and AFTER are commits (exported with ``git archive``, so uncommitted work plays no part) or folders
holding a source tree (the working tree: ``.``, AFTER's default). Each version dubs the same audio
(``--audio``, else ``--seconds`` of the benchmarks' synthetic voice, seed 3) onto the same person bundle
in a fresh process with its own code first on the path, and the frames it hands the video encoder are
kept (raw, before H.264, so an encoder setting does not hide or fake a change of the picture; a changed
encoder shows in the mp4s' sizes and decoded frames, printed too). ``--before-env`` / ``--after-env`` set
environment variables of one side (e.g. the fp32 reference: ``NVP_PRECISION=fp32``).

Printed: frames, whole-frame max |Δ| (levels of 255) and the share of pixels that differ, and the mouth box's
PSNR (the box around the target frame's tracked outer-lip landmarks grown by 60 % of the mouth width on each
side, :func:`nvp.image_metrics.mouth_box`, as the quality evaluations use) over all frames (their pooled
squared error) and on the worst frame. Exit 0 when the mouth-box PSNR is at least ``--min-psnr`` (40 dB).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from scripts.common import ROOT

RUN = """
import json, sys
from pathlib import Path
import numpy as np
from nvp.media import VideoWriter
from nvp.app.dub import dub

audio, person, out = sys.argv[1], sys.argv[2], Path(sys.argv[3])
raw = open(out / "frames.raw", "wb")
shape = []
write = VideoWriter.write

def keep(self, frame):
    shape[:] = frame.shape
    raw.write(np.ascontiguousarray(frame).tobytes())
    return write(self, frame)

VideoWriter.write = keep
r = dub(audio, person, out / "dub.mp4", progress=False)
raw.close()
np.save(out / "targets.npy", np.asarray(r.target_frames))
(out / "info.json").write_text(json.dumps({"frames": r.frames, "shape": shape}))
"""


def tree_of(version: str, work: Path) -> Path:
    """A folder with the source of ``version`` (a folder as it is, else a commit exported there)."""
    if Path(version).is_dir():
        return Path(version).resolve()
    tree = work / f"tree-{version}"
    tree.mkdir(parents=True)
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", version], capture_output=True, check=True)
    subprocess.run(["tar", "-x", "-C", str(tree)], input=archive.stdout, check=True)
    return tree


def run(tree: Path, audio: Path, person: Path, out: Path, env: list[str]) -> dict:
    """Dubs with the code in ``tree``; the folder's ``frames.raw``, ``targets.npy``, ``info.json``."""
    out.mkdir(parents=True)
    extra = dict(kv.split("=", 1) for kv in env)
    full = dict(os.environ, PYTHONPATH=str(tree), **extra)
    subprocess.run(
        [sys.executable, "-c", RUN, str(audio), str(person), str(out)], cwd=tree, env=full, check=True
    )
    return json.loads((out / "info.json").read_text())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("before", help="commit or source folder before the change")
    ap.add_argument("after", nargs="?", default=str(ROOT), help="after it (default: the working tree)")
    ap.add_argument("--person", type=Path, required=True, help="person bundle folder (nvp fit)")
    ap.add_argument("--audio", type=Path, help="driving audio (default: --seconds of a synthetic voice)")
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--before-env", nargs="*", default=[], metavar="K=V")
    ap.add_argument("--after-env", nargs="*", default=[], metavar="K=V")
    ap.add_argument("--min-psnr", type=float, default=40.0)
    ap.add_argument("--keep", type=Path, help="keep the runs in this folder (default: a temporary one)")
    args = ap.parse_args(argv)

    from nvp.face_model import default_face_model
    from nvp.image_metrics import mouth_box
    from nvp.tracked import TrackedSequence

    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        audio = args.audio
        if audio is None:
            import soundfile as sf

            from nvp.app.demo_voice import AUDIO_RATE, speech_script, synth_voice

            rng = np.random.default_rng(3)
            audio = work / "speech.wav"
            sf.write(audio, synth_voice(speech_script(args.seconds, rng), args.seconds, rng), AUDIO_RATE)
        person = args.person.resolve()
        outs, infos = [], []
        for side, version, env in (
            ("before", args.before, args.before_env),
            ("after", args.after, args.after_env),
        ):
            out = work / side
            infos.append(run(tree_of(version, work), audio.resolve(), person, out, env))
            outs.append(out)
        (a_info, b_info), (a, b) = infos, outs
        if a_info != b_info:
            print(f"different frames: {a_info} vs {b_info}")
            return 1
        n, shape = a_info["frames"], tuple(a_info["shape"])
        fa = np.memmap(a / "frames.raw", np.uint8, "r", shape=(n, *shape))
        fb = np.memmap(b / "frames.raw", np.uint8, "r", shape=(n, *shape))
        targets = np.load(a / "targets.npy")
        model = default_face_model()
        from nvp.app.dub import PersonBundle

        seq = TrackedSequence.load(PersonBundle.load(person).path("tracked"))
        lips = seq.landmarks[:, model.landmark_groups["lips_outer"]]
        worst_delta, changed, box_se, box_px, worst_psnr = 0, 0, 0.0, 0, np.inf
        for j in range(n):
            x, y = fa[j].astype(np.int16), fb[j].astype(np.int16)
            d = np.abs(x - y)
            worst_delta, changed = max(worst_delta, int(d.max())), changed + int((d.max(2) > 0).sum())
            y0, y1, x0, x1 = mouth_box(lips[targets[j]], shape[:2])
            se = float((d[y0:y1, x0:x1].astype(np.float64) ** 2).sum())
            px = d[y0:y1, x0:x1].size
            box_se, box_px = box_se + se, box_px + px
            if se > 0:
                worst_psnr = min(worst_psnr, 10 * np.log10(255**2 / (se / px)))
        psnr = np.inf if box_se == 0 else 10 * np.log10(255**2 / (box_se / box_px))
        sizes = [(o / "dub.mp4").stat().st_size for o in outs]
        from nvp.media import iter_frames

        decoded = 0  # the mp4s' own frames (the encoder's settings and its input's conversion show here)
        for x, y in zip(iter_frames(a / "dub.mp4"), iter_frames(b / "dub.mp4"), strict=False):
            decoded = max(decoded, int(np.abs(x.astype(np.int16) - y.astype(np.int16)).max()))
        print(f"{args.before} {' '.join(args.before_env)} → {args.after} {' '.join(args.after_env)}")
        print(
            f"{n} frames of {shape[1]}x{shape[0]}: whole-frame max |Δ| {worst_delta}, pixels changed "
            f"{changed / (n * shape[0] * shape[1]):.3%}"
        )
        print(f"mouth-box PSNR {psnr:.2f} dB over all frames, {worst_psnr:.2f} dB on the worst frame")
        print(f"mp4 size {sizes[0] / 1e6:.2f} → {sizes[1] / 1e6:.2f} MB, decoded frames' max |Δ| {decoded}")
    return 0 if psnr >= args.min_psnr else 1


if __name__ == "__main__":
    raise SystemExit(main())
