"""p, b and m on the rendered picture: a fitted person dubbed with speech made from a text, with and without
that text (``nvp dub --transcript``; ``nvp say`` passes its own text the same way), measured on the output
frames by an independent probe (mediapipe's landmarks, no nvp geometry).

    python -m scripts.eval.say_closures --person BUNDLE [--out out/eval_say_closures] [--texts en fr]

For each text of ``eval_text_closures.TEXTS`` the speech is made offline (English: piper, as ``nvp say``;
others: the espeak-ng program) and dubbed onto the person twice. mediapipe's face landmarker reads every
output frame; the mouth is closed where the inner-lip gap (landmarks 13-14) over the eye-corner distance
(33-263) is at or below the person's closed level, measured the same way on their own footage
(``nvp.metrics.closed_level``). p / b / m frames are where the phoneme recogniser hears them in the speech
(posteriors >= 0.5, not the text); one is closed when the mouth is closed at some frame from
``BILABIAL_LEAD_S`` before it to it. The footage's own rate (its audio, its frames) is printed beside.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import soundfile as sf

from nvp.app.dub import dub
from nvp.app.report import markdown_table
from nvp.audio_features import extract_features, phoneme_labels
from nvp.bundle import PersonBundle
from nvp.media import probe_video, read_audio
from nvp.metrics import (
    BILABIAL_LEAD_S,
    bilabial_classes,
    bilabial_closure_rate,
    bilabial_frames,
    closed_level,
)
from scripts.eval.text_closures import TEXTS, speak
from tracking.detect import detect_video

SR = 16000


def mouth_gaps(video: Path) -> np.ndarray:
    """``(T,)`` inner-lip gap over the eye-corner distance per frame of ``video`` (NaN without a face)."""
    d = detect_video(video, progress=False)
    p = d.points[:, :, :2].astype(np.float64)
    iod = np.linalg.norm(p[:, 33] - p[:, 263], axis=1)
    return np.linalg.norm(p[:, 13] - p[:, 14], axis=1) / iod


def bilabial_rate(gap: np.ndarray, audio: np.ndarray, fps: float, closed: float) -> tuple[int, int]:
    """(closed p/b/m frames, p/b/m frames) of a video's gaps ``(T,)`` and its 16 kHz speech."""
    post = extract_features(audio, SR, kind="phonemes")
    bil = bilabial_frames(post.values, bilabial_classes(phoneme_labels()), post.rate, fps, len(gap))
    bil &= np.isfinite(gap)
    if not bil.any():
        return 0, 0
    rate = bilabial_closure_rate(gap, bil, closed, int(round(BILABIAL_LEAD_S * fps)))
    return int(round(rate * bil.sum())), int(bil.sum())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--person", type=Path, required=True, help="a person bundle from nvp fit")
    ap.add_argument("--out", type=Path, default=Path("out/eval_say_closures"))
    ap.add_argument("--texts", nargs="*", default=["en", "fr"], choices=list(TEXTS))
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    bundle = PersonBundle.load(args.person)
    footage = bundle.path("target")
    real_gap = mouth_gaps(footage)
    fps = probe_video(footage).fps
    closed = closed_level(real_gap[np.isfinite(real_gap)])
    shut, total = bilabial_rate(real_gap, read_audio(footage, SR), fps, closed)
    real = f"{shut / total:.2f}"
    rows = [
        {"speech": "the footage", "p/b/m frames": total, "closed, audio only": real, "closed, with text": "—"}
    ]
    with tempfile.TemporaryDirectory() as tmp:
        for key in args.texts:
            audio, language = speak(*TEXTS[key])
            wav = Path(tmp) / f"{key}.wav"
            sf.write(wav, audio, SR)
            row = {"speech": key}
            for with_text in (False, True):
                out = args.out / f"{key}_{'text' if with_text else 'audio'}.mp4"
                transcript = (TEXTS[key][1], language) if with_text else None
                dub(wav, args.person, out, progress=False, transcript=transcript)
                shut, total = bilabial_rate(mouth_gaps(out), audio, fps, closed)
                row["p/b/m frames"] = total
                row["closed, with text" if with_text else "closed, audio only"] = (
                    f"{shut / max(total, 1):.2f}"
                )
            rows.append(row)
            print(row, flush=True)
    (args.out / "results.json").write_text(json.dumps(rows, indent=2) + "\n")
    md = markdown_table(rows, ["speech", "p/b/m frames", "closed, audio only", "closed, with text"])
    (args.out / "results.md").write_text(md + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
