"""Benchmark the rasterizers on the shipped face model: ms per frame, rasterization + readback.

Usage: ``.venv/bin/python -m scripts.bench.raster [--frames 200] [--sizes 512 256] [--ref-frames 3]``

Each frame poses the face model differently (head turn and mouth opening varying over the run), so the
vertex buffer is updated on every call, as in real use. The timing covers everything ``rasterize`` does:
projection to clip space, vertex upload, drawing, readback of both float32 targets, and conversion to a
``RasterOutput`` of torch tensors. llvmpipe renders on all CPU cores, so other load on the machine shows
up directly in the mean; the minimum approximates the unloaded cost.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np


def rotation_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def make_frames(model, n: int, size: int) -> tuple[list[np.ndarray], float, np.ndarray]:
    """``n`` posed meshes in camera coordinates, a focal length and principal point for ``size``²."""
    ident = np.zeros(model.num_id)
    frames = []
    for i in range(n):
        t = i / max(n - 1, 1)
        exp = np.zeros(model.num_exp)
        exp[0] = 3.0 * np.sin(np.pi * 4 * t) ** 2
        verts = model.vertices(ident, exp) @ rotation_y(np.deg2rad(30 * np.sin(2 * np.pi * t))).T
        frames.append(verts + np.array([0.0, 0.0, 50.0]))
    focal = size * 50.0 / 20.0  # face (~15 cm wide) fills about three quarters of the image
    return frames, focal, np.array([size / 2, size / 2])


def time_calls(rasterize, frames, warmup: int) -> list[float]:
    for verts in frames[:warmup]:
        rasterize(verts)
    times = []
    for verts in frames:
        t0 = time.perf_counter()
        rasterize(verts)
        times.append((time.perf_counter() - t0) * 1e3)
    return times


def bench_size(model, size: int, n_frames: int, warmup: int, ref_frames: int) -> None:
    from renderer.gl import GLRasterizer
    from renderer.raster_ref import rasterize_reference

    tris, uvs = model.triangles, model.uvs
    frames, focal, center = make_frames(model, n_frames, size)
    with GLRasterizer(size, size) as gl:
        times = time_calls(lambda v: gl.rasterize(v, tris, uvs, focal, center), frames, warmup)
        out = gl.rasterize(frames[0], tris, uvs, focal, center)
        times_out = time_calls(lambda v: gl.rasterize(v, tris, uvs, focal, center, out=out), frames, warmup)
        renderer = gl.renderer_name
        cover = float(out.mask.float().mean())
    ref_times = time_calls(
        lambda v: rasterize_reference(v, tris, uvs, focal, center, size, size), frames[:ref_frames], warmup=1
    )
    print(f"{size}x{size}: GL on {renderer}, face covers {cover:.0%} of the image")
    for label, ts in (("new output tensors", times), ("out= reused tensors", times_out)):
        print(
            f"  GL, {label}: mean {statistics.mean(ts):.2f} ms/frame, median {statistics.median(ts):.2f}, "
            f"min {min(ts):.2f}, p95 {np.percentile(ts, 95):.2f} over {len(ts)} frames"
        )
    print(f"  torch reference: {statistics.mean(ref_times):.0f} ms/frame over {len(ref_times)} frames")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=200, help="timed frames per size (after warm-up)")
    parser.add_argument("--warmup", type=int, default=10, help="untimed frames first")
    parser.add_argument("--sizes", type=int, nargs="+", default=[512, 256], help="square image sizes")
    parser.add_argument("--ref-frames", type=int, default=3, help="frames for the slow torch reference")
    args = parser.parse_args()

    import torch

    from nvp.face_model import default_face_model

    model = default_face_model()
    print(
        f"face model: {model.num_vertices} vertices, {len(model.triangles)} triangles; torch threads "
        f"{torch.get_num_threads()}"
    )
    for size in args.sizes:
        bench_size(model, size, args.frames, args.warmup, args.ref_frames)


if __name__ == "__main__":
    main()
