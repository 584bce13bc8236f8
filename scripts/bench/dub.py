"""Benchmark ``nvp dub``: frames/s, peak memory and where the time goes, on a person bundle.

    python -m scripts.bench.dub [--seconds 10] [--person PERSON_DIR | --size 512]

Without ``--person``, a bundle is made from nvp's demo target (a ``--size``² talking astronaut, renderer
trained for 2 steps: speed does not depend on training). The driving audio is ``--seconds`` of a
synthetic voice; the dub runs in a fresh process so its peak RSS is its own, a second time while another
process keeps one core busy (a Python busy loop), and a third time under ``cProfile`` with one render
worker on one PyTorch thread, as each of the parallel workers has (``NVP_THREADS=1 OMP_NUM_THREADS=1``:
cProfile sees only its own thread, and the dub renders frames in parallel threads otherwise; with PyTorch's
two threads in one worker, their busy waiting on a loaded machine made the networks look several times
their share), which splits the wall time into stages (decode, rasterize, network, detail transfer,
crop and paste, encode, audio → expressions; profiling slows everything a little, so the shares matter,
not the sums).
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

STAGES = {
    "decode": ("nvp/media/frames.py", "frames_at"),
    "rasterize": ("renderer/inputs.py", "__call__"),
    "network": ("renderer/networks.py", "forward"),
    "detail transfer": ("renderer/band.py", "_moved"),
    "detail band": ("renderer/band.py", "_band"),
    "crop": ("renderer/crop.py", "cut"),
    "teeth choice": ("renderer/interior.py", "entry_costs"),
    "paste": ("renderer/crop.py", "paste_region"),
    "encode": ("nvp/media/writer.py", "write"),
    "audio → expressions": ("nvp/app/dub.py", "speech_expressions"),
}
"""Stage → (file, function) whose cumulative time is the stage's."""


def allocator_option(ap: argparse.ArgumentParser) -> None:
    """``--glibc-defaults`` of the benchmarks that run nvp in their own process (:func:`set_allocator`)."""
    ap.add_argument(
        "--glibc-defaults",
        action="store_true",
        help="leave glibc's allocator as it comes (nvp keeps freed memory, nvp/allocator.py): for comparing",
    )


def set_allocator(glibc_defaults: bool) -> None:
    """Keep freed memory as the CLI does, unless ``--glibc-defaults``."""
    from nvp.allocator import keep_freed_memory

    if not glibc_defaults:
        keep_freed_memory()


def child(audio: str, person: str, out: str, profile: bool = False, glibc_defaults: bool = False) -> None:
    import cProfile
    import pstats

    from nvp.app.dub import dub

    set_allocator(glibc_defaults)
    prof = cProfile.Profile() if profile else None
    t0 = time.perf_counter()
    if prof:
        prof.enable()
    r = dub(audio, person, out, progress=False)
    if prof:
        prof.disable()
    wall = time.perf_counter() - t0
    rss = peak_rss_mb()
    m = {"frames": r.frames, "audio_s": r.audio_seconds, "wall_s": wall, "peak_rss_mb": rss}
    if prof:
        stats = pstats.Stats(prof).stats  # (file, line, function) → (calls, prim calls, tt, ct, callers)
        m["stages_s"] = {  # the outermost matching function (largest cumulative time)
            stage: max(
                (ct for (f, _, fn), (_, _, _, ct, _) in stats.items() if f.endswith(path) and fn == name),
                default=0.0,
            )
            for stage, (path, name) in STAGES.items()
        }
    print(json.dumps(m))


def demo_person(folder: Path, size: int) -> Path:
    """A person bundle in ``folder`` from nvp's demo target (a ``size``² talking astronaut, 4 s), its renderer
    trained for 2 steps: enough for speed and memory, which do not depend on training."""
    from nvp.app.demo_clip import make_demo_clip
    from nvp.app.fit import FitConfig, fit

    clip = make_demo_clip(folder / "target.mp4", seconds=4.0, size=size)
    return fit(clip.path, folder / "person", FitConfig(steps=2), progress=False).root


def run_child(audio: Path, person: Path, out: Path, *extra: str, env: dict | None = None) -> dict:
    """:func:`child`'s dub in a fresh process (its peak RSS its own): what it measured."""
    cmd = [sys.executable, "-m", "scripts.bench.dub", "--child", str(audio), str(person), str(out), *extra]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=True, env=env)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def peak_rss_mb() -> float:
    """This process's peak resident memory in MB since it started: Linux's ``VmHWM``, not ``ru_maxrss``,
    which a process started by ``subprocess`` inherits from its parent (the kernel keeps the larger of the
    two across the ``exec``: a child of a parent that peaked at 940 MB reports at least 940 MB)."""
    try:
        status = Path("/proc/self/status").read_text()
    except OSError:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    kb = next(line.split()[1] for line in status.splitlines() if line.startswith("VmHWM:"))
    return int(kb) / 1024


def cpu_name() -> str:
    """The CPU's model name (``/proc/cpuinfo``) and whether it computes bfloat16 natively (the networks'
    precision follows it, :func:`renderer.networks.fast_bf16`); the machine type elsewhere."""
    try:
        info = Path("/proc/cpuinfo").read_text()
    except OSError:
        return platform.machine()
    names = [line.split(":", 1)[1].strip() for line in info.splitlines() if line.startswith("model name")]
    flags = next((line for line in info.splitlines() if line.startswith("flags")), "").split()
    bf16 = "avx512_bf16" in flags or "amx_bf16" in flags
    return f"{names[0] if names else platform.machine()}, {'with' if bf16 else 'no'} bfloat16"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--person", type=Path)
    ap.add_argument("--size", type=int, default=512, help="demo target's frame size without --person")
    ap.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    ap.add_argument("--profile", action="store_true", help=argparse.SUPPRESS)
    allocator_option(ap)
    args = ap.parse_args(argv)
    if args.child:
        child(*args.child, profile=args.profile, glibc_defaults=args.glibc_defaults)
        return 0
    import numpy as np
    import soundfile as sf

    from nvp.app.demo_voice import AUDIO_RATE, speech_script, synth_voice

    print(f"# bench_dub ({cpu_name()}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f})")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        person = args.person or demo_person(tmp, args.size)
        rng = np.random.default_rng(3)
        wav = tmp / "speech.wav"
        sf.write(wav, synth_voice(speech_script(args.seconds, rng), args.seconds, rng), AUDIO_RATE)

        def run(*extra: str, env: dict | None = None) -> dict:
            extra += ("--glibc-defaults",) if args.glibc_defaults else ()
            return run_child(wav, person, tmp / "dub.mp4", *extra, env=env)

        m = run()
        stages = run("--profile", env={**os.environ, "NVP_THREADS": "1", "OMP_NUM_THREADS": "1"})
        busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])  # another process, one core
        try:
            time.sleep(1.0)
            loaded = run()
        finally:
            busy.kill()
    m["fps"] = m["frames"] / m["wall_s"]
    m["x_realtime"] = m["audio_s"] / m["wall_s"]
    m["profiled_wall_s"], m["stages_s"] = stages["wall_s"], stages["stages_s"]
    m["busy_fps"] = loaded["frames"] / loaded["wall_s"]
    print(f"person: {person if args.person else f'demo target, {args.size}x{args.size}'}")
    print(
        f"dub of {m['audio_s']:.1f} s: {m['frames']} frames in {m['wall_s']:.1f} s = {m['fps']:.1f} frames/s "
        f"({m['x_realtime']:.2f}x real time), peak RSS {m['peak_rss_mb']:.0f} MB"
    )
    print(
        f"with another process keeping one core busy: {m['busy_fps']:.1f} frames/s "
        f"({m['busy_fps'] / m['fps']:.0%} of the above)"
    )
    print(f"\nwhere the time goes (profiled run on one render worker, {stages['wall_s']:.1f} s wall):\n")
    print("| stage | s | ms/frame | share |\n|---|---|---|---|")
    rest = stages["wall_s"] - sum(stages["stages_s"].values())
    for stage, sec in [*stages["stages_s"].items(), ("other", rest)]:
        print(f"| {stage} | {sec:.2f} | {1000 * sec / m['frames']:.1f} | {sec / stages['wall_s']:.0%} |")
    print("BENCH_JSON " + json.dumps(m))
    return 0


if __name__ == "__main__":
    sys.exit(main())
