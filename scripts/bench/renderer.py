"""Benchmark the neural renderer: rasterization, rendering frames/s per preset, training s/step, memory.

    python -m scripts.bench.renderer [--frames 40] [--steps 6] [--presets cpu quality paper]

Synthetic input (speed does not depend on content): the face model posed by ``tracking.synthetic`` in a
512×512 frame; networks with random weights saved and loaded like trained ones.

1. Rasterization (moderngl, EGL/llvmpipe) of the 468-vertex face model at 512², ms/frame.
2. Rendering per preset, the full ``nvp dub`` per-frame path (``renderer.render.FrameRenderer.render``:
   crop, two rasterizations, neural texture, both U-Nets, paste into the 512² frame), frames/s.
3. Training per preset: seconds per optimisation step (batch of the preset), peak RSS.

Targets: the cpu preset renders >= 10 frames/s. The machine may be shared; the load average is printed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--presets", nargs="+", default=["cpu", "quality", "paper"])
    args = ap.parse_args(argv)

    from nvp.face_model import default_face_model
    from renderer.gl import GLRasterizer
    from renderer.networks import make_renderer, save_renderer
    from renderer.preset import PRESETS
    from renderer.render import FrameRenderer
    from renderer.train import RendererTrainConfig, train_renderer
    from renderer.train_data import FrameCache
    from tracking.synthetic import synthetic_tracked

    model = default_face_model()
    size = 512
    t = args.frames
    seq = synthetic_tracked(model, frames=t, size=size, focal=1024.0)
    verts = seq.camera_vertices(model, np.arange(t))
    print(
        f"# bench_renderer ({platform.machine()}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}, "
        f"torch {torch.__version__}, {torch.get_num_threads()} threads)\n"
    )
    results: dict = {"rows": []}
    from renderer.raster import empty_output

    with GLRasterizer(size, size) as gl:
        out = empty_output(size, size)
        for i in range(3):
            gl.rasterize(verts[i], model.triangles, model.uvs, seq.focal, seq.center, out=out)
        t0 = time.perf_counter()
        for i in range(t):
            gl.rasterize(verts[i], model.triangles, model.uvs, seq.focal, seq.center, out=out)
        raster_ms = (time.perf_counter() - t0) / t * 1000
    print(f"rasterization 512x512: {raster_ms:.2f} ms/frame\n")
    results["raster_ms_512"] = raster_ms
    frame = np.full((size, size, 3), 128, np.uint8)
    print("| preset | crop | U-Net base | dilated | parameters | render frames/s | train s/step (batch) |")
    print("|---|---|---|---|---|---|---|")
    for name in args.presets:
        p = PRESETS[name]
        with tempfile.TemporaryDirectory() as tmp:
            net = make_renderer(p)
            params = sum(x.numel() for x in net.parameters())
            save_renderer(net, Path(tmp), p, {})
            with FrameRenderer(Path(tmp), model, seq) as fr:
                n = max(3, args.frames // (20 if p.dilated else 1))
                fr.render(frame, 0, verts[0], verts[0])
                t0 = time.perf_counter()
                for i in range(n):
                    fr.render(frame, i % t, verts[i % t], verts[i % t])
                fps = n / (time.perf_counter() - t0)
            s = p.crop
            rng = np.random.default_rng(0)
            cache = FrameCache(
                frames=np.arange(8),
                crops=rng.integers(0, 255, (8, s, s, 3), dtype=np.uint8),
                uv=rng.random((8, s, s, 2)).astype(np.float16),
                mask=np.ones((8, s, s), bool),
                mouth=np.zeros((8, s, s), bool),
                region=np.ones((8, s, s), bool),
                boxes=np.zeros((8, 3), np.float32),
                vertices=verts[np.arange(8) % t].astype(np.float32),
                camera=np.array([seq.focal, *seq.center], np.float32),
            )
            steps = 2 if p.dilated else args.steps
            train_renderer(
                cache, RendererTrainConfig(preset=name, steps=1), Path(tmp) / "warm", progress=False
            )
            t0 = time.perf_counter()
            train_renderer(
                cache, RendererTrainConfig(preset=name, steps=steps), Path(tmp) / "t", progress=False
            )
            step_s = (time.perf_counter() - t0) / steps
        row = {
            "preset": name,
            "crop": s,
            "base": p.base,
            "dilated": p.dilated,
            "parameters": params,
            "render_fps": fps,
            "train_s_per_step": step_s,
            "batch": p.batch,
        }
        results["rows"].append(row)
        cells = [
            name,
            s,
            p.base,
            p.dilated,
            f"{params / 1e6:.2f} M",
            f"{fps:.1f}",
            f"{step_s:.2f} ({p.batch})",
        ]
        print("| " + " | ".join(map(str, cells)) + " |")
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    results["peak_rss_mb"] = rss
    print(f"\npeak RSS {rss:.0f} MB")
    print("BENCH_JSON " + json.dumps(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
