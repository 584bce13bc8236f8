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


# ------------------------------------------------------------------------------- lip-sync behaviour

BILABIAL_PHONES = ("p", "pʰ", "p͈", "b", "ɓ", "m")
"""Phones made with both lips closed, in the phoneme recogniser's IPA set (``phoneme_labels()``): p, its
aspirated and tense forms, b, the implosive ɓ, m. Bilabial fricatives (ɸ, β) and the trill ʙ do not close
the lips and are left out."""


def bilabial_classes(labels: tuple[str, ...] | list[str]) -> np.ndarray:
    """``(K,)`` indices of :data:`BILABIAL_PHONES` in a phoneme recogniser's class labels."""
    idx = np.array([i for i, name in enumerate(labels) if name in BILABIAL_PHONES], dtype=int)
    if len(idx) == 0:
        raise ValueError("expected the phone labels to contain p, b or m, found none")
    return idx


def bilabial_frames(
    log_posteriors: np.ndarray,
    classes: np.ndarray,
    rate: float,
    fps: float,
    num_frames: int,
    threshold: float = 0.5,
) -> np.ndarray:
    """``(T,)`` bool: video frames during which the audio says p, b or m.

    Args:
        log_posteriors: ``(N, D)`` phone log-probabilities at ``rate`` Hz (row ``n`` covers
            ``[n, n + 1) / rate`` s).
        classes: indices of the bilabial phones (:func:`bilabial_classes`).
        rate, fps: rates of the posteriors and of the video frames (frame ``i`` covers ``[i, i + 1) / fps``).
        threshold: a posterior row is bilabial when the summed probability of ``classes`` reaches this.
    Returns:
        a frame is bilabial when any posterior row overlapping it is.
    """
    prob = np.exp(np.asarray(log_posteriors, np.float64)[:, classes]).sum(1)
    row = prob >= threshold
    i = np.arange(num_frames)
    first = np.floor(i / fps * rate + 1e-9).astype(int)
    last = np.maximum(first, np.ceil((i + 1) / fps * rate - 1e-9).astype(int) - 1)
    cum = np.concatenate([[0], np.cumsum(row)])
    lo, hi = np.clip(first, 0, len(row)), np.clip(last + 1, 0, len(row))
    return (cum[hi] - cum[lo]) > 0


def closed_level(real_gap: np.ndarray, fraction: float = 0.15) -> float:
    """Inner-lip gap at or below which a mouth counts as closed: ``min + fraction * (p95 - min)`` of the real
    video's gaps ``(T,)`` (NaN ignored). ``fraction=0.15`` is nvp's closed level; 0.3 its resting level."""
    g = np.asarray(real_gap, np.float64)
    lo, hi = np.nanmin(g), np.nanpercentile(g, 95)
    return float(lo + fraction * (hi - lo))


BILABIAL_LEAD_S = 0.16
"""How long before the phone recogniser's p / b / m frame the lips may close. The recogniser (CTC-style:
one peaked frame per phone) marks these phones at or after the release, while the lips close during the
preceding 50-150 ms. Chosen on the validation people of ``scripts/data_split.json`` (184 bilabial frames,
real tracked mouths): windows from 0 / 0.08 / 0.12 / 0.16 / 0.2 s before the marked frame to it found
the mouth closed at 25 / 49 / 69 / 80 / 82 % of them, against 16 / 26 / 29 / 33 / 34 % at random frames."""


def bilabial_closure_rate(
    gap: np.ndarray, bilabial: np.ndarray, level: float, before: int, after: int = 0
) -> float:
    """Fraction of bilabial frames (``(T,)`` bool) at which the mouth closes: the smallest inner-lip gap
    ``(T,)`` from ``before`` frames before the frame to ``after`` frames after it is at or below ``level``
    (see :data:`BILABIAL_LEAD_S` for ``before``). NaN if there is no bilabial frame with a finite gap."""
    g = np.asarray(gap, np.float64)
    idx = np.flatnonzero(bilabial)
    ok = np.isfinite(g[idx])
    if not ok.any():
        return float("nan")
    padded = np.pad(np.where(np.isfinite(g), g, np.inf), (before, after), constant_values=np.inf)
    window = np.lib.stride_tricks.sliding_window_view(padded, before + after + 1).min(1)[idx]
    return float(np.mean(window[ok] <= level))


def pause_mask(voiced: np.ndarray, fps: float, min_pause_s: float = 0.3) -> np.ndarray:
    """``(T,)`` bool: frames inside runs of at least ``min_pause_s`` seconds of unvoiced frames
    (``voiced`` ``(T,)`` bool). Runs touching either end of the clip count too."""
    v = np.asarray(voiced, bool)
    out = np.zeros(len(v), bool)
    need = int(np.ceil(min_pause_s * fps - 1e-9))
    edges = np.diff(np.concatenate([[0], (~v).astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    for a, b in zip(starts, ends, strict=True):
        if b - a >= need:
            out[a:b] = True
    return out


def pause_behaviour(gap: np.ndarray, pauses: np.ndarray, speech: np.ndarray, rest_level: float) -> dict:
    """How a mouth behaves in pauses: inner-lip gaps ``gap`` ``(T,)``, pause and speech frames (``(T,)``
    bool, disjoint).

    Returns ``pause_closed_fraction`` (pause frames with the gap at or below ``rest_level``: closed or
    resting) and ``pause_motion_ratio`` (mean ``|gap[t+1] - gap[t]|`` over consecutive pause frames divided
    by the same over consecutive speech frames; 0 for a still mouth in pauses, about 1 for a mouth that
    keeps talking). NaN where there are no such frames.
    """
    g = np.asarray(gap, np.float64)
    p, s = np.asarray(pauses, bool), np.asarray(speech, bool)
    closed = float(np.nanmean(g[p] <= rest_level)) if p.any() else float("nan")
    d = np.abs(np.diff(g))
    dp, ds = d[p[1:] & p[:-1]], d[s[1:] & s[:-1]]
    dp, ds = dp[np.isfinite(dp)], ds[np.isfinite(ds)]
    ratio = float(dp.mean() / ds.mean()) if len(dp) and len(ds) and ds.mean() > 0 else float("nan")
    return {"pause_closed_fraction": closed, "pause_motion_ratio": ratio}


def opening_range_ratio(gap: np.ndarray, real_gap: np.ndarray, q: float = 95.0) -> float:
    """``q``-th percentile of the inner-lip gap ``(T,)`` over that of the real video ``(T',)`` (1 is the real
    range; below 1 the mouth opens too little). NaN ignored."""
    real = float(np.nanpercentile(real_gap, q))
    return float(np.nanpercentile(gap, q) / real) if real > 0 else float("nan")


def corner_motion_asymmetry(vertices: np.ndarray, left: int, right: int) -> float:
    """How lopsided a mouth moves: ``(s_l - s_r) / (s_l + s_r)`` where ``s`` is the RMS distance of a mouth
    corner (vertex ``left`` / ``right`` of ``vertices`` ``(T, V, 3)``, object space) from its mean position
    over the frames. 0: both corners move alike; ±1: only one moves. NaN for a still mouth."""
    s = [np.sqrt(np.mean(np.sum((vertices[:, i] - vertices[:, i].mean(0)) ** 2, -1))) for i in (left, right)]
    return float((s[0] - s[1]) / (s[0] + s[1])) if s[0] + s[1] > 0 else float("nan")
