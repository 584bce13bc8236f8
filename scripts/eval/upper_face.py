"""Blinks and brows of animations from audio alone (issue 50): does an export of new speech blink at the
person's own rate, and do its brows move within their footage's range?

    python -m scripts.eval.upper_face [--cache /tmp/nvp-cache] [--audio AUDIO] [--out out/eval_upper_face]

For each test person of ``scripts/data_split.json`` (their clips joined into one footage when they have
several, as ``scripts/eval/lipsync.py --joined`` does; people with under ``--min-seconds`` of footage left
out: a blink rate from a few seconds means little), their upper face is learned from the tracked footage
exactly as ``nvp fit`` does (:func:`nvp.upper_face.learn_upper_face` on the mesh's landmarks) and sampled for
``--audio`` (default: a 46 s English talk, looped to ``--seconds``) as ``nvp predict`` does
(:func:`nvp.upper_face.upper_face_motion`). Measured on the mesh of the tracked footage and of the output,
the same way (:func:`nvp.upper_face.blink_runs`, :func:`nvp.upper_face.brow_height`): blinks per minute, and
the brow height's 5th-95th percentile range and spread. The footage's own blink rate (no prior) is the
target; ``learned`` is the rate the style keeps (pulled towards the population's on short footage).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from nvp.app.corpus import load_sample
from nvp.app.report import markdown_table
from nvp.face_model import default_face_model
from nvp.media import read_audio
from nvp.upper_face import blink_runs, brow_height, eye_openness, learn_upper_face, upper_face_motion
from nvp.vad import voice_activity
from scripts.common import SHARED, SPLIT, data_missing
from scripts.eval.lipsync import joined_footage

SR = 16000


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cache", type=Path, default=Path("/tmp/nvp-cache"))
    ap.add_argument("--audio", type=Path, default=SHARED / "audio" / "styletalk__intro.wav")
    ap.add_argument("--seconds", type=float, default=60.0, help="length of the animation")
    ap.add_argument("--min-seconds", type=float, default=20.0, help="least footage a person needs here")
    ap.add_argument("--out", type=Path, default=Path("out/eval_upper_face"))
    args = ap.parse_args(argv)
    if data_missing(SHARED):
        return 0
    split = json.loads(SPLIT.read_text())
    model = default_face_model()
    audio = read_audio(args.audio, SR)
    audio = np.tile(audio, int(np.ceil(args.seconds * SR / len(audio))))[: int(args.seconds * SR)]
    rows = []
    for person, v in sorted(split["people"].items()):
        clips = [c for c in v["clips"] if c in split["test"]]
        if not clips:
            continue
        video = SHARED / "video" / clips[0]
        if len(clips) > 1:
            video = joined_footage(
                [SHARED / "video" / c for c in clips], args.cache / "joined" / f"{person}.mp4"
            )
        seq = load_sample(video, args.cache, "phonemes", progress=False).tracked
        ok = seq.valid
        minutes = ok.sum() / seq.fps / 60
        if minutes * 60 < args.min_seconds:
            continue
        points = model.vertices(seq.identity, seq.expression[ok])[:, model.landmark_vertices]
        upper = learn_upper_face(points, seq.expression[ok], np.ones(ok.sum(), bool), seq.fps)
        own = len(blink_runs(eye_openness(points), np.ones(len(points), bool))) / minutes
        fps = seq.fps
        voice = voice_activity(audio, SR, fps, int(args.seconds * fps))
        motion = upper_face_motion(upper, audio, SR, voice, fps, seed=0)
        out = model.vertices(seq.identity, np.median(seq.expression[ok], 0) + motion)[
            :, model.landmark_vertices
        ]
        made = len(blink_runs(eye_openness(out), np.ones(len(out), bool))) / (args.seconds / 60)
        h_real, h_out = brow_height(points), brow_height(out)
        outside = np.mean((h_out < h_real.min()) | (h_out > h_real.max()))
        lo, hi = np.percentile(h_real, [5, 95])
        rows.append(
            {
                "person": person,
                "language": v["language"],
                "footage s": f"{minutes * 60:.0f}",
                "blinks/min footage": f"{own:.1f}",
                "learned": f"{upper.blinks_per_min:.1f}",
                "export": f"{made:.1f}",
                "export / footage": f"{made / own:.2f}" if own else "—",
                "brow p5-p95 footage": f"{lo:.3f}-{hi:.3f}",
                "brow p5-p95 export": "{:.3f}-{:.3f}".format(*np.percentile(h_out, [5, 95])),
                "brow spread export / footage": f"{h_out.std() / h_real.std():.2f}",
                "export outside footage range": f"{outside:.3f}",
            }
        )
        print(rows[-1], flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    md = markdown_table(rows)
    (args.out / "results.md").write_text(md + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
