"""Pure metric functions on landmark tracks (pixels) and images — shared by evaluations and benchmarks."""

from __future__ import annotations

import numpy as np


def interocular_distance(landmarks: np.ndarray, left_eye: np.ndarray, right_eye: np.ndarray) -> np.ndarray:
    """``(...)`` distance between the centres of the two eye contours of landmarks ``(..., L, 2)``, px."""
    return np.linalg.norm(
        landmarks[..., left_eye, :].mean(-2) - landmarks[..., right_eye, :].mean(-2), axis=-1
    )


def landmark_error(pred: np.ndarray, target: np.ndarray, idx: np.ndarray | None = None) -> np.ndarray:
    """Per-frame mean distance ``(T,)`` between landmarks ``pred``, ``target`` ``(T, L, 2)``; NaN-aware."""
    if idx is not None:
        pred, target = pred[:, idx], target[:, idx]
    return np.nanmean(np.linalg.norm(pred - target, axis=-1), axis=-1)


def jitter(track: np.ndarray, idx: np.ndarray | None = None) -> np.ndarray:
    """Per-frame jitter ``(T-2,)``: mean norm of the second temporal difference of landmarks ``(T, L, 2)``.

    A still point scores 0; constant-velocity motion scores 0; noise of standard deviation ``s`` per axis
    scores about ``sqrt(6 * 2) * s * sqrt(pi) / 2`` (mean of a Rayleigh of scale ``sqrt(6) s``).
    """
    if idx is not None:
        track = track[:, idx]
    d2 = track[2:] - 2 * track[1:-1] + track[:-2]
    return np.nanmean(np.linalg.norm(d2, axis=-1), axis=-1)


def inner_lip_gap(landmarks: np.ndarray, upper: int = 13, lower: int = 14) -> np.ndarray:
    """``(T,)`` distance between the inner-lip midpoints (mediapipe landmarks 13 and 14), px."""
    return np.linalg.norm(landmarks[:, upper] - landmarks[:, lower], axis=-1)


def closure_f1(pred_gap: np.ndarray, true_gap: np.ndarray, threshold: float) -> dict[str, float]:
    """Lip-closure precision, recall and F1: a frame is closed when its inner-lip gap is below ``threshold``.

    Args:
        pred_gap, true_gap: ``(T,)`` inner-lip gaps (any unit, the same for both and the threshold).
    """
    p, t = pred_gap < threshold, true_gap < threshold
    tp = float((p & t).sum())
    precision = tp / p.sum() if p.sum() else 0.0
    recall = tp / t.sum() if t.sum() else 0.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    return {"closure_precision": precision, "closure_recall": recall, "closure_f1": f1}


def psnr(a: np.ndarray, b: np.ndarray, peak: float = 255.0) -> float:
    """Peak signal-to-noise ratio in dB of two images of the same shape (``inf`` when identical)."""
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(peak**2 / mse)


def ssim(a: np.ndarray, b: np.ndarray, window: int = 11) -> float:
    """Mean structural similarity of two ``(H, W, 3)`` uint8 images (kornia, Gaussian window)."""
    import torch
    from kornia.metrics import ssim as kssim

    ta = torch.from_numpy(np.ascontiguousarray(a)).permute(2, 0, 1)[None].float() / 255
    tb = torch.from_numpy(np.ascontiguousarray(b)).permute(2, 0, 1)[None].float() / 255
    return float(kssim(ta, tb, window).mean())


def av_offset(generated: np.ndarray, real: np.ndarray, max_lag: int = 10) -> tuple[int, float]:
    """Offset in frames between two mouth-opening signals ``(T,)`` by normalised cross-correlation.

    Returns ``(lag, correlation)``: a positive lag means the generated mouth moves ``lag`` frames *after*
    the real one (``generated[t + lag] ~ real[t]``); 0 is perfect sync. NaN frames are ignored.
    """
    g = (generated - np.nanmean(generated)) / (np.nanstd(generated) + 1e-12)
    r = (real - np.nanmean(real)) / (np.nanstd(real) + 1e-12)
    best, best_c = 0, -np.inf
    for lag in range(-max_lag, max_lag + 1):
        x, y = (g[lag:], r[: len(r) - lag]) if lag >= 0 else (g[:lag], r[-lag:])
        n = min(len(x), len(y))
        c = np.nanmean(x[:n] * y[:n]) if n > 2 else -np.inf
        if c > best_c:
            best, best_c = lag, c
    return best, float(best_c)
