"""Benchmark speech feature extraction: speed as a multiple of real time, and peak memory on a long file.

    python -m scripts.bench.audio_features [--minutes 10] [--repeats 3] [--out out/bench_audio_features.txt]

1. Speed on a real speech clip (``../shared/data/audio/latentsync__demo2_audio.wav``, 19.8 s, English,
   16 kHz) when ../shared is present, otherwise on a synthetic syllable-like signal of the same length:
   ``extract_features`` for ``phonemes`` (hama's model in PyTorch) and ``mel``, plus ``frame_windows`` at
   25 fps, as × real time (audio seconds per wall-clock second; best of ``--repeats``).
2. Peak memory: the clip tiled to ``--minutes`` minutes and written as a 16 kHz wav; each kind runs
   ``features_from_file`` + ``frame_windows`` in a fresh process, which reports ``ru_maxrss`` after its
   imports and at the end, and the wall time (× real time, torch's default threads).

The target for later is features + Audio2ExpressionNet prediction at >= 50× real time overall. The
machine may be shared with other jobs, so timings are noisy; the load average is printed.
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

from scripts.common import SHARED

CLIP = SHARED / "audio" / "latentsync__demo2_audio.wav"
SR = 16000


def synthetic_speech(seconds: float, seed: int = 0) -> np.ndarray:
    """Syllable-like stand-in for speech: noise-burst consonants and formant-weighted harmonic vowels."""
    rng = np.random.default_rng(seed)
    n = int(seconds * SR)
    x = np.zeros(n)
    vowels = [(730, 1090, 2440), (270, 2290, 3010), (300, 870, 2240), (530, 1840, 2480)]
    pos = int(0.2 * SR)
    while pos < n - SR // 2:
        c = int(rng.uniform(0.04, 0.09) * SR)
        x[pos : pos + c] += rng.standard_normal(c) * np.hanning(c) * 0.15
        pos += c
        length = int(rng.uniform(0.10, 0.22) * SR)
        f0 = rng.uniform(100, 160)
        t = np.arange(length) / SR
        v = sum(
            sum(
                g * np.exp(-(((h * f0 - fm) / 100.0) ** 2))
                for fm, g in zip(vowels[h % 4], (1, 0.6, 0.3), strict=True)
            )
            * np.sin(2 * np.pi * h * f0 * t)
            for h in range(1, 30)
        )
        x[pos : pos + length] += 0.3 * v / (np.abs(v).max() + 1e-9) * np.hanning(length)
        pos += length + int(rng.uniform(0.0, 0.3) * SR)
    return (0.5 * x / np.abs(x).max()).astype(np.float32)


def maxrss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kB on Linux


def child(kind: str, path: str) -> None:
    """Run in a fresh process: features of a file plus windows; print JSON with memory and time."""
    import scipy.fft  # noqa: F401
    import scipy.ndimage  # noqa: F401
    import scipy.signal  # noqa: F401

    from nvp.audio_features import features_from_file
    from nvp.windows import frame_windows

    base = maxrss_mb()
    t0 = time.perf_counter()
    feats = features_from_file(path, kind=kind)
    t1 = time.perf_counter()
    after_features = maxrss_mb()
    windows = frame_windows(feats, 25.0)
    t2 = time.perf_counter()
    print(
        json.dumps(
            {
                "kind": kind,
                "duration_s": feats.duration_s,
                "features_shape": list(feats.values.shape),
                "features_mb": feats.values.nbytes / 2**20,
                "windows_shape": list(windows.shape),
                "windows_mb": windows.nbytes / 2**20,
                "features_s": t1 - t0,
                "windows_s": t2 - t1,
                "rss_after_imports_mb": base,
                "peak_rss_after_features_mb": after_features,
                "peak_rss_mb": maxrss_mb(),
            }
        )
    )


def best_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--minutes", type=float, default=10.0, help="length of the tiled file for the memory test"
    )
    ap.add_argument("--repeats", type=int, default=3, help="timing repeats on the short clip (best is kept)")
    ap.add_argument("--out", type=Path, default=None, help="also write the report to this file")
    ap.add_argument("--child", nargs=2, metavar=("KIND", "PATH"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(*args.child)
        return

    import soundfile as sf

    from nvp.audio_features import extract_features
    from nvp.media import read_audio
    from nvp.windows import frame_windows

    lines: list[str] = []

    def say(s: str = "") -> None:
        print(s, flush=True)
        lines.append(s)

    say(
        f"# bench_audio_features ({platform.machine()}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f})"
    )
    if CLIP.exists():
        audio = read_audio(CLIP, SR)
        say(f"clip: {CLIP.name} ({len(audio) / SR:.1f} s, real English speech from ../shared/data)")
    else:
        audio = synthetic_speech(19.8)
        say(f"clip: ../shared/data not found ({CLIP}); using a 19.8 s synthetic syllable-like signal")
    seconds = len(audio) / SR

    say(f"\n## speed on the clip (best of {args.repeats})")
    extract_features(audio[:SR], SR, kind="phonemes")  # load hama once
    for kind in ["phonemes", "mel"]:
        feats = extract_features(audio, SR, kind=kind)
        t_feat = best_time(lambda k=kind: extract_features(audio, SR, kind=k), args.repeats)
        t_win = best_time(lambda f=feats: frame_windows(f, 25.0), args.repeats)
        say(
            f"{kind:9s} features {feats.values.shape} @ {feats.rate:g} Hz: {t_feat:6.3f} s = "
            f"{seconds / t_feat:7.1f}x real time; frame_windows @25 fps: {t_win * 1000:6.1f} ms "
            f"({seconds / t_win:7.0f}x); together {seconds / (t_feat + t_win):7.1f}x"
        )
    from hama import ASRModel, _engine

    if _engine.available():  # the same weights in hama's own native engine, for comparison
        session = ASRModel().session
        feed = {"waveform": audio[None].astype(np.float32), "waveform_lengths": np.array([len(audio)])}
        t1 = best_time(lambda: session.run(["log_probs", "out_lengths"], feed), args.repeats)
        say(f"phonemes in hama's native engine (reference, not used by nvp): {seconds / t1:.1f}x real time")

    say(f"\n## {args.minutes:g}-minute file (clip tiled), fresh process per kind")
    reps = int(np.ceil(args.minutes * 60 / seconds))
    long_audio = np.tile(audio, reps)[: int(args.minutes * 60 * SR)]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "long.wav"
        sf.write(path, long_audio, SR, subtype="PCM_16")
        del long_audio
        say(f"file: {path.stat().st_size / 2**20:.1f} MB 16-bit wav, {args.minutes * 60:.0f} s")
        for kind in ["phonemes", "mel"]:
            res = subprocess.run(
                [sys.executable, "-m", "scripts.bench.audio_features", "--child", kind, str(path)],
                capture_output=True,
                text=True,
                check=True,
            )
            r = json.loads(res.stdout.strip().splitlines()[-1])
            say(
                f"{kind:9s} features {tuple(r['features_shape'])} ({r['features_mb']:.0f} MB) in "
                f"{r['features_s']:.1f} s = {r['duration_s'] / r['features_s']:.1f}x real time; "
                f"windows {tuple(r['windows_shape'])} ({r['windows_mb']:.0f} MB) in {r['windows_s']:.1f} s"
            )
            say(
                f"          RSS after imports {r['rss_after_imports_mb']:.0f} MB, peak after features "
                f"{r['peak_rss_after_features_mb']:.0f} MB, peak after windows {r['peak_rss_mb']:.0f} MB"
            )
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
