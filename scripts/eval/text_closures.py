"""Do p, b and m close the lips when the text is known? Speech made from a text, dubbed onto test people with
and without that text (``nvp say`` / ``nvp dub --transcript``), at the expression level.

    python -m scripts.eval.text_closures [--cache /tmp/nvp-cache] [--out out/eval_text_closures]

Each person of ``--videos`` (default: test people of ``scripts/data_split.json`` in several languages, never
used for training or choosing anything) gets their style from their whole clip exactly as ``nvp fit`` makes
it (``nvp.person.style_from_sample`` with the clip's voice activity). Each text of :data:`TEXTS` is spoken
offline (English: piper's joe voice, as ``nvp say``; other languages: the espeak-ng program with that
language's voice — Debian's ``espeak-ng`` package) and turned into the person's expressions as ``nvp dub``
does (``nvp.person.predict_expressions``), once from the audio alone and once with the transcript.

Metric (``nvp.metrics``, as ``scripts/eval/lipsync.py``): the p / b / m frames are those where the phoneme
recogniser hears p, b or m in the speech (posteriors >= 0.5; from the audio, not from the text); such a frame
counts as closed when the predicted inner-lip gap is at or below the person's closed level (of their own
tracked footage) at some frame from ``BILABIAL_LEAD_S`` before it to it. The real footage's own rate (test
people, ``scripts/eval/lipsync.py``) is the reference: 0.71 pooled, 0.77-0.86 on longer English footage.
Rounding, the same way: the frames where the recogniser hears a rounded (spread) vowel in the speech, the
share of rounded ones with the mouth at or below the closed level and the median mouth width on rounded over
spread ones (``scripts/eval/lipsync.py``; real footage 0.95 English, 0.87-0.91 Cantonese, Italian,
Portuguese).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

from nvp.app.corpus import load_sample
from nvp.app.report import markdown_table
from nvp.audio2exp import load_net
from nvp.audio_features import extract_features, phoneme_labels, prepare_audio
from nvp.face_model import default_face_model
from nvp.metrics import (
    BILABIAL_LEAD_S,
    bilabial_classes,
    bilabial_closure_rate,
    bilabial_frames,
    closed_level,
)
from nvp.opening import default_opening_model
from nvp.person import predict_expressions, style_from_sample, voiced_frames
from nvp.rounding import rounded_classes
from nvp.tts import synthesize
from scripts.common import ROOT, SHARED
from scripts.eval.lipsync import rounded_narrowing, spread_classes

ASSETS = ROOT / "nvp" / "assets"
SR = 16000
TEXTS = {
    "en": (
        "en-us",
        "Peter Piper picked a peck of pickled peppers. Bob met my mum by the big blue boat, "
        "and Pam baked a plum pie for my brother Ben.",
    ),
    "en2": (
        "en-us",
        "Maybe we should probably move the meeting to Monday morning, before the membership board publishes "
        "the budget.",
    ),
    "fr": ("fr", "Mon père boit du vin blanc, puis Paul mange une pomme bien mûre au bord de la mer."),
    "es": ("es", "Mi madre bebe poco, pero Pablo come bombones buenos en el barco de Bilbao."),
    "de": ("de", "Mein Bruder baut ein paar bunte Boote, bevor Mama beim Bäcker Brot bestellt."),
}
VIDEOS = (
    "multivsr__hxn8clTtMTo-00001.mp4",  # French
    "multivsr__GgQ9IGGSQ0I-00003.mp4",  # Italian
    "multivsr__RGI2GUiiL6o-00003.mp4",  # Portuguese
    "nltmlipsync__bazigar_part1.mp4",  # Hindi
    "emotionllama__sample_00000694.mp4",  # Mandarin
    "avcrossnet__E3_av.mp4",  # English
    "pcavs__681600002_av.mp4",  # English
    "deepavsr__00019.mp4",  # English
)


def speak(lang: str, text: str) -> tuple[np.ndarray, str]:
    """16 kHz mono speech of ``text`` and the espeak-ng language of its phonemes."""
    engine, voice = ("piper", None) if lang == "en-us" else ("espeak-ng", lang)
    s = synthesize(text, voice=voice, engine=engine)
    return prepare_audio(s.audio, s.rate), s.language  # 16 kHz


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cache", type=Path, default=Path("/tmp/nvp-cache"))
    ap.add_argument("--out", type=Path, default=Path("out/eval_text_closures"))
    ap.add_argument("--videos", nargs="*", default=list(VIDEOS))
    args = ap.parse_args(argv)
    if not SHARED.is_dir():
        print(f"no real data at {SHARED}: nothing to evaluate", file=sys.stderr)
        return 1
    net, manifest = load_net(ASSETS / "audio2exp_phonemes.json")
    opening = default_opening_model()
    model = default_face_model()
    bil_idx = bilabial_classes(phoneme_labels())
    lead = None
    speech = {k: speak(*v) for k, v in TEXTS.items()}
    rows = []
    for name in args.videos:
        video = SHARED / "video" / name
        s = load_sample(video, args.cache, "phonemes", progress=False)
        ow = load_sample(video, args.cache, opening.feature_kind, progress=False).windows
        seq = s.tracked
        fps = seq.fps
        lead = int(round(BILABIAL_LEAD_S * fps))
        sample = dataclasses.replace(s, opening_windows=ow)
        voiced = voiced_frames(video, fps, seq.num_frames)
        style = style_from_sample(net, manifest, sample, model, voiced=voiced, opening=opening)
        closed = closed_level(model.inner_lip_gap(seq.identity, seq.expression[seq.valid]))
        for key, (audio, language) in speech.items():
            n = int(np.ceil(len(audio) / SR * fps))
            post = extract_features(audio, SR, kind="phonemes")
            bil = bilabial_frames(post.values, bil_idx, post.rate, fps, n)
            rnd = bilabial_frames(post.values, rounded_classes(), post.rate, fps, n)
            spr = bilabial_frames(post.values, spread_classes(), post.rate, fps, n)
            row = {
                "video": name,
                "text": key,
                "bilabial_frames": int(bil.sum()),
                "rounded_frames": int(rnd.sum()),
            }
            for with_text in (False, True):
                transcript = (TEXTS[key][1], language) if with_text else None
                expr = predict_expressions(audio, SR, fps, style, net, num_frames=n, transcript=transcript)
                gap = model.inner_lip_gap(seq.identity, expr)
                rate = bilabial_closure_rate(gap, bil, closed, lead)
                how = "with text" if with_text else "audio only"
                row[how] = int(round(rate * bil.sum()))
                row[f"rounded closed, {how}"] = int(np.sum(gap[rnd] <= closed))
                row[f"rounded width, {how}"] = rounded_narrowing(
                    model.mouth_width(seq.identity, expr), rnd, spr
                )
            rows.append(row)
            print(f"{name} {key}: {row}", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(rows, indent=2) + "\n")
    table = []
    for key in TEXTS:
        sel = [r for r in rows if r["text"] == key]
        total = sum(r["bilabial_frames"] for r in sel)
        table.append(
            {
                "text": key,
                "people": len(sel),
                "p/b/m frames": total,
                "closed, audio only": f"{sum(r['audio only'] for r in sel) / total:.2f}",
                "closed, with text": f"{sum(r['with text'] for r in sel) / total:.2f}",
                "worst person, audio only → with text": "{:.2f} → {:.2f}".format(
                    min(r["audio only"] / r["bilabial_frames"] for r in sel if r["bilabial_frames"]),
                    min(r["with text"] / r["bilabial_frames"] for r in sel if r["bilabial_frames"]),
                ),
                "rounded-vowel frames": (rf := sum(r["rounded_frames"] for r in sel)),
                "rounded closed, audio only → with text": "{:.2f} → {:.2f}".format(
                    *(
                        sum(r[f"rounded closed, {h}"] for r in sel) / max(rf, 1)
                        for h in ("audio only", "with text")
                    )
                ),
                "width rounded / spread, audio only → with text": "{:.3f} → {:.3f}".format(
                    *(
                        np.nanmean([r[f"rounded width, {h}"] for r in sel])
                        for h in ("audio only", "with text")
                    )
                ),
            }
        )
    md = markdown_table(table)
    (args.out / "results.md").write_text(md + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
