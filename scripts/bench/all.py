"""Run nvp's benchmarks and print one table of throughput, latency and peak memory, with the machine.

    python -m scripts.bench.all [--quick] [--only tracking audio2exp renderer dub]

Each benchmark runs as its own process (``python -m scripts.bench.<name>``); its full report is printed
too and its figures are read from the ``BENCH_JSON`` line it prints. Benchmarks that read ../shared/data
fall back to nvp's own synthetic clips when it is absent (and say so). The machine may be shared: the load
average is printed with each run.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

QUICK = {
    "tracking": ["--seconds-1080p", "30"],
    "audio2exp": ["--minutes", "2", "--repeats", "1"],
    "renderer": ["--frames", "20", "--steps", "3", "--presets", "cpu", "quality"],
    "dub": ["--seconds", "5"],
}


def rows_for(name: str, r: dict) -> list[tuple[str, str, str, str]]:
    """(stage, measure, value, target) rows from one benchmark's BENCH_JSON."""
    if name == "tracking":
        return [
            (
                "tracking",
                "512² end to end (decode+detect+fit)",
                f"{r['512']['end_to_end_fps']:.1f} frames/s",
                "≥ 25",
            ),
            (
                "tracking",
                f"1080p, {r['1080p']['frames']} frames: peak RSS",
                f"{r['1080p']['peak_rss_gb']:.2f} GB",
                "≤ 2 GB",
            ),
        ]
    if name == "audio2exp":
        out = [
            (f"audio → expressions ({s['kind']})", "20 s clip", f"{s['x_realtime']:.1f}× real time", "≥ 50×")
            for s in r["speed"]
        ]
        out += [
            (
                f"audio → expressions ({m['kind']})",
                "long file: peak RSS",
                f"{m['rss_peak_mb']:.0f} MB",
                "bounded",
            )
            for m in r["memory"]
        ]
        return out
    if name == "renderer":
        out = [("renderer", "rasterization 512²", f"{r['raster_ms_512']:.1f} ms/frame", "")]
        for p in r["rows"]:
            target = "≥ 10 frames/s" if p["preset"] == "cpu" else ""
            out.append(
                (f"renderer ({p['preset']})", "render 512² frame", f"{p['render_fps']:.1f} frames/s", target)
            )
            out.append(
                (
                    f"renderer ({p['preset']})",
                    f"training step (batch {p['batch']})",
                    f"{p['train_s_per_step']:.2f} s",
                    "",
                )
            )
        out.append(("renderer", "peak RSS", f"{r['peak_rss_mb']:.0f} MB", ""))
        return out
    if name == "dub":
        return [
            (
                "dub",
                "frames/s (whole path)",
                f"{r['fps']:.1f} frames/s ({r['x_realtime']:.2f}× real time)",
                "",
            ),
            ("dub", "peak RSS", f"{r['peak_rss_mb']:.0f} MB", ""),
        ]
    return []


def machine() -> str:
    import torch

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    return (
        f"{cpu}, {os.cpu_count()} cores, {mem:.0f} GB RAM, {platform.system()} {platform.release()}, "
        f"Python {platform.python_version()}, torch {torch.__version__}"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="shorter runs (less accurate)")
    ap.add_argument("--only", nargs="+", choices=list(QUICK), default=list(QUICK))
    args = ap.parse_args(argv)
    table = []
    for name in args.only:
        cmd = [sys.executable, "-m", f"scripts.bench.{name}", *(QUICK[name] if args.quick else [])]
        print(f"\n===== bench_{name} (load {os.getloadavg()[0]:.2f}) =====", flush=True)
        proc = subprocess.run(cmd, capture_output=True, text=True)
        print(proc.stdout)
        found = [ln for ln in proc.stdout.splitlines() if ln.startswith("BENCH_JSON ")]
        if proc.returncode != 0 or not found:
            print(proc.stderr[-2000:])
            table.append((name, "FAILED", f"exit {proc.returncode}", ""))
            continue
        table.extend(rows_for(name, json.loads(found[-1][len("BENCH_JSON ") :])))
    print(f"\n## nvp benchmarks — {machine()}\n")
    print("| stage | measure | value | target |\n|---|---|---|---|")
    for row in table:
        print("| " + " | ".join(row) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
