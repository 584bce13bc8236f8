"""Pure geometry functions (numpy for batch statistics, torch for differentiable fitting).

Camera convention everywhere outside the GL module: OpenCV (x right, y down, z forward), pixels with
row 0 at the top; a pinhole camera ``u = fx * X / Z + cx``, ``v = fy * Y / Z + cy``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import torch


def similarity_procrustes(
    src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted similarity transform minimising ``sum w_i |s R src_i + t - dst_i|^2`` (Umeyama).

    Args:
        src, dst: ``(..., N, 3)`` corresponding points (batched over leading dims).
        weights: ``(N,)`` non-negative weights; uniform if None.

    Returns:
        scale ``(...)``, rotation ``(..., 3, 3)`` (det +1), translation ``(..., 3)``.
    """
    n = src.shape[-2]
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    mu_s = np.einsum("n,...nc->...c", w, src)
    mu_d = np.einsum("n,...nc->...c", w, dst)
    s0 = src - mu_s[..., None, :]
    d0 = dst - mu_d[..., None, :]
    cov = np.einsum("n,...ni,...nj->...ij", w, d0, s0)
    u, sig, vt = np.linalg.svd(cov)
    det = np.linalg.det(u @ vt)
    fix = np.ones(sig.shape)
    fix[..., -1] = np.sign(det)
    rot = u @ (fix[..., :, None] * vt)
    var_s = np.einsum("n,...nc->...", w, s0**2)
    scale = (sig * fix).sum(-1) / var_s
    trans = mu_d - scale[..., None] * np.einsum("...ij,...j->...i", rot, mu_s)
    return scale, rot, trans


def project(points: torch.Tensor, focal: torch.Tensor, center: torch.Tensor) -> torch.Tensor:
    """Pinhole projection of camera-space points.

    Args:
        points: ``(..., N, 3)`` camera-space points (z > 0 in front of the camera).
        focal: scalar or ``(...,)`` focal length in pixels (square pixels).
        center: ``(2,)`` principal point in pixels.

    Returns:
        ``(..., N, 2)`` pixel coordinates.
    """
    z = points[..., 2:3].clamp_min(1e-6)
    f = focal if focal.ndim == 0 else focal[..., None, None]
    return points[..., :2] / z * f + center


def posed(vertices: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Camera-frame points ``(..., V, 3)`` of object-frame ``vertices`` ``(..., V, 3)`` under rotations
    ``(..., 3, 3)`` and translations ``(..., 3)`` (``R X + t``; leading dimensions broadcast)."""
    if rotation.ndim == 2:  # one pose: a single matrix product
        return vertices @ rotation.T + translation
    return np.einsum("...ij,...vj->...vi", rotation, vertices) + translation[..., None, :]


def unposed(points: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Object-frame points of camera-frame ``points`` ``(..., V, 3)`` posed by one ``rotation`` ``(3, 3)``
    and ``translation`` ``(3,)``: the inverse of :func:`posed`."""
    return (points - translation) @ rotation


def pinhole(points: np.ndarray, focal: float, center: np.ndarray) -> np.ndarray:
    """Pixels ``(..., V, 2)`` of camera-frame ``points`` ``(..., V, 3)`` (numpy twin of :func:`project`)."""
    return focal * points[..., :2] / np.maximum(points[..., 2:3], 1e-6) + center


def skew(v: torch.Tensor) -> torch.Tensor:
    """Cross-product matrices ``(..., 3, 3)`` of vectors ``(..., 3)``: ``skew(a) @ b == cross(a, b)``."""
    x, y, z = v.unbind(-1)
    import torch

    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).reshape(*v.shape[:-1], 3, 3)
