"""Speaking-style transfer on real footage: does person A talking in person B's style move like B?

    python -m scripts.eval.style_transfer --cache /tmp/nvp-cache [--pairs A.mp4 B.mp4 ...] [--audio X.wav]

For each pair: both people's styles are made from their whole clip as ``nvp fit`` makes them
(``nvp.person.style_from_sample`` with their voice activity); one speech file (default: A's own audio) is
turned into expressions three ways — A's style on A's face, B's style on B's face, B's style transferred to
A (``nvp.person.transferred_style``, as ``nvp dub --style``) on A's face — and the mouth statistics of each
are compared (expression level, nothing rendered):

- opening spread: 95th minus 5th percentile of the inner-lip gap (cm);
- closure rate: fraction of voiced frames at or below the face's closed level
  (``nvp.metrics.closed_level`` of that person's tracked gaps);
- corner asymmetry: ``nvp.metrics.corner_motion_asymmetry`` of the mouth corners (mediapipe 61 / 291).

The transfer works when A-with-B's-style is closer to B than A is, on each statistic. Writes
``results.md`` / ``results.json``. Tracking and features are cached under ``--cache``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from scripts.common import SHARED, data_missing

DEFAULT_PAIRS = ["mimictalk__German_20s.mp4", "dfrf__cnn2_25fps.mp4"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--pairs", nargs="+", default=DEFAULT_PAIRS, help="clips of ../shared/data/video: A B ..."
    )
    ap.add_argument("--audio", type=Path, help="speech to say (default: each pair's A clip's own audio)")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/nvp-cache"))
    ap.add_argument("--out", type=Path, default=Path("out/eval_style_transfer"))
    args = ap.parse_args(argv)
    if data_missing(SHARED):
        return 0
    if len(args.pairs) % 2:
        ap.error("--pairs takes clips two by two (A B)")
    from nvp.app.corpus import load_sample
    from nvp.app.report import markdown_table
    from nvp.audio2exp import default_audio2exp
    from nvp.face_model import default_face_model
    from nvp.media import read_audio
    from nvp.metrics import closed_level, corner_motion_asymmetry
    from nvp.person import predict_expressions, style_from_sample, transferred_style, voiced_frames
    from nvp.vad import frame_speech_probability

    net, manifest = default_audio2exp("phonemes")
    model = default_face_model()
    corners = model.landmark_vertices[[61, 291]]
    rows = []
    for a_name, b_name in zip(args.pairs[::2], args.pairs[1::2], strict=True):
        people = {}
        for name in (a_name, b_name):
            video = SHARED / "video" / name
            s = load_sample(video, args.cache, "phonemes", progress=False)
            voiced = voiced_frames(video, s.tracked.fps, s.tracked.num_frames)
            style = style_from_sample(net, manifest, s, model, voiced=voiced)
            gap = model.inner_lip_gap(s.tracked.identity, s.expression[s.valid])
            people[name] = (s.tracked, style, closed_level(gap))
        speech = args.audio or SHARED / "video" / a_name
        audio = read_audio(speech, 16000)
        fps = people[a_name][0].fps
        expr_style = {
            "A": (a_name, people[a_name][1]),
            "B": (b_name, people[b_name][1]),
            "A in B's style": (a_name, transferred_style(people[a_name][1], people[b_name][1])),
        }
        n = None
        voiced = None
        for label, (face, style) in expr_style.items():
            seq, _, closed = people[face]
            expr = predict_expressions(audio, 16000, fps, style, net, num_frames=n)
            n = len(expr)
            if voiced is None:
                voiced = frame_speech_probability(audio, 16000, fps, n) >= 0.5
            gap = model.inner_lip_gap(seq.identity, expr)
            verts = model.vertices(seq.identity, expr)
            rows.append(
                {
                    "pair": f"{Path(a_name).stem} ← {Path(b_name).stem}",
                    "speech": Path(speech).name,
                    "output": label,
                    "opening spread (cm)": float(np.percentile(gap, 95) - np.percentile(gap, 5)),
                    "closure rate (voiced)": float(np.mean(gap[voiced] <= closed)),
                    "corner asymmetry": corner_motion_asymmetry(verts, *corners),
                }
            )
    args.out.mkdir(parents=True, exist_ok=True)
    keys = ("opening spread (cm)", "closure rate (voiced)", "corner asymmetry")
    verdict = []
    for i in range(0, len(rows), 3):
        a, b, ab = rows[i : i + 3]
        verdict.append(
            {
                "pair": a["pair"],
                **{k: "closer to B" if abs(ab[k] - b[k]) < abs(a[k] - b[k]) else "NOT closer" for k in keys},
            }
        )
    text = markdown_table(rows, digits=3) + "\n" + markdown_table(verdict) + "\n"
    (args.out / "results.md").write_text(text)
    (args.out / "results.json").write_text(json.dumps(rows, indent=1) + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
