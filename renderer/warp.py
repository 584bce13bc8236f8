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

from renderer.masks import gaussian_blur


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
    # pixel position and depth in one pass over the fragments (it runs for every rendered frame)
    values = torch.cat([source_pixels, source_depth[:, None].to(source_pixels)], 1)
    both = surface_points(triangle_id, barycentric, triangles, values)
    pos, z = both[..., :2], both[..., 2]
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


def sample_pixels(image: torch.Tensor, positions: torch.Tensor, mode: str = "bilinear") -> torch.Tensor:
    """Samples ``(C, ...)`` of ``image`` ``(C, H, W)`` at pixel positions ``(..., 2)`` (x, y with pixel
    centres at +0.5; the border is replicated), or ``(B, C, ...)`` of a batch ``(B, C, H, W)`` at ``(B, ...,
    2)``. ``mode="bicubic"`` for detail that must stay sharp: bilinear reads between pixels average away fine
    texture (on real footage at random sub-pixel shifts the energy of detail finer than a 5×5 blur keeps
    0.63-0.95 of itself, mean 0.76; bicubic 0.94-1.00, mean 0.97, like Lanczos-3's 0.98, at a tenth of its
    cost)."""
    batch = image.dim() == 4
    images, at = (image, positions) if batch else (image[None], positions[None])
    b, c, h, w = images.shape
    flat = at.reshape(b, -1, 1, 2)
    grid = torch.stack([2 * flat[..., 0] / w - 1, 2 * flat[..., 1] / h - 1], -1)
    out = F.grid_sample(images.float(), grid, mode=mode, padding_mode="border", align_corners=False)
    out = out[..., 0].reshape(b, c, *at.shape[1:-1])
    return out if batch else out[0]


def mesh_edges(triangles: np.ndarray) -> np.ndarray:
    """``(E, 2)`` the distinct edges of ``triangles`` ``(F, 3)``."""
    pairs = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [0, 2]]])
    return np.unique(np.sort(pairs, 1), axis=0)


def rigidity(target: np.ndarray, source: np.ndarray, edges: np.ndarray, scale: float) -> np.ndarray:
    """``(V,)`` float32 in [0, 1]: how rigidly the surface around each vertex moved between a source
    frame's geometry and the geometry being rendered (``(V, 3)`` each, any rigid pose): 1 minus the largest
    relative length change of the vertex's ``edges`` over ``scale``, clipped. Skin that moved without
    stretching (a chin carried down by the jaw) keeps its texture and creases; where it stretched or
    folded (lip corners, cheeks beside a widening mouth) the creases and shading change."""

    def lengths(v: np.ndarray) -> np.ndarray:
        return np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1)

    before = lengths(np.asarray(source, np.float64))
    strain = np.abs(lengths(np.asarray(target, np.float64)) - before) / np.maximum(before, 1e-6)
    worst = np.zeros(len(target))
    np.maximum.at(worst, edges[:, 0], strain)
    np.maximum.at(worst, edges[:, 1], strain)
    return np.clip(1.0 - worst / scale, 0.0, 1.0).astype(np.float32)


def smooth(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """``x`` ``(B, C, H, W)`` low-passed like a Gaussian of about ``sigma`` pixels (≥ 1): averaged over 2×2
    pixels, blurred by ``sigma / 2`` (:func:`renderer.masks.gaussian_blur`) and bilinearly enlarged back.
    For ``sigma`` 2 the impulse response has a spread of 2.18 pixels; on a 7-channel 144×192 window it takes
    1.3 ms instead of 3.0 for the full-size blur (one core), and it runs on every rendered frame."""
    half = sigma / 2
    small = gaussian_blur(F.avg_pool2d(x, 2, ceil_mode=True), 2 * int(np.ceil(2.5 * half)) + 1, half)
    return F.interpolate(small, size=x.shape[-2:], mode="bilinear", align_corners=False)


def moved_detail(
    source: torch.Tensor,
    source_crop_res: torch.Tensor,
    source_low: torch.Tensor,
    render_band: torch.Tensor,
    fine: torch.Tensor,
    band: torch.Tensor,
) -> torch.Tensor:
    """The footage's detail to add to an upsampled render, at the output's resolution.

    All inputs are at the same output pixels: ``source`` ``(C, h, w)`` the source frame moved onto the
    new surface (one sample of it at full resolution), ``source_crop_res`` the same point of its copy at the
    crop's resolution, ``source_low`` of its low-pass (:func:`smooth` at the crop, about ``sigma`` crop
    pixels), ``render_band`` the render's own detail finer than that (upsampled; it is replaced).
    ``fine`` ``(1, h, w)`` weighs the detail finer than the crop can hold, ``band`` ``(1, h, w)`` the band
    between that and ``sigma`` (where the surface moved rigidly, so creases and shading are the source's
    too); both in [0, 1].

    The networks render shape and shading well but soften the skin's detail even at the crop's own
    resolution; the footage has it. Where both weights are 1 the band comes from the source frame at full
    resolution (``source_crop_res`` cancels: nothing is moved into the crop and enlarged again, which would
    blur it twice), and where nothing moved render + detail is the source frame itself."""
    return band * (source_crop_res - source_low - render_band) + fine * (source - source_crop_res)
