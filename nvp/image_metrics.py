"""Image quality where nvp paints: region PSNR / SSIM, sharpness and seams, next to the real footage.

Full-frame PSNR is dominated by pixels copied from the footage; these pure functions measure only the
painted region (a weight map ``(H, W)`` in [0, 1], 1 where the render replaced the footage) or a box around
the mouth, and compare the fine detail of a generated image with the real one (ratio 1.0 = as detailed as
the footage). Images are ``(H, W, 3)`` uint8 (RGB), boxes ``(y0, y1, x0, x1)`` pixel bounds.
"""

from __future__ import annotations

import numpy as np

Box = tuple[int, int, int, int]


def masked_psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray, peak: float = 255.0) -> float:
    """PSNR in dB of ``a`` vs ``b`` over the pixels where ``mask`` ``(H, W)`` is true (``inf`` if equal
    there, NaN when the mask is empty)."""
    m = np.asarray(mask, bool)
    if not m.any():
        return float("nan")
    d = a[m].astype(np.float64) - b[m].astype(np.float64)
    mse = float(np.mean(d**2))
    return float("inf") if mse == 0 else 10.0 * np.log10(peak**2 / mse)


def masked_ssim(a: np.ndarray, b: np.ndarray, mask: np.ndarray, window: int = 7) -> float:
    """Mean SSIM (kornia, Gaussian ``window``) of ``a`` vs ``b`` over the pixels where ``mask`` is true."""
    import torch
    from kornia.metrics import ssim

    m = np.asarray(mask, bool)
    if not m.any():
        return float("nan")
    ta = torch.from_numpy(np.ascontiguousarray(a)).permute(2, 0, 1)[None].float() / 255
    tb = torch.from_numpy(np.ascontiguousarray(b)).permute(2, 0, 1)[None].float() / 255
    smap = ssim(ta, tb, window).mean(1)[0].numpy()
    return float(smap[m].mean())


def mouth_box(lips: np.ndarray, shape: tuple[int, int], grow: float = 0.6) -> Box:
    """Box around lip landmarks ``(L, 2)`` (x, y pixels) grown on every side by ``grow`` × the mouth width,
    clipped to an image of ``shape`` ``(H, W)``."""
    lo, hi = np.nanmin(lips, 0), np.nanmax(lips, 0)
    pad = grow * (hi[0] - lo[0])
    h, w = shape
    x0, y0 = int(max(np.floor(lo[0] - pad), 0)), int(max(np.floor(lo[1] - pad), 0))
    x1, y1 = int(min(np.ceil(hi[0] + pad), w)), int(min(np.ceil(hi[1] + pad), h))
    return y0, y1, x0, x1


def _gray(img: np.ndarray) -> np.ndarray:
    return img.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)


def _gray_around(img: np.ndarray, box: Box, margin: int) -> tuple[np.ndarray, tuple[slice, slice]]:
    """Grey levels of ``box`` grown by ``margin`` pixels (within the image) and the slices of ``box`` in
    them: a filter of that reach sees there what it sees over the whole image (at the image's own edge
    the crop's edge is the image's), without converting and filtering the whole frame."""
    y0, y1, x0, x1 = box
    h, w = img.shape[:2]
    gy0, gx0 = max(y0 - margin, 0), max(x0 - margin, 0)
    grey = _gray(img[gy0 : min(y1 + margin, h), gx0 : min(x1 + margin, w)])
    return grey, (slice(y0 - gy0, y1 - gy0), slice(x0 - gx0, x1 - gx0))


def high_frequency(img: np.ndarray, box: Box) -> np.ndarray:
    """``(h, w)`` float32: the image minus its 5×5 Gaussian blur (grey levels) inside ``box``, the finest
    detail (stubble, pores, teeth edges); blurred as over the whole image, so the box's edge is not one."""
    import cv2

    g, inner = _gray_around(img, box, 2)
    return (g - cv2.GaussianBlur(g, (5, 5), 0))[inner]


def high_frequency_energy(img: np.ndarray, box: Box) -> float:
    """Mean square of :func:`high_frequency` inside ``box``: how much fine detail there is."""
    return float(np.mean(high_frequency(img, box) ** 2))


def high_frequency_agreement(fake: np.ndarray, real: np.ndarray, box: Box) -> float:
    """Mean product of the two images' :func:`high_frequency` inside ``box``. Over
    ``sqrt(energy(fake) * energy(real))`` it is the correlation of their fine detail: 1 when the fake's detail
    is the real one's, 0 for detail unrelated to it (grain, specks, another frame's stubble a few pixels
    off) — which the energy ratio counts as sharpness. Pooled over frames by :func:`detail_in_place`."""
    return float(np.mean(high_frequency(fake, box) * high_frequency(real, box)))


def detail_in_place(agreement: np.ndarray, energy: np.ndarray, real_energy: np.ndarray) -> float:
    """Correlation of a re-creation's fine detail with the footage's, pooled over frames: the sums of
    per-frame :func:`high_frequency_agreement` over the root of the product of the summed
    :func:`high_frequency_energy` of the two (1.0 = the footage's detail, in place; NaN without any)."""
    norm = float(np.sqrt(np.sum(energy) * np.sum(real_energy)))
    return float(np.sum(agreement) / norm) if norm > 0 else float("nan")


MOUTH_REGIONS = ("interior", "lips", "skin")
"""The parts of a mouth box :func:`mouth_regions` returns, in the order reports list them."""


def mouth_regions(outer: np.ndarray, inner: np.ndarray, box: Box) -> dict[str, np.ndarray]:
    """``box`` ``(h, w)`` split by lip landmarks (``(L, 2)`` x, y pixels; ordered loops): ``interior``
    inside the inner contour (teeth, tongue), ``lips`` between the two contours, ``skin`` the rest — where
    fine detail is lost differs (the lips change shape with every word, the skin around them mostly moves)."""
    import cv2

    y0, y1, x0, x1 = box

    def inside(loop: np.ndarray) -> np.ndarray:
        out = np.zeros((y1 - y0, x1 - x0), np.uint8)
        cv2.fillPoly(out, [np.round(loop[:, :2] - [x0, y0]).astype(np.int32)], 1)
        return out.astype(bool)

    interior, mouth = inside(inner), inside(outer)
    return {"interior": interior, "lips": mouth & ~interior, "skin": ~mouth}


def high_frequency_sums(img: np.ndarray, box: Box, regions: dict[str, np.ndarray]) -> dict[str, float]:
    """Sum of squared :func:`high_frequency` over each of ``regions`` (``(h, w)`` bool over ``box``, as
    :func:`mouth_regions`): pooled over frames, a fake's sums over the real frames' are its fine detail kept
    per region."""
    hf = high_frequency(img, box) ** 2
    return {name: float(hf[mask].sum()) for name, mask in regions.items()}


def laplacian_energy(img: np.ndarray, box: Box) -> float:
    """Mean absolute Laplacian (3×3, grey levels) inside ``box``."""
    import cv2

    g, inner = _gray_around(img, box, 1)
    return float(np.mean(np.abs(cv2.Laplacian(g, cv2.CV_32F, ksize=1)[inner])))


def border_band(weight: np.ndarray, width: int = 3) -> np.ndarray:
    """``(H, W)`` bool band of ``width`` pixels on each side of the painted region's border (weight 0.5)."""
    import cv2

    inside = (np.asarray(weight) >= 0.5).astype(np.uint8)
    k = np.ones((2 * width + 1, 2 * width + 1), np.uint8)
    return (cv2.dilate(inside, k) - cv2.erode(inside, k)).astype(bool)


def seam_gradient_ratio(fake: np.ndarray, real: np.ndarray, weight: np.ndarray, width: int = 3) -> float:
    """Mean gradient magnitude of ``fake`` over that of ``real`` in the band around the painted region's
    border (1.0 = no seam; a visible edge or a blurred ring moves it away from 1). NaN without a border."""
    import cv2

    band = border_band(weight, width)
    if not band.any():
        return float("nan")

    def grad(img: np.ndarray) -> np.ndarray:
        g = _gray(img)
        return np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))[band]

    r = grad(real).mean()
    return float(grad(fake).mean() / r) if r > 0 else float("nan")
