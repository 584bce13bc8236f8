"""Benchmark the tracker: throughput (decode, detect, fit, end to end) and peak memory.

    python -m scripts.bench.tracking [--seconds-1080p 180]

1. A 512×512 talking-head video (``dfrf__cnn2_25fps.mp4`` from ../shared/data when present, otherwise
   nvp's own demo clip rendered at 512²): frames/s of decoding alone, of decode + landmark detection (and
   the optical flow around the lips), of the model fit, and end to end. Target: ≥ 25 frames/s end to end.
2. A 1920×1080 video of ``--seconds-1080p`` seconds (default 3 minutes), made by looping a 1080p clip from
   ../shared/data without re-encoding (or the demo clip rendered at 1080p): peak resident memory of
   ``nvp track`` in a fresh process. Target: ≤ 2 GB.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from scripts.common import VIDEOS

DATA = VIDEOS


def loop_media(src: Path, dst: Path, seconds: float, audio: bool = True) -> None:
    """Concatenate copies of ``src``'s first video stream (and audio stream, with ``audio``; packets copied,
    no re-encoding) up to ``seconds``."""
    import av

    with av.open(str(src)) as probe:
        clip = float(probe.duration / 1e6)
    with av.open(str(dst), "w") as out:
        outs: dict[str, object] = {}
        offsets: dict[str, int] = {}
        for _ in range(max(1, math.ceil(seconds / clip - 1e-6))):  # whole copies, no more than needed
            with av.open(str(src)) as inp:
                streams = [*inp.streams.video[:1], *(inp.streams.audio[:1] if audio else ())]
                first: dict[str, int] = {}
                ends: dict[str, int] = {}
                for st in streams:
                    if st.type not in outs:
                        outs[st.type] = out.add_stream_from_template(st)
                        offsets[st.type] = 0
                for pkt in inp.demux(streams):
                    if pkt.dts is None:
                        continue
                    kind = pkt.stream.type
                    first.setdefault(kind, pkt.dts)  # may be negative (encoder delay)
                    ends[kind] = max(ends.get(kind, pkt.dts), pkt.pts + (pkt.duration or 0))
                    pkt.pts += offsets[kind]
                    pkt.dts += offsets[kind]
                    pkt.stream = outs[kind]
                    out.mux(pkt)
                for kind, end in ends.items():  # the next copy starts where this one ended
                    offsets[kind] += end - first[kind]


def make_clip(size: int, seconds: float, path: Path) -> Path:
    from nvp.app.demo_clip import make_demo_clip

    make_demo_clip(path, seconds=seconds, size=size)
    return path


def bench_512(video: Path) -> dict:
    from nvp.face_model import default_face_model
    from nvp.media import iter_frames, probe_video
    from tracking.detect import detect_video
    from tracking.lipflow import lip_landmarks
    from tracking.track import fit_detections

    info = probe_video(video)
    t = time.perf_counter()
    n = sum(1 for _ in iter_frames(video))
    decode = n / (time.perf_counter() - t)
    t = time.perf_counter()
    det = detect_video(video, progress=False, lips=lip_landmarks(default_face_model()))  # as track_video
    t_det = time.perf_counter() - t
    t = time.perf_counter()
    fit_detections(det)
    t_fit = time.perf_counter() - t
    return {
        "video": f"{video.name} ({info.width}x{info.height}, {n} frames)",
        "decode_fps": decode,
        "decode_detect_fps": n / t_det,
        "fit_fps": n / t_fit,
        "end_to_end_fps": n / (t_det + t_fit),
    }


def bench_memory(video: Path) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "nvp.app.cli", "-q", "track", str(video), "-o", str(Path(tmp) / "track")]
        t = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.perf_counter() - t
        if proc.returncode:
            raise RuntimeError(proc.stderr[-2000:])
    peak_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return {"peak_rss_gb": peak_kb / 1024**2, "wall_s": wall}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds-1080p", type=float, default=180.0)
    args = ap.parse_args(argv)
    os.environ.setdefault("GLOG_minloglevel", "2")
    print(
        f"machine: {platform.node()} {platform.machine()}, {os.cpu_count()} cores, "
        f"Python {platform.python_version()}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        src512 = DATA / "dfrf__cnn2_25fps.mp4"
        if not src512.exists():
            print(f"{DATA} not found: using nvp's demo clip rendered at 512x512")
            src512 = make_clip(512, 60.0, tmp / "demo512.mp4")
        r = bench_512(src512)
        print(f"512x512: {r['video']}")
        for k in ("decode_fps", "decode_detect_fps", "fit_fps", "end_to_end_fps"):
            print(f"  {k:<20} {r[k]:8.1f} frames/s")
        print(f"  target end to end ≥ 25 frames/s: {'PASS' if r['end_to_end_fps'] >= 25 else 'FAIL'}")

        src1080 = DATA / "wav2lipgfpgan__kim_7s_raw.mp4"
        long = tmp / "long1080.mp4"
        if src1080.exists():
            loop_media(src1080, long, args.seconds_1080p, audio=False)
        else:
            print(f"{DATA} not found: using nvp's demo clip rendered at 1080x1080")
            make_clip(1080, args.seconds_1080p, long)
        from nvp.media import probe_video

        info = probe_video(long)
        m = bench_memory(long)
        print(f"1080p: {info.width}x{info.height}, {info.duration_s:.0f} s, {info.num_frames} frames")
        print(
            f"  nvp track peak RSS   {m['peak_rss_gb']:8.2f} GB  (wall {m['wall_s']:.0f} s, "
            f"{info.num_frames / m['wall_s']:.1f} frames/s incl. start-up)"
        )
        print(f"  target peak ≤ 2 GB: {'PASS' if m['peak_rss_gb'] <= 2 else 'FAIL'}")
    print("BENCH_JSON " + json.dumps({"512": r, "1080p": {**m, "frames": info.num_frames}}, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
