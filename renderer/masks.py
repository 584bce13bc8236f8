"""Soft-mask morphology on ``(B, 1, H, W)`` tensors: square dilation, erosion and box blur; and a Gaussian
blur of ``(B, C, H, W)`` images with kernels made once.

Square windows are separable, so each operation is two 1-D passes (rows, then columns). A 1-D running
maximum over ``n`` taps is taken by doubling (the maximum of two shifted copies covers twice the taps, so
``log2 n + 1`` elementwise maxima), a 1-D mean by differences of a cumulative sum; both give exactly what
``max_pool2d`` / ``avg_pool2d`` with a ``(2r + 1)²`` window give, at a fraction of the cost (on a 192² crop
with two threads a radius-6 dilation took 1.1 ms with max pooling, 0.07 ms this way — it runs five times
per rendered frame).
"""

from __future__ import annotations

from functools import cache

import torch
import torch.nn.functional as F


def _running_max(x: torch.Tensor, dim: int, r: int) -> torch.Tensor:
    """Maximum over ``2r + 1`` taps centred on each element along ``dim`` (outside counts as nothing)."""
    pad = (r, r, 0, 0) if dim == 3 else (0, 0, r, r)
    cur, taps, need = F.pad(x, pad, value=float("-inf")), 1, 2 * r + 1
    while taps < need:
        step = min(taps, need - taps)
        n = cur.shape[dim] - step
        cur = torch.maximum(cur.narrow(dim, 0, n), cur.narrow(dim, step, n))
        taps += step
    return cur


def _running_mean(x: torch.Tensor, dim: int, r: int) -> torch.Tensor:
    """Mean over the ``2r + 1`` taps centred on each element along ``dim`` that lie inside the image."""
    n = x.shape[dim]
    zero = torch.zeros_like(x.narrow(dim, 0, 1))
    csum = torch.cat([zero, x.cumsum(dim)], dim)  # csum[i] = sum of x[:i]
    idx = torch.arange(n, device=x.device)
    hi, lo = (idx + r + 1).clamp(max=n), (idx - r).clamp(min=0)
    shape = [1] * x.ndim
    shape[dim] = n
    total = csum.index_select(dim, hi) - csum.index_select(dim, lo)
    return total / (hi - lo).to(x.dtype).view(shape)


def dilate(mask: torch.Tensor, r: int) -> torch.Tensor:
    """Maximum over the ``(2r + 1)²`` window around each pixel (outside the image counts as nothing)."""
    if r <= 0:
        return mask
    return _running_max(_running_max(mask, 2, r), 3, r)


def erode(mask: torch.Tensor, r: int) -> torch.Tensor:
    """Minimum over the ``(2r + 1)²`` window around each pixel (the image border does not erode)."""
    return -dilate(-mask, r)


def box_blur(mask: torch.Tensor, r: int) -> torch.Tensor:
    """Mean over the ``(2r + 1)²`` window around each pixel, clipped to the image."""
    if r <= 0:
        return mask
    return _running_mean(_running_mean(mask, 2, r), 3, r)


@cache
def _gaussian_taps(size: int, sigma: float) -> torch.Tensor:
    from kornia.filters import get_gaussian_kernel1d

    return get_gaussian_kernel1d(size, sigma)[0]


def gaussian_blur(x: torch.Tensor, size: int, sigma: float) -> torch.Tensor:
    """``x`` ``(B, C, H, W)`` blurred by a ``size × size`` Gaussian of ``sigma`` pixels, the border
    replicated: kornia's ``gaussian_blur2d(x, (size, size), (sigma, sigma), "replicate")`` bit for bit (the
    same taps, the same two passes), without making the kernels and checking the input on every call, which
    took most of its time on the renderer's small images (one thread: 0.31 → 0.13 ms for a 72 × 80 mask,
    0.64 → 0.42 ms for a 96² colour image; several run for every rendered frame)."""
    taps, c, r = _gaussian_taps(size, float(sigma)).to(x), x.shape[1], size // 2
    x = F.pad(x, (r, r, r, r), mode="replicate")
    x = F.conv2d(x, taps.view(1, 1, 1, size).expand(c, 1, 1, size), groups=c)
    return F.conv2d(x, taps.view(1, 1, size, 1).expand(c, 1, size, 1), groups=c)
