"""Evaluate audio-to-expression on held-out people and on foreign/synthetic speech.

    python -m scripts.eval.audio2exp [--phonemes NET.json] [--mel out/a2e/mel/best.json]

1. Held-out time of validation videos (never seen by the generic network): the person map is solved on the
   first 80 % of each video, the last 20 % is predicted from its audio. Metrics (see
   ``nvp.app.train_audio2exp.evaluate_person``): mouth landmark error / IOD, lip vertex error (mm),
   correlation of predicted and tracked mouth opening, lip-closure F1. Rows: phonemes net, the same net
   without its temporal filter, mel net (if given), and the person's-mean-expression baseline.
2. Robustness: the longest validation person's style driven by every clip in ../shared/data/audio (other
   languages, singing, text-to-speech) and by silence: correlation between predicted mouth opening and the
   audio's loudness envelope, and the mouth opening during pauses vs speech.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from nvp.app.corpus import load_sample
from nvp.app.report import markdown_table
from nvp.app.train_audio2exp import evaluate_person
from nvp.audio2exp import audio_expressions, load_net
from nvp.face_model import default_face_model
from nvp.media import read_audio
from nvp.person import predict_expressions, style_from_sample
from nvp.vad import rms_envelope_db, voice_activity
from scripts.common import ROOT, SHARED, data_missing

ASSETS = ROOT / "nvp" / "assets"
SR = 16000


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--phonemes", type=Path, default=ASSETS / "audio2exp_phonemes.json")
    ap.add_argument("--mel", type=Path)
    ap.add_argument("--cache", type=Path, default=Path("out/a2e/cache"))
    ap.add_argument("--out", type=Path, default=Path("out/eval_audio2exp"))
    args = ap.parse_args(argv)
    if data_missing(SHARED):
        return 0
    model = default_face_model()
    net, manifest = load_net(args.phonemes)
    val_names = manifest["split"]["validation"]
    args.out.mkdir(parents=True, exist_ok=True)
    nets = {"phonemes": (net, True), "phonemes, no filter": (net, False)}
    if args.mel:
        nets["mel"] = (load_net(args.mel)[0], True)
    rows = []
    samples = {}
    for name in val_names:
        video = SHARED / "video" / name
        for label, (n, use_filter) in nets.items():
            kind = "mel" if label.startswith("mel") else "phonemes"
            s = samples.get((name, kind)) or load_sample(video, args.cache, kind, progress=False)
            samples[(name, kind)] = s
            r = evaluate_person(s, model, audio_expressions(n, s.windows, use_filter))
            rows.append({"video": name, "method": label, **r})
        s = samples[(name, "phonemes")]
        voice = voice_activity(read_audio(video, SR), SR, s.tracked.fps, s.tracked.num_frames)
        r = evaluate_person(s, model, audio_expressions(net, s.windows), voice=voice)
        rows.append({"video": name, "method": "phonemes + voice gate", **r})
        rows.append({"video": name, "method": "mean expression", **evaluate_person(s, model, None)})
    cols = [
        "video",
        "method",
        "mouth_error_iod",
        "lip_vertex_error_mm",
        "opening_corr",
        "closure_precision",
        "closure_recall",
        "closure_f1",
        "test_frames",
    ]
    summary = []
    for label in [*nets, "phonemes + voice gate", "mean expression"]:
        sel = [r for r in rows if r["method"] == label]
        summary.append({"method": label, **{c: float(np.mean([r[c] for r in sel])) for c in cols[2:-1]}})
    text = (
        "## Held-out 20 % of validation videos\n\n"
        + markdown_table(rows, cols)
        + "\n### Mean over videos\n\n"
    )
    text += markdown_table(summary, ["method", *cols[2:-1]])

    # robustness: the longest validation person's style driven by other audio (the `nvp dub` path)
    name = max(val_names, key=lambda n: samples[(n, "phonemes")].tracked.num_frames)
    s = samples[(name, "phonemes")]
    style = style_from_sample(net, manifest, s, model)
    gap_person = model.inner_lip_gap(s.tracked.identity, s.expression[s.valid])
    closed_mm, median_mm = 10 * np.percentile(gap_person, 5), 10 * np.median(gap_person)
    rob = []
    fps = 25.0
    for clip in [None, *sorted((SHARED / "audio").iterdir())]:
        audio = np.zeros(SR * 4, np.float32) if clip is None else read_audio(clip, SR)
        expr = predict_expressions(audio, SR, fps, style, net)
        gap = 10 * model.inner_lip_gap(s.tracked.identity, expr)
        # RMS level (dBFS) of the audio shown with each video frame
        loud = rms_envelope_db(audio, SR, 1 / fps)[: len(gap)]
        loud = np.pad(loud, (0, len(gap) - len(loud)), mode="edge")
        speech = loud > loud.max() - 30
        pause = np.ones_like(speech) if clip is None else loud < loud.max() - 45
        ok = clip is not None and gap.std() > 0 and speech.any()
        rob.append(
            {
                "audio": "silence (4 s of zeros)" if clip is None else clip.name,
                "corr_opening_loudness": float(np.corrcoef(gap, loud)[0, 1]) if ok else float("nan"),
                "opening_speech_mm": float(gap[speech].mean()) if ok else float("nan"),
                "opening_pause_mm": float(gap[pause].mean()) if pause.any() else float("nan"),
            }
        )
    speech_corr = [r["corr_opening_loudness"] for r in rob if np.isfinite(r["corr_opening_loudness"])]
    text += (
        f"\n## Robustness: style of {name} driven by other audio (nvp.person.predict_expressions)\n\n"
        f"The person's own tracked inner-lip gap: 5th percentile (closed) {closed_mm:.2f} mm, median "
        f"{median_mm:.2f} mm. Mean correlation of predicted opening and loudness over "
        f"{len(speech_corr)} clips: {np.mean(speech_corr):.3f}.\n\n"
    )
    text += markdown_table(rob, ["audio", "corr_opening_loudness", "opening_speech_mm", "opening_pause_mm"])
    (args.out / "results.md").write_text(text)
    (args.out / "results.json").write_text(
        json.dumps({"heldout": rows, "summary": summary, "robustness": rob}, indent=2) + "\n"
    )
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
