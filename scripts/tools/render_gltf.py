"""Render frames of an exported face animation (``nvp predict --export anim.glb``) to look at it.

    python -m scripts.tools.render_gltf anim.glb -o sheet.png [--frames 0 10 20] [--size 256]

Reads the file back (``nvp.gltf.read_glb``, pygltflib), puts each chosen keyframe's mesh 40 cm in front of
a pinhole camera and rasterizes it with nvp's rasterizer (``renderer.gl``), shaded by the surface normal
(head-on light); the frames go side by side into one PNG, each labelled with its time and the inner-lip
gap (cm) of the face model's mesh.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def shade(vertices_cam: np.ndarray, triangles: np.ndarray, size: int, gl) -> np.ndarray:
    """``(size, size)`` uint8 grey image of the mesh (camera frame, cm) lit from the camera."""
    out = gl.rasterize(vertices_cam, triangles, np.zeros((len(vertices_cam), 2)), size * 2.2, [size / 2] * 2)
    v = vertices_cam[triangles]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
    light = np.abs(n[:, 2])  # towards the camera (either winding)
    tid = out.triangle_id.numpy()
    img = np.where(tid >= 0, 40 + 215 * light[np.maximum(tid, 0)], 0)
    return img.astype(np.uint8)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("animation", type=Path, help=".glb written by nvp predict --export")
    ap.add_argument("-o", "--output", type=Path, required=True, help="output PNG")
    ap.add_argument("--frames", type=int, nargs="*", help="keyframes (default: 6 spread over the animation)")
    ap.add_argument("--size", type=int, default=256, help="pixels per frame")
    args = ap.parse_args(argv)
    import cv2

    from nvp.gltf import CM_TO_GLTF, read_glb
    from renderer.gl import GLRasterizer

    anim = read_glb(args.animation)
    t = len(anim.weights)
    frames = args.frames or np.linspace(0, t - 1, 6).round().astype(int).tolist()
    tiles = []
    with GLRasterizer(args.size, args.size) as gl:
        for j in frames:
            cam = anim.vertices(j) / CM_TO_GLTF + [0, 0, 40]  # back to the camera frame (cm, y down)
            img = cv2.cvtColor(shade(cam, anim.triangles, args.size, gl), cv2.COLOR_GRAY2BGR)
            gap = float(np.linalg.norm(cam[13] - cam[14]))  # inner-lip midpoints of the face model's mesh
            label = f"{j / anim.fps:.2f}s gap {gap:.2f}"
            cv2.putText(img, label, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 255, 255), 1, cv2.LINE_AA)
            tiles.append(img)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.output), np.hstack(tiles))
    print(
        f"{len(tiles)} frames of {t} ({anim.fps:.2f} fps, {len(anim.target_names)} morph targets)"
        f" → {args.output}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
