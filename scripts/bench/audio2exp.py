"""Benchmark audio → expressions: speed as a multiple of real time, and peak memory on a 10-minute file.

    python -m scripts.bench.audio2exp [--minutes 10] [--repeats 3] [--kinds phonemes mel]

The measured path is what ``nvp dub`` runs before rendering (``nvp.person.predict_expressions``): speech
features → per-frame windows at 25 fps → shipped Audio2ExpressionNet (per-frame net + temporal filter, and
its closure head when it has one) → person map → opening model blend (phonemes) → closures → voice gate →
expression coefficients.

1. Speed on a real 19.8 s English clip (``../shared/data/audio/latentsync__demo2_audio.wav``) when
   ../shared is present, otherwise on synthetic syllable-like audio of the same length; best of
   ``--repeats``, with the feature extraction alone timed separately.
2. Peak memory: the clip tiled to ``--minutes`` minutes, written as a 16 kHz wav, and predicted from the
   file in a fresh process per kind (``ru_maxrss`` after imports and at the end, wall time).

Target: >= 50x real time. The machine may be shared with other jobs; the load average is printed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from scripts.bench.audio_features import CLIP, SR, synthetic_speech

FPS = 25.0


def _style(kind: str):
    """A person style for the shipped net of ``kind`` (a random but plausible map: speed only)."""
    from nvp.audio2exp import PersonMap, default_audio2exp
    from nvp.face_model import default_face_model
    from nvp.opening import default_opening_model
    from nvp.person import OpeningStyle, PersonStyle

    net, manifest = default_audio2exp(kind)
    k = default_face_model().num_exp
    rng = np.random.default_rng(0)
    pmap = PersonMap(
        rng.normal(0, 0.1, (k, net.cfg.audio_exp_dim)).astype(np.float32), np.zeros(k, np.float32)
    )
    closed = np.zeros(k, np.float32) if net.closure is not None else None  # the closure path runs too
    opening = None  # and the opening model's (phonemes: features of the same recogniser pass)
    if kind == "phonemes":
        w = rng.normal(0, 0.1, k).astype(np.float32)
        d = (w / (w @ w)).astype(np.float32)
        sha = default_opening_model().sha256
        opening = OpeningStyle(w, 0.5, d, 0.25, 0.3, 0.0, sha, closed_below=-1.0)  # closes as a fit's does
    return net, PersonStyle(pmap, np.zeros(k, np.float32), kind, manifest["sha256"], {}, closed, opening)


def speed(audio: np.ndarray, kind: str, repeats: int) -> dict:
    """Best-of-``repeats`` seconds of feature extraction alone and of the whole prediction path."""
    from nvp.audio_features import extract_features
    from nvp.person import predict_expressions

    net, style = _style(kind)
    best_feat = best_total = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        extract_features(audio, SR, kind=kind)
        t1 = time.perf_counter()
        expr = predict_expressions(audio, SR, FPS, style, net)
        t2 = time.perf_counter()
        best_feat, best_total = min(best_feat, t1 - t0), min(best_total, t2 - t1)
    dur = len(audio) / SR
    return {
        "kind": kind,
        "frames": len(expr),
        "features_s": best_feat,
        "rest_s": max(best_total - best_feat, 0.0),
        "total_s": best_total,
        "x_realtime": dur / best_total,
    }


def child(path: str, kind: str) -> None:
    """Run in a fresh process: predict from a file and print JSON with RSS figures."""
    from nvp.media import read_audio
    from nvp.person import predict_expressions

    net, style = _style(kind)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t0 = time.perf_counter()
    audio = read_audio(path, SR)
    expr = predict_expressions(audio, SR, FPS, style, net)
    dt = time.perf_counter() - t0
    rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"frames": len(expr), "seconds": dt, "rss_imports_mb": rss0, "rss_peak_mb": rss1}))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--kinds", nargs="+", default=["phonemes", "mel"])
    ap.add_argument("--child", nargs=2, metavar=("WAV", "KIND"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(*args.child)
        return 0
    import soundfile as sf

    from nvp.media import read_audio

    if CLIP.exists():
        audio, source = read_audio(CLIP, SR), f"{CLIP.name} (real English speech)"
    else:
        audio, source = synthetic_speech(19.8), "synthetic speech (../shared/data not present)"
    dur = len(audio) / SR
    print(f"# bench_audio2exp ({platform.machine()}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f})")
    print(f"clip: {source}, {dur:.1f} s, {FPS:g} fps\n")
    print("| features | frames | features s | windows + network + gate s | total s | x real time |")
    print("|---|---|---|---|---|---|")
    results: dict = {
        "machine": platform.processor() or platform.machine(),
        "clip_s": dur,
        "speed": [],
        "memory": [],
    }
    for kind in args.kinds:
        r = speed(audio, kind, args.repeats)
        results["speed"].append(r)
        print(
            f"| {kind} | {r['frames']} | {r['features_s']:.3f} | {r['rest_s']:.3f} | {r['total_s']:.3f} "
            f"| {r['x_realtime']:.1f} |"
        )
    reps = int(np.ceil(args.minutes * 60 / dur))
    long_audio = np.tile(audio, reps)[: int(args.minutes * 60 * SR)]
    print(f"\n{args.minutes:g}-minute file (clip tiled), fresh process per kind\n")
    print("| features | frames | wall s | x real time | RSS after imports MB | peak RSS MB |")
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        wav = Path(tmp) / "long.wav"
        sf.write(wav, long_audio, SR, subtype="PCM_16")
        for kind in args.kinds:
            out = subprocess.run(
                [sys.executable, "-m", "scripts.bench.audio2exp", "--child", str(wav), kind],
                capture_output=True,
                text=True,
                check=True,
            )
            m = json.loads(out.stdout.strip().splitlines()[-1])
            m["kind"] = kind
            results["memory"].append(m)
            print(
                f"| {kind} | {m['frames']} | {m['seconds']:.1f} | {args.minutes * 60 / m['seconds']:.1f} "
                f"| {m['rss_imports_mb']:.0f} | {m['rss_peak_mb']:.0f} |"
            )
    print("\nBENCH_JSON " + json.dumps(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
