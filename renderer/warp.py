"""Moving the footage's own pixels with the geometry: where each rendered surface point is in a source frame.

A dub changes the mouth and jaw of a footage frame whose every pixel is real: stubble, skin pores and lip
texture are there, only in the old shape. The rasterized new geometry says, for every crop pixel, which
surface point (triangle, barycentrics) it shows; the same surface point under the source frame's tracked
geometry lands at a known pixel of the source frame. Sampling the source there moves its detail with the
surface (a mesh-driven warp). Pure functions; shapes: ``S`` crop side, ``V`` vertices, ``F`` triangles.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F


def surface_points(
    triangle_id: torch.Tensor, barycentric: torch.Tensor, triangles: torch.Tensor, values: torch.Tensor
) -> torch.Tensor:
    """Per-pixel interpolation of per-vertex ``values`` ``(V, C)`` over the visible surface.

    Args:
        triangle_id: ``(S, S)`` int64 visible triangle (-1 = background).
        barycentric: ``(S, S, 3)`` float32 barycentrics of the pixel centre in that triangle.
        triangles: ``(F, 3)`` int64 vertex indices.
        values: ``(V, C)`` float per-vertex values (e.g. the source frame's pixel positions).

    Returns:
        ``(S, S, C)`` float32, 0 on the background.
    """
    tri = triangles[triangle_id.clamp_min(0)]  # (S, S, 3)
    out = (values[tri] * barycentric[..., None]).sum(-2)
    return out * (triangle_id >= 0)[..., None]


def source_positions(
    triangle_id: torch.Tensor,
    barycentric: torch.Tensor,
    triangles: torch.Tensor,
    source_pixels: torch.Tensor,
    source_depth: torch.Tensor,
    source_zbuffer: torch.Tensor,
    source_crop: tuple[float, np.ndarray],
    usable: torch.Tensor,
    tolerance: float = 0.3,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Where the surface point seen at each crop pixel is in the source frame, and whether it is seen there.

    Args:
        triangle_id, barycentric: fragments of the geometry being rendered, ``(S, S)`` and ``(S, S, 3)``.
        triangles: ``(F, 3)`` int64.
        source_pixels: ``(V, 2)`` the vertices under the source frame's tracked geometry, in source-frame
            pixels (row 0 = top).
        source_depth: ``(V,)`` their camera z (cm).
        source_zbuffer: ``(S, S)`` camera z of the nearest surface in the source frame's crop (0 = none).
        source_crop: ``(scale, origin)`` of the source crop: crop pixel = (frame pixel - origin) · scale.
        usable: ``(F,)`` bool: triangles whose source pixels may be moved (not the mouth interior, whose
            source may be closed when the new geometry opens it).
        tolerance: depth difference (cm) above which the point is hidden in the source (occluded).

    Returns:
        ``(S, S, 2)`` source-frame pixel positions and ``(S, S)`` float32 validity (1 = the surface point is
        on a usable triangle and visible in the source).
    """
    pos = surface_points(triangle_id, barycentric, triangles, source_pixels)
    z = surface_points(triangle_id, barycentric, triangles, source_depth[:, None])[..., 0]
    scale, origin = source_crop
    crop_xy = (pos - torch.as_tensor(origin, dtype=pos.dtype)) * scale
    s = source_zbuffer.shape[0]
    ij = crop_xy.floor().long()
    inside = (ij >= 0).all(-1) & (ij < s).all(-1)
    ij = ij.clamp(0, s - 1)
    seen = source_zbuffer[ij[..., 1], ij[..., 0]]
    visible = inside & (seen > 0) & ((seen - z).abs() < tolerance)
    valid = visible & (triangle_id >= 0) & usable[triangle_id.clamp_min(0)]
    return pos, valid.float()


def sample_pixels(image: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
    """Bilinear samples ``(C, ...)`` of ``image`` ``(C, H, W)`` at pixel positions ``(..., 2)`` (x, y with
    pixel centres at +0.5; the border is replicated)."""
    c, h, w = image.shape
    flat = positions.reshape(1, -1, 1, 2)
    grid = torch.stack([2 * flat[..., 0] / w - 1, 2 * flat[..., 1] / h - 1], -1)
    out = F.grid_sample(
        image[None].float(), grid, mode="bilinear", padding_mode="border", align_corners=False
    )
    return out[0, :, :, 0].reshape(c, *positions.shape[:-1])
