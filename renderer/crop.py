"""Face crops stabilised by the tracked pose: where to cut, how to cut, and how to paste back.

A crop is a square box ``(cx, cy, side)`` in full-frame pixels, resampled to ``size × size``. Boxes follow
the projected face-model vertices, smoothed over time (centre lightly, size strongly) so the crop neither
jitters nor lags the head. The camera of a crop is the frame's camera scaled and shifted, so the mesh can
be rasterized directly at crop resolution.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from kornia.filters import get_gaussian_kernel1d

from renderer.masks import box_blur, dilate, gaussian_blur
from renderer.warp import moved_detail, sample_pixels, smooth


@dataclass
class MovedDetail:
    """A source frame's fine detail moved onto a rendered surface, for :func:`paste_region`.

    Attributes:
        source: ``(C, H', W')`` the source frame (or the part of it the positions refer to).
        source_crop: ``(C, S, S)`` its crop at ``source_box`` (same value range).
        source_box: ``(3,)`` that crop's box in ``source``'s pixels.
        positions: ``(S, S, 2)`` the source pixel (x, y) showing the surface point seen at each crop pixel
            (:func:`renderer.warp.source_positions`; the pixel itself where the source is the painted frame
            and its own background is kept); read only where ``fine`` > 0.
        fine: ``(S, S)`` weight of the detail finer than the crop (1 where the source sees the point).
        band: ``(S, S)`` weight (at most ``fine``) of the band between the crop's resolution and ``sigma``
            crop pixels, which replaces the render's (where the surface also moved rigidly; 0 for none).
            ``fine`` counts inside ``paint`` only (outside it ``detail`` adds the footage's own).
        render_band: ``(C, S, S)`` the render's own band finer than ``sigma`` (see
            :func:`renderer.warp.smooth`), in the crop's value range.
        sigma: the band's scale in crop pixels.
        kept: ``(S, S)`` weight of the *painted frame's own* detail finer than ``sigma`` off the mesh, in
            place of the render's (the band around the surface the networks paint, where the footage's own
            pixels are right: :meth:`renderer.band.DetailBand._kept_background`) when the source is
            another frame; None for none (a source that is the painted frame itself holds that band in
            ``fine`` and ``band``). Needs :func:`paste_region`'s ``detail``.
    """

    source: torch.Tensor
    source_crop: torch.Tensor
    source_box: np.ndarray
    positions: torch.Tensor
    fine: torch.Tensor
    band: torch.Tensor
    render_band: torch.Tensor
    sigma: float
    kept: torch.Tensor | None = None


def _gaussian_smooth(x: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing along axis 0 with edge padding; ``sigma`` in samples (0 = unchanged)."""
    if sigma <= 0 or len(x) < 2:
        return x.copy()
    r = int(np.ceil(3 * sigma))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k /= k.sum()
    pad = np.concatenate([np.repeat(x[:1], r, 0), x, np.repeat(x[-1:], r, 0)])
    return np.stack([np.convolve(pad[:, j], k, mode="valid") for j in range(x.shape[1])], 1)


def crop_boxes(
    points: np.ndarray, scale: float = 1.6, center_sigma: float = 1.5, size_sigma: float = 8.0
) -> np.ndarray:
    """Square crop boxes ``(T, 3)`` = ``(cx, cy, side)`` in pixels around per-frame 2D points.

    Args:
        points: ``(T, V, 2)`` projected face vertices (pixels).
        scale: box side relative to the larger extent of the points (room for hair, chin and neck).
        center_sigma, size_sigma: temporal Gaussian smoothing (frames) of the centre and of the side.
    """
    lo, hi = points.min(1), points.max(1)
    center = (lo + hi) / 2
    side = (hi - lo).max(1, keepdims=True) * scale
    # the mesh stops at the hairline and chin: shift the box down a little to include the chin and jaw
    center = center + np.array([0.0, 0.05]) * side
    return np.concatenate([_gaussian_smooth(center, center_sigma), _gaussian_smooth(side, size_sigma)], 1)


def crop_camera(focal: float, center: np.ndarray, box: np.ndarray, size: int) -> tuple[float, np.ndarray]:
    """Focal length and principal point of the camera seeing the crop ``box`` at ``size × size``."""
    s = size / box[2]
    origin = box[:2] - box[2] / 2
    return float(focal * s), ((np.asarray(center) - origin) * s).astype(np.float32)


def _sample_grid(boxes: torch.Tensor, size: int, height: int, width: int) -> torch.Tensor:
    """``grid_sample`` grid ``(B, size, size, 2)`` reading each box from a ``height × width`` image."""
    t = (torch.arange(size, dtype=torch.float32, device=boxes.device) + 0.5) / size - 0.5  # -0.5 .. 0.5
    x = boxes[:, 0, None] + boxes[:, 2, None] * t[None]  # (B, S) pixel x of each crop column
    y = boxes[:, 1, None] + boxes[:, 2, None] * t[None]
    gx = (2 * x / width - 1)[:, None, :].expand(-1, size, -1)
    gy = (2 * y / height - 1)[:, :, None].expand(-1, -1, size)
    return torch.stack([gx, gy], -1)


CUT_SUPERSAMPLE = 4
"""At most this many bilinear reads per crop pixel and axis when :func:`cut` shrinks the footage."""


def cut(frames: torch.Tensor, boxes: torch.Tensor, size: int) -> torch.Tensor:
    """Crops ``(B, C, size, size)`` of ``frames`` ``(B, C, H, W)`` at ``boxes`` ``(B, 3)`` (the border is
    replicated where a box leaves the frame).

    Where a box is larger than the crop, each crop pixel is the mean of ``m × m`` bilinear reads spread over
    the footage pixels it covers (``m`` = the box's footage pixels per crop pixel, rounded up, at most
    :data:`CUT_SUPERSAMPLE`): one read per crop pixel would point-sample a face 2-6 times larger than the crop
    and alias its stubble and lip lines into noise that moves with every sub-pixel shift of the box."""
    m = min(max(int(np.ceil(float(boxes[:, 2].max()) / size - 1e-3)), 1), CUT_SUPERSAMPLE)
    grid = _sample_grid(boxes.float(), size * m, frames.shape[2], frames.shape[3])
    out = F.grid_sample(frames.float(), grid, mode="bilinear", padding_mode="border", align_corners=False)
    return F.avg_pool2d(out, m) if m > 1 else out


def box_slices(box: np.ndarray, height: int, width: int, grow: int = 0) -> tuple[slice, slice]:
    """Row and column slices of the pixels of a ``height × width`` frame inside crop ``box``; ``grow``: that
    many more pixels on every side (``grow=2`` holds every pixel a bilinear cut or paste of the box
    touches)."""
    cx, cy, side = (float(v) for v in box)
    half = side / 2
    return (
        slice(max(int(cy - half) - grow, 0), max(min(int(cy + half) + grow, height), 0)),
        slice(max(int(cx - half) - grow, 0), max(min(int(cx + half) + grow, width), 0)),
    )


def feather(size: int, border: float = 0.08, device: str | torch.device = "cpu") -> torch.Tensor:
    """``(1, 1, size, size)`` blend weights: 1 inside, falling smoothly to 0 over ``border`` of the side at
    the crop's edges, so a pasted crop has no visible seam."""
    t = (torch.arange(size, dtype=torch.float32, device=device) + 0.5) / size
    d = torch.minimum(t, 1 - t) / border
    w = torch.clamp(d, 0, 1)
    w = w * w * (3 - 2 * w)  # smoothstep
    return (w[:, None] * w[None, :])[None, None]


def colour_match(
    render: torch.Tensor,
    footage: torch.Tensor,
    where: torch.Tensor,
    free: tuple[float, float] = (0.1, 0.015),
    min_pixels: int = 192,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-channel ``gain`` and ``offset`` ``(C, 1, 1)`` that bring ``render`` ``(C, h, w)`` to
    ``footage`` ``(C, h, w)`` (values in [0, 1]) over the pixels ``where`` ``(h, w)`` is true; a gain of 1
    and an offset of 0 when fewer than ``min_pixels`` are given. A footage frame fading to white or black,
    or shot brighter or darker than the frames the renderer learned, shows the same face in other light:
    gain · render + offset puts the render into it.

    The least-squares gain's difference from 1 (kept within 0.2-5, refitted without the pixels it fits
    worst) and the difference of the means are left out up to ``free`` = (gain, mean), taken in full from
    twice that, smoothly in between: the networks' render is a little softer than the footage (held-out
    frames of a 60 px face: gain 1.04-1.08 to the upper face), which is no reason to change the painted
    part's contrast, and the means differ by a level or two."""
    c = render.shape[0]
    gain, offset = torch.ones(c, 1, 1), torch.zeros(c, 1, 1)
    if int(where.sum()) < min_pixels:
        return gain, offset
    x, y = render[:, where].double(), footage[:, where].double()

    def fit(use: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        n = use.sum(1).clamp_min(1)
        xm, ym = (x * use).sum(1) / n, (y * use).sum(1) / n
        # a gain of 1 weighs as much as a spread of two levels: a flat render's gain is 1, not undefined
        prior = n * (2 / 255) ** 2
        cov = ((x - xm[:, None]) * (y - ym[:, None]) * use).sum(1) + prior
        return (cov / ((((x - xm[:, None]) ** 2) * use).sum(1) + prior)).clamp(0.2, 5.0), xm, ym

    g, xm, ym = fit(torch.ones_like(x, dtype=torch.bool))
    # again without the pixels that fit worst (a hand or hair in front of the face, a blink)
    err = (g[:, None] * (x - xm[:, None]) + ym[:, None] - y).abs()
    g, xm, ym = fit(err <= 3 * err.median(1, keepdim=True).values + 1e-6)

    def beyond(x: torch.Tensor, limit: float) -> torch.Tensor:
        w = ((x.abs() - limit) / limit).clamp(0, 1)
        return x * w * w * (3 - 2 * w)

    gain = 1 + beyond(g - 1, free[0])
    offset = xm * (1 - gain) + beyond(ym - xm, free[1])  # the render's mean moved by the part beyond free
    return gain.float()[:, None, None], offset.float()[:, None, None]


def region_weight(region: torch.Tensor, grow: float = 0.03) -> torch.Tensor:
    """Paste weights ``(B, 1, S, S)`` for a crop whose rendered part is ``region`` ``(B, 1, S, S)``: 1 up
    to ``grow`` of the side around the region, falling to 0 at three times that. Pixels outside keep the
    footage at its full resolution instead of a resampled (softer) copy from the crop."""
    r = max(1, round(grow * region.shape[-1]))
    return box_blur(dilate(region, 2 * r), r)


def paste(
    frame: torch.Tensor,
    crop: torch.Tensor,
    box: np.ndarray,
    weight: torch.Tensor,
    detail: tuple[torch.Tensor, torch.Tensor] | None = None,
    moved: MovedDetail | None = None,
    paint: torch.Tensor | None = None,
    with_weight: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Blend ``crop`` ``(C, S, S)`` back into ``frame`` ``(C, H, W)`` (both float) at ``box``.

    Only the frame pixels under the box are resampled (from the crop, bilinear) and blended with
    ``weight`` ``(1, 1, S, S)``; returns a new frame.

    ``detail = (original, keep)``: ``original`` ``(C, S, S)`` is the crop that was cut from ``frame``
    and ``keep`` ``(1, 1, S, S)`` is 1 where the footage may show through (outside the replaced region).
    There the frame's own fine detail, which the crop lost by being resampled to ``S × S``, is added back
    (the frame minus its crop-resolution copy), so the footage around a rendered face stays as sharp as
    it was; where the crop equals ``original`` the frame comes back unchanged.

    ``moved`` (:class:`MovedDetail`) with ``paint`` ``(1, 1, S, S)`` (the painted lower face): the fine
    detail of a source frame is added at the surface positions, sampled from the source at full
    resolution (:func:`renderer.warp.moved_detail`): inside ``paint`` what the crop is too coarse to hold,
    and where ``moved.band`` the whole band finer than ``moved.sigma`` crop pixels in place of the
    render's, so the network's render keeps its colours and gains the footage's stubble, pores and lip
    texture moved with the new geometry.

    ``with_weight``: also return the ``(H, W)`` blend weight of the crop in the frame (0 = footage kept).
    """
    out = frame.clone()
    full_weight = torch.zeros(frame.shape[1:])
    pasted = paste_region(frame, crop, box, weight, detail, moved, paint)
    if pasted is not None:
        blended, a, (rows, cols) = pasted
        out[:, rows, cols] = blended
        full_weight[rows, cols] = a
    return (out, full_weight) if with_weight else out


def paste_region(
    frame: torch.Tensor,
    crop: torch.Tensor,
    box: np.ndarray,
    weight: torch.Tensor,
    detail: tuple[torch.Tensor, torch.Tensor] | None = None,
    moved: MovedDetail | None = None,
    paint: torch.Tensor | None = None,
    interior: tuple[torch.Tensor, torch.Tensor, torch.Tensor, tuple[int, int]] | None = None,
) -> tuple[torch.Tensor, torch.Tensor, tuple[slice, slice]] | None:
    """:func:`paste` for the frame pixels the weight reaches only (the rows and columns under the box where
    it is not 0; a lower face is a third of its box): the blended pixels ``(C, h, w)``, their blend weight
    ``(h, w)`` and the ``(rows, columns)`` slices of the frame they replace; None when the box lies outside
    the frame or the weight is 0. The rest of the frame is unchanged, so a caller holding the frame as uint8
    need not convert all of it.

    ``interior = (patch, positions, mask, (row, col))``: where ``mask`` ``(h', w')`` (the crop's mouth
    interior, a window of the crop from ``row``, ``col``) the crop is replaced by ``patch`` ``(C, P, P)``
    (another footage frame's mouth, :mod:`renderer.mouths`) sampled at full resolution at ``positions``
    ``(h', w', 2)`` (patch pixels)."""
    _, h, w = frame.shape
    s = crop.shape[-1]
    cx, cy, side = (float(v) for v in box)
    x0, x1 = max(int(np.floor(cx - side / 2)), 0), min(int(np.ceil(cx + side / 2)), w)
    y0, y1 = max(int(np.floor(cy - side / 2)), 0), min(int(np.ceil(cy + side / 2)), h)
    # only the frame pixels the weight reaches (where it is 0 the frame stays as it is): a frame pixel
    # centre x reads crop columns floor(u) and floor(u) + 1 at u = (x + 0.5 - left) / step - 0.5
    on = weight.expand(1, 1, s, s)[0, 0] > 0
    rows_on, cols_on = torch.nonzero(on.any(1))[:, 0], torch.nonzero(on.any(0))[:, 0]
    if len(rows_on) == 0:
        return None
    step, left, top = side / s, cx - side / 2, cy - side / 2
    x0 = max(x0, int(np.floor(left + (int(cols_on[0]) - 0.5) * step - 0.5)))
    x1 = min(x1, int(np.ceil(left + (int(cols_on[-1]) + 1.5) * step - 0.5)) + 1)
    y0 = max(y0, int(np.floor(top + (int(rows_on[0]) - 0.5) * step - 0.5)))
    y1 = min(y1, int(np.ceil(top + (int(rows_on[-1]) + 1.5) * step - 0.5)) + 1)
    if x1 <= x0 or y1 <= y0:
        return None
    # frame pixel centres of the region, in normalised crop coordinates
    xs = ((torch.arange(x0, x1, dtype=torch.float32) + 0.5 - cx) / side) * 2
    ys = ((torch.arange(y0, y1, dtype=torch.float32) + 0.5 - cy) / side) * 2
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1)[None].to(crop.device)
    maps = [crop[None].float(), weight.expand(1, 1, s, s)]
    if detail is not None:
        maps += [detail[0][None].float(), detail[1].expand(1, 1, s, s)]
    n_maps = sum(m.shape[1] for m in maps)
    has_kept = moved is not None and moved.kept is not None and detail is not None
    c = crop.shape[0]
    if moved is not None:
        valid = moved.fine[None, None].float()
        named = {  # the moved detail's maps, sampled with the crop's
            # the surface's source positions weighted by where they are valid (normalised below: a frame
            # pixel beside the silhouette reads the surface's positions, not those off it)
            "positions": moved.positions.permute(2, 0, 1)[None].float() * valid,
            "valid": valid,
            "fine": valid * paint,
            "band": moved.band[None, None].float(),
            "render_band": moved.render_band[None].float(),
        }
        if has_kept:
            # the frame's own band; inside the painted part its detail finer than the crop; its low-pass
            named |= {
                "kept": moved.kept[None, None].float(),
                "kept_fine": moved.kept[None, None].float() * paint,
                "own_low": smooth(detail[0][None].float(), moved.sigma),
            }
        maps += list(named.values())
    stacked = torch.cat(maps, 1)
    sampled = F.grid_sample(stacked, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    rgb, a = sampled[0, :c], sampled[0, c : c + 1]
    under = frame[:, y0:y1, x0:x1]
    blended = a * rgb + (1 - a) * under
    if detail is not None:
        low, keep = sampled[0, c + 1 : 2 * c + 1], sampled[0, 2 * c + 1 : 2 * c + 2]
        blended = blended + a * keep * (under - low)
    if moved is not None:
        got = dict(
            zip(named, torch.split(sampled[0, n_maps:], [m.shape[1] for m in named.values()]), strict=True)
        )
        # only over the rows and columns where any detail is added (the painted lower face, not the box)
        on = torch.cat([got[name] for name in ("fine", "band", "kept") if name in got]).amax(0) > 0
        rows, cols = torch.nonzero(on.any(1))[:, 0], torch.nonzero(on.any(0))[:, 0]
        if len(rows):
            r, k = slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1)
            part = {name: m[:, r, k] for name, m in got.items()}
            pos = (part["positions"] / part["valid"].clamp_min(1e-6)).permute(1, 2, 0)  # source-frame pixels
            sx, sy, sside = (float(v) for v in moved.source_box)
            crop_pos = (pos - torch.tensor([sx - sside / 2, sy - sside / 2])) * (s / sside)
            src_crop = moved.source_crop[None].float()
            low = sample_pixels(torch.cat([src_crop, smooth(src_crop, moved.sigma)], 1)[0], crop_pos)
            source = sample_pixels(moved.source, pos, "bicubic")
            render_band = part["render_band"]
            detail = moved_detail(source, low[:c], low[c:], render_band, part["fine"], part["band"])
            if has_kept:
                # the frame's own band (its crop minus that crop's low-pass) and its detail finer than
                # the crop inside the painted part (outside it ``detail`` adds that already)
                crop_res = sampled[0, c + 1 : 2 * c + 1, r, k]
                own = (
                    under[:, r, k],
                    crop_res,
                    part["own_low"],
                    render_band,
                    part["kept_fine"],
                    part["kept"],
                )
                detail = detail + moved_detail(*own)
            blended[:, r, k] += a[:, r, k] * detail
    if interior is not None:
        _paste_interior(blended, rgb, a, (y0, x0), box, s, interior)
    return blended, a[0], (slice(y0, y1), slice(x0, x1))


INTERIOR_EDGE_SIGMA = 0.5
"""Blur (crop pixels) of the crop's binary mouth-interior mask before it is enlarged to the footage's pixels
and cut there (:func:`sharp_edge`): enough to round the crop pixels' staircase into the inner lips' curve."""

INTERIOR_EDGE_SLOPE = float(get_gaussian_kernel1d(3, INTERIOR_EDGE_SIGMA)[0, 1])
"""Slope (per crop pixel) of the blurred mask across a straight edge of the binary one: the 3×3 Gaussian's
centre weight (0.79: a 0 | 1 step becomes 0.107 | 0.893)."""

INTERIOR_EDGE_LEVEL = 0.6
"""Level of the blurred mask where the bank's interior takes over (0.5: the binary mask's own edge; 0.6 lies
0.13 crop pixels inside it). Chosen on dfrf__cnn2, edtalk__pose_source2 and wav2lipgfpgan kim (mouth box of
the visual, audio-driven and dub re-creations, against the mask enlarged as it is): 0.5 / 0.6 / 0.7 → PSNR
−0.02 / +0.01 / +0.04 dB, high-frequency ratio +0.03 / +0.02 / +0.01 (means; kim's +0.06-0.09 / +0.04-0.07 /
0.00-0.09): the highest sharpness that loses no PSNR."""


def interior_edge_field(mask: torch.Tensor) -> torch.Tensor:
    """``(h, w)`` float: the crop's binary mouth-interior ``mask`` ``(h, w)`` blurred by
    :data:`INTERIOR_EDGE_SIGMA`, to be read at footage pixels by :func:`sharp_edge`."""
    return gaussian_blur(mask[None, None].float(), 3, INTERIOR_EDGE_SIGMA)[0, 0]


def sharp_edge(field: torch.Tensor, step: float) -> torch.Tensor:
    """:func:`interior_edge_field` read at footage pixels (bilinearly), ``step`` footage pixels per crop
    pixel, as the weight of the bank's interior: cut at :data:`INTERIOR_EDGE_LEVEL` over about one footage
    pixel. The mask enlarged as it is ramped over a crop pixel, so on a 1080p face the teeth met the lips
    over 3-4 pixels of the networks' soft render where the footage shows a sharp line; where the crop is as
    fine as the footage or finer (``step`` ≤ 1) the ramp stays a crop pixel wide."""
    gain = max(step, 1.0) / INTERIOR_EDGE_SLOPE
    return ((field - INTERIOR_EDGE_LEVEL) * gain + 0.5).clamp(0, 1)


def _paste_interior(
    blended: torch.Tensor,
    rgb: torch.Tensor,
    a: torch.Tensor,
    origin: tuple[int, int],
    box: np.ndarray,
    size: int,
    interior: tuple[torch.Tensor, torch.Tensor, torch.Tensor, tuple[int, int]],
) -> None:
    """:func:`paste_region`'s mouth interior, in place on ``blended`` ``(C, h, w)`` (frame pixels from
    ``origin``; ``rgb`` and ``a`` the sampled crop and its weight there), over the frame pixels under the
    interior's crop window only."""
    patch, positions, mask, (row, col) = interior
    cx, cy, side = (float(v) for v in box)
    hw, ww = mask.shape
    left, top = cx - side / 2, cy - side / 2
    step = side / size  # frame pixels per crop pixel
    _, h, w = blended.shape
    fx0 = max(int(np.floor(left + col * step)) - origin[1], 0)
    fx1 = min(int(np.ceil(left + (col + ww) * step)) - origin[1], w)
    fy0 = max(int(np.floor(top + row * step)) - origin[0], 0)
    fy1 = min(int(np.ceil(top + (row + hw) * step)) - origin[0], h)
    if fx1 <= fx0 or fy1 <= fy0:
        return
    # those frame pixels' centres in the window's normalised coordinates (align_corners=False)
    xs = ((torch.arange(fx0, fx1) + origin[1] + 0.5 - left) / step - col) / ww * 2 - 1
    ys = ((torch.arange(fy0, fy1) + origin[0] + 0.5 - top) / step - row) / hw * 2 - 1
    grid = torch.stack(torch.meshgrid(xs.float(), ys.float(), indexing="xy"), -1)[None]
    maps = torch.cat([positions.permute(2, 0, 1), interior_edge_field(mask)[None]])[None].float()
    sampled = F.grid_sample(maps, grid, mode="bilinear", padding_mode="zeros", align_corners=False)[0]
    inside = sharp_edge(sampled[2:], step) * a[:, fy0:fy1, fx0:fx1]
    colour = sample_pixels(patch, sampled[:2].permute(1, 2, 0), "bicubic")
    blended[:, fy0:fy1, fx0:fx1] += inside * (colour - rgb[:, fy0:fy1, fx0:fx1])
