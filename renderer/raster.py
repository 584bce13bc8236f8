"""Rasterizer interface: ``RasterOutput`` (per-pixel fragments) and the camera → clip-space helper.

Two backends produce a ``RasterOutput`` from a mesh in camera coordinates:

- ``renderer.gl.GLRasterizer``: OpenGL through moderngl on a headless EGL context (fast; the default).
- ``renderer.raster_ref.TorchRasterizer``: a slow pure-torch reference used by the tests.

Both take the same arguments::

    rasterize(vertices_cam (V,3), triangles (F,3), uvs (V,2), focal, center (2,)) -> RasterOutput

Conventions (shared by both backends):

- Camera: OpenCV pinhole, x right, y down, z forward; a camera point ``(x, y, z)`` lands at the continuous
  image position ``focal * (x, y) / z + center`` (column, row). Pixel ``(row r, col c)`` covers
  ``[c, c+1) x [r, r+1)`` and is sampled at its centre ``(c + 0.5, r + 0.5)``. Row 0 is the top of the
  image; nothing outside the moderngl module knows that OpenGL counts rows from the bottom.
- Backface culling is off (the mouth-interior triangles must show whichever way they face); the nearest
  surface along the pixel ray wins (z-buffer on camera depth).
- Barycentrics, UVs and depth are perspective-correct: ``sum_i barycentric[..., i] * X_i`` is the 3D point
  on the triangle seen through the pixel centre, and ``depth`` is its camera z.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

#: Default ratio between the automatic near plane and the nearest vertex (see :func:`depth_range`).
AUTO_NEAR_FACTOR = 0.5
#: Default ratio between the automatic far plane and the farthest vertex.
AUTO_FAR_FACTOR = 2.0


@dataclass(frozen=True)
class RasterOutput:
    """Per-pixel rasterization result for one image of size ``H x W`` (row 0 = top of the image).

    All fields are contiguous CPU torch tensors: new ones on every call, unless the caller passes a previous
    ``RasterOutput`` as ``out=`` to be overwritten in place (never a view of a backend's internal buffer).

    Attributes:
        triangle_id: ``(H, W)`` int64 index into ``triangles`` of the visible triangle; ``-1`` = background.
        barycentric: ``(H, W, 3)`` float32 perspective-correct barycentric coordinates of the pixel centre
            w.r.t. the visible triangle's vertices ``triangles[id, 0..2]`` (non-negative up to rounding,
            summing to 1); ``0`` in the background.
        uv: ``(H, W, 2)`` float32 texture coordinates interpolated from the per-vertex ``uvs`` (same
            convention as the face model: v = 0 at the top of the texture); ``0`` in the background.
        depth: ``(H, W)`` float32 camera z of the visible surface point, in the units of the vertices
            (cm for the face model); ``0`` in the background (never ``inf``: safe to multiply by the mask).
        mask: ``(H, W)`` bool, True where a triangle covers the pixel centre (``triangle_id >= 0``).
    """

    triangle_id: torch.Tensor
    barycentric: torch.Tensor
    uv: torch.Tensor
    depth: torch.Tensor
    mask: torch.Tensor

    @property
    def height(self) -> int:
        return int(self.triangle_id.shape[0])

    @property
    def width(self) -> int:
        return int(self.triangle_id.shape[1])

    def to(self, device: torch.device | str) -> RasterOutput:
        """The same fragments on another device."""
        return RasterOutput(
            *(t.to(device) for t in (self.triangle_id, self.barycentric, self.uv, self.depth, self.mask))
        )


def empty_output(height: int, width: int) -> RasterOutput:
    """An uninitialised ``RasterOutput`` of size ``height x width``, for the backends' ``out=`` argument."""
    return RasterOutput(
        triangle_id=torch.empty((height, width), dtype=torch.int64),
        barycentric=torch.empty((height, width, 3), dtype=torch.float32),
        uv=torch.empty((height, width, 2), dtype=torch.float32),
        depth=torch.empty((height, width), dtype=torch.float32),
        mask=torch.empty((height, width), dtype=torch.bool),
    )


def check_output(out: RasterOutput, height: int, width: int) -> None:
    """Raise ``ValueError`` unless ``out`` can be filled in place for a ``height x width`` image."""
    ref = empty_output(0, 0)
    for name in ("triangle_id", "barycentric", "uv", "depth", "mask"):
        t, r = getattr(out, name), getattr(ref, name)
        shape = (height, width) + tuple(r.shape[2:])
        if tuple(t.shape) != shape or t.dtype != r.dtype or t.device.type != "cpu" or not t.is_contiguous():
            raise ValueError(
                f"out.{name} must be a contiguous CPU {r.dtype} tensor of shape {shape}, "
                f"got {t.dtype} {tuple(t.shape)} on {t.device} (contiguous={t.is_contiguous()})"
            )


def as_numpy(x: np.ndarray | torch.Tensor, dtype: type) -> np.ndarray:
    """A C-contiguous numpy array of ``dtype`` from a numpy array or (any-device) torch tensor."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.ascontiguousarray(np.asarray(x), dtype=dtype)


def check_mesh(vertices_cam: np.ndarray, triangles: np.ndarray, uvs: np.ndarray, center: np.ndarray) -> None:
    """Raise ``ValueError`` unless the arrays have the shapes ``rasterize`` expects."""
    if vertices_cam.ndim != 2 or vertices_cam.shape[1] != 3:
        raise ValueError(f"vertices_cam must be (V,3), got {vertices_cam.shape}")
    v = vertices_cam.shape[0]
    if triangles.ndim != 2 or triangles.shape[1] != 3:
        raise ValueError(f"triangles must be (F,3), got {triangles.shape}")
    if triangles.size and (triangles.min() < 0 or triangles.max() >= v):
        raise ValueError(
            f"triangles must index vertices in [0, {v}), found [{triangles.min()}, {triangles.max()}]"
        )
    if triangles.shape[0] >= 2**24:
        raise ValueError(f"at most 2^24 - 1 triangles are supported, got {triangles.shape[0]}")
    if uvs.shape != (v, 2):
        raise ValueError(f"uvs must be ({v},2) like the vertices, got {uvs.shape}")
    if center.shape != (2,):
        raise ValueError(f"center must be (2,), got {center.shape}")


def depth_range(z: np.ndarray, near: float | None, far: float | None) -> tuple[float, float]:
    """The clipping planes used for one call: explicit values, or automatic ones from the vertex depths.

    ``None`` picks ``near = AUTO_NEAR_FACTOR * min(z)`` and ``far = AUTO_FAR_FACTOR * max(z)`` (over the
    vertices in front of the camera), which keeps every vertex inside the frustum and spends the depth
    buffer's precision on the mesh. Only the z-buffer uses these planes; ``RasterOutput.depth`` is the
    interpolated camera z and does not depend on them.

    Args:
        z: ``(V,)`` camera depths of the vertices.
        near, far: explicit planes (units of ``z``), or None for automatic.

    Returns:
        ``(near, far)`` with ``0 < near < far``.
    """
    front = z[z > 0]
    zmax = float(front.max()) if front.size else 1.0
    zmin = float(front.min()) if front.size else 1.0
    n = AUTO_NEAR_FACTOR * zmin if near is None else float(near)
    f = AUTO_FAR_FACTOR * zmax if far is None else float(far)
    if not 0 < n < f:
        raise ValueError(f"need 0 < near < far, got near={n}, far={f}")
    return n, f


def to_clip(
    vertices_cam: np.ndarray,
    focal: float,
    center: np.ndarray,
    width: int,
    height: int,
    near: float,
    far: float,
) -> np.ndarray:
    """OpenGL clip coordinates ``(V, 4)`` float32 of OpenCV camera points ``(V, 3)``.

    The result follows OpenGL's own convention: after the perspective divide, ``x_ndc = -1 .. 1`` spans
    the image from its left to its right edge, ``y_ndc = -1 .. 1`` from its **bottom** to its **top**
    edge (y up, as GL expects), and ``z_ndc = -1 .. 1`` from ``near`` to ``far``; ``w`` is the camera z.
    So with ``(u, v) = focal * (x, y) / z + center`` (v = image row, down)::

        x_ndc = 2 u / width - 1,   y_ndc = 1 - 2 v / height,
        z_ndc = (far + near) / (far - near) - 2 far near / ((far - near) z).

    Args:
        vertices_cam: ``(V, 3)`` points in the camera frame (x right, y down, z forward).
        focal: focal length in pixels.
        center: ``(2,)`` principal point ``(cx, cy)`` in pixels.
        width, height: image size in pixels.
        near, far: clipping planes, units of ``vertices_cam`` (``0 < near < far``).

    Returns:
        ``(V, 4)`` float32 clip coordinates ``(x_c, y_c, z_c, w_c)`` with ``w_c = z``.
    """
    v = np.asarray(vertices_cam, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices_cam must be (V,3), got {v.shape}")
    if not 0 < near < far:
        raise ValueError(f"need 0 < near < far, got near={near}, far={far}")
    cx, cy = (float(c) for c in np.asarray(center, dtype=np.float64).reshape(2))
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    out = np.empty((v.shape[0], 4), dtype=np.float64)
    out[:, 0] = (2.0 * focal / width) * x + (2.0 * cx / width - 1.0) * z
    out[:, 1] = -(2.0 * focal / height) * y - (2.0 * cy / height - 1.0) * z
    out[:, 2] = (far + near) / (far - near) * z - 2.0 * far * near / (far - near)
    out[:, 3] = z
    return out.astype(np.float32)


def project_pixels(vertices_cam: np.ndarray | torch.Tensor, focal: float, center) -> np.ndarray:
    """Continuous image positions ``(V, 2)`` (column, row) of camera points ``(V, 3)``.

    ``focal * (x, y) / z + center``; the centre of pixel ``(row r, col c)`` is at ``(c + 0.5, r + 0.5)``.
    """
    v = as_numpy(vertices_cam, np.float64)
    return focal * v[:, :2] / v[:, 2:3] + np.asarray(center, dtype=np.float64).reshape(1, 2)
