"""Slow pure-torch reference rasterizer, the ground truth the OpenGL backend is tested against.

Straightforward and explicit rather than fast (a Python loop over triangles): for each triangle, the
pixel centres ``(c + 0.5, r + 0.5)`` inside its screen-space bounding box are tested with the three edge
functions (a centre exactly on an edge counts as inside), screen-space barycentrics ``l_i`` are turned
into perspective-correct ones ``b_i = (l_i / z_i) / sum_j (l_j / z_j)``, the depth of the surface point is
``1 / sum_j (l_j / z_j)``, and a z-buffer keeps the nearest (the first drawn on an exact tie, like
OpenGL's ``<`` depth test). Computation is in float64.

Differences from ``renderer.gl.GLRasterizer`` (all confined to a few pixels): OpenGL snaps vertices to
a sub-pixel grid and applies the top-left fill rule to centres exactly on an edge; its depth test works
on 24-bit window depth; and it clips triangles that cross the near or far plane, while this reference
drops them entirely.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from renderer.raster import RasterOutput, as_numpy, check_mesh, check_output, depth_range


def rasterize_reference(
    vertices_cam: np.ndarray | torch.Tensor,
    triangles: np.ndarray | torch.Tensor,
    uvs: np.ndarray | torch.Tensor,
    focal: float,
    center: np.ndarray | torch.Tensor,
    width: int,
    height: int,
    near: float | None = None,
    far: float | None = None,
) -> RasterOutput:
    """Rasterize one mesh seen by an OpenCV pinhole camera (reference implementation).

    Args:
        vertices_cam: ``(V, 3)`` vertices in the camera frame (x right, y down, z forward), any units.
        triangles: ``(F, 3)`` vertex indices (any winding; no culling).
        uvs: ``(V, 2)`` per-vertex texture coordinates.
        focal: focal length in pixels.
        center: ``(2,)`` principal point in pixels.
        width, height: image size in pixels.
        near, far: clipping planes (units of the vertices), None for automatic (see
            :func:`renderer.raster.depth_range`); triangles with a vertex outside ``(near, far)`` are
            dropped.

    Returns:
        ``RasterOutput`` of size ``(height, width)``, row 0 = top of the image.
    """
    verts_np = as_numpy(vertices_cam, np.float64)
    tris_np = as_numpy(triangles, np.int64)
    uv_np = as_numpy(uvs, np.float64)
    c = as_numpy(center, np.float64).reshape(-1)
    check_mesh(verts_np, tris_np, uv_np, c)
    near, far = depth_range(verts_np[:, 2], near, far)

    verts = torch.from_numpy(verts_np)
    z = verts[:, 2]
    safe_z = torch.where(z > 0, z, torch.ones_like(z))
    pix = focal * verts[:, :2] / safe_z[:, None] + torch.from_numpy(c)[None]  # (V,2) column, row

    zbuf = torch.full((height, width), math.inf, dtype=torch.float64)
    tri_id = torch.full((height, width), -1, dtype=torch.int64)
    bary = torch.zeros((height, width, 3), dtype=torch.float64)

    pix_l = pix.tolist()
    z_l = z.tolist()
    for f, (i0, i1, i2) in enumerate(tris_np.tolist()):
        zs = (z_l[i0], z_l[i1], z_l[i2])
        if min(zs) <= near or max(zs) >= far:
            continue
        (x0, y0), (x1, y1), (x2, y2) = pix_l[i0], pix_l[i1], pix_l[i2]
        area = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)
        if area == 0.0:
            continue
        # columns whose centre c + 0.5 lies in [min x, max x], clamped to the image
        c_lo = max(math.ceil(min(x0, x1, x2) - 0.5), 0)
        c_hi = min(math.floor(max(x0, x1, x2) - 0.5), width - 1)
        r_lo = max(math.ceil(min(y0, y1, y2) - 0.5), 0)
        r_hi = min(math.floor(max(y0, y1, y2) - 0.5), height - 1)
        if c_lo > c_hi or r_lo > r_hi:
            continue
        px = torch.arange(c_lo, c_hi + 1, dtype=torch.float64)[None, :] + 0.5
        py = torch.arange(r_lo, r_hi + 1, dtype=torch.float64)[:, None] + 0.5
        # screen-space barycentrics from the edge functions (sign-normalised by the signed area)
        l0 = ((x2 - x1) * (py - y1) - (y2 - y1) * (px - x1)) / area
        l1 = ((x0 - x2) * (py - y2) - (y0 - y2) * (px - x2)) / area
        l2 = ((x1 - x0) * (py - y0) - (y1 - y0) * (px - x0)) / area
        inside = (l0 >= 0) & (l1 >= 0) & (l2 >= 0)
        if not bool(inside.any()):
            continue
        w = torch.stack([l0 / zs[0], l1 / zs[1], l2 / zs[2]], dim=-1)  # (h,w,3)
        inv_depth = w.sum(-1)
        depth = 1.0 / inv_depth
        rows, cols = slice(r_lo, r_hi + 1), slice(c_lo, c_hi + 1)
        win = inside & (depth < zbuf[rows, cols])
        zbuf[rows, cols] = torch.where(win, depth, zbuf[rows, cols])
        tri_id[rows, cols] = torch.where(win, f, tri_id[rows, cols])
        bary[rows, cols] = torch.where(win[..., None], w / inv_depth[..., None], bary[rows, cols])

    mask = tri_id >= 0
    corner_uv = torch.from_numpy(uv_np)[torch.from_numpy(tris_np)]  # (F,3,2)
    uv = (bary[..., None] * corner_uv[tri_id.clamp(min=0)]).sum(-2) * mask[..., None]
    return RasterOutput(
        triangle_id=tri_id,
        barycentric=bary.float(),
        uv=uv.float(),
        depth=torch.where(mask, zbuf, torch.zeros_like(zbuf)).float(),
        mask=mask,
    )


class TorchRasterizer:
    """The reference rasterizer behind the same interface as ``renderer.gl.GLRasterizer`` (no GL needed).

    Args:
        width, height: output image size in pixels.
        near, far: clipping planes, None for automatic (see :func:`rasterize_reference`).
    """

    def __init__(self, width: int, height: int, near: float | None = None, far: float | None = None) -> None:
        if width <= 0 or height <= 0:
            raise ValueError(f"width and height must be positive, got {width}x{height}")
        self.width = int(width)
        self.height = int(height)
        self.near = near
        self.far = far

    def __enter__(self) -> TorchRasterizer:
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def release(self) -> None:
        """Nothing to free (for interface parity with ``GLRasterizer``)."""

    def rasterize(
        self,
        vertices_cam: np.ndarray | torch.Tensor,
        triangles: np.ndarray | torch.Tensor,
        uvs: np.ndarray | torch.Tensor,
        focal: float,
        center: np.ndarray | torch.Tensor,
        out: RasterOutput | None = None,
    ) -> RasterOutput:
        """See :func:`rasterize_reference`; ``out`` is filled in place like ``GLRasterizer.rasterize``."""
        if out is not None:
            check_output(out, self.height, self.width)
        res = rasterize_reference(
            vertices_cam, triangles, uvs, focal, center, self.width, self.height, self.near, self.far
        )
        if out is None:
            return res
        for name in ("triangle_id", "barycentric", "uv", "depth", "mask"):
            getattr(out, name).copy_(getattr(res, name))
        return out
