"""Latency and keeping up of ``nvp live`` on this machine.

    python -m scripts.bench.live --person person/ --audio speech.wav [--busy] [--seconds 20]

Plays the first ``--seconds`` of the audio in real time into ``nvp.app.live.live`` (frames to a fragmented
mp4 in a temporary folder) and prints: frames, dropped frames, output frames/s against the footage's rate,
latency from the arrival of a frame's audio to the frame being written (median, 95th percentile, max;
the first 10 % of frames, the warm-up, left out), and the part of it that is the look-ahead. ``--busy``
keeps one core busy with another process meanwhile (as when the machine does something else).
Also prints how closely the streamed expressions follow whole-file prediction for the same audio.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from scripts.bench.dub import allocator_option, set_allocator


def _spin(stop) -> None:
    x = 0
    while not stop.is_set():
        for _ in range(100000):
            x += 1


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--person", type=Path, required=True, help="person bundle from nvp fit")
    ap.add_argument("--audio", type=Path, required=True, help="speech to play (any audio or video file)")
    ap.add_argument("--seconds", type=float, default=20.0, help="play this much of it")
    ap.add_argument("--busy", action="store_true", help="keep one core busy with another process")
    ap.add_argument("--max-lag", type=float, default=1.0)
    ap.add_argument(
        "--fps", type=float, help="the stream's frame rate (nvp live --fps; default the person's)"
    )
    allocator_option(ap)
    args = ap.parse_args(argv)
    set_allocator(args.glibc_defaults)
    import soundfile as sf

    from nvp.app.dub import load_person
    from nvp.app.live import live
    from nvp.bundle import PersonBundle
    from nvp.face_model import default_face_model
    from nvp.media import read_audio
    from nvp.person import predict_expressions
    from nvp.stream import ExpressionStream

    audio = read_audio(args.audio, 16000)[: int(args.seconds * 16000)]
    stop = mp.Event()
    spinner = mp.Process(target=_spin, args=(stop,), daemon=True) if args.busy else None
    if spinner:
        spinner.start()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            wav = Path(tmp) / "speech.wav"
            sf.write(wav, audio, 16000)
            t0 = time.perf_counter()
            r = live(
                wav, args.person, Path(tmp) / "live.mp4", realtime=True, max_lag_s=args.max_lag, fps=args.fps
            )
            wall = time.perf_counter() - t0
    finally:
        stop.set()
        if spinner:
            spinner.join()
    lat = r.latency_s[len(r.latency_s) // 10 :]
    print(f"person {args.person}, audio {args.audio.name} ({r.audio_seconds:.1f} s), busy core: {args.busy}")
    print(
        f"frames {r.frames}, dropped {r.dropped} ({r.dropped / r.frames:.0%}), rendered "
        f"{(r.frames - r.dropped) / wall:.1f} frames/s for a {r.fps:.2f} fps stream, wall {wall:.1f} s"
    )
    print(
        f"latency after warm-up: median {np.median(lat):.3f} s, p95 {np.percentile(lat, 95):.3f} s, "
        f"max {lat.max():.3f} s; look-ahead {r.lookahead_s:.2f} s of it, beyond it: median "
        f"{np.median(lat) - r.lookahead_s:.3f} s"
    )
    person = load_person(PersonBundle.load(args.person))
    fps = person.tracked.fps
    whole = predict_expressions(audio, 16000, fps, person.style, person.net)
    stream = ExpressionStream(person.style, person.net, fps)
    parts = [stream.push(audio[i : i + 3200]) for i in range(0, len(audio), 3200)] + [stream.finish()]
    model = default_face_model()
    ident = person.tracked.identity
    g_s, g_w = (model.inner_lip_gap(ident, e) for e in (np.concatenate(parts), whole))
    print(f"streamed vs whole-file expressions: inner-lip gap correlation {np.corrcoef(g_s, g_w)[0, 1]:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
