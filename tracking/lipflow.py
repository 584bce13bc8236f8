"""Lip landmarks steadied by the image's own motion.

A landmark detector places the lips of each frame on its own, a pixel or so off in a random direction
(at 512², frame-to-frame displacements of the detected lip points disagree with the image's optical flow
by 0.9 px RMS while the lips move 1.5 px). The image motion between neighbouring frames is measured far
more precisely than that, so each frame's outer lip contour (:func:`lip_landmarks`) is predicted from the
neighbouring frame's estimate moved by the optical flow and blended with the frame's own detection (a
complementary filter: the detections keep the estimate from drifting, the flow carries the motion without
the lag of temporal smoothing), once forwards and once backwards in time, and the two passes averaged.
"""

from __future__ import annotations

import numpy as np

CROP_MAX = 256
"""Longest side in pixels of the region the flow is computed on (larger mouths are measured downscaled)."""

MARGIN = 1.0
"""The flow region: the box around both frames' lip points grown on every side by this fraction of its width
(plus 8 px). The flow needs the face around the lips to find their motion: re-creating dfrf__cnn2's held-out
frames (see :data:`tracking.fit.TrackingConfig.lip_flow`; the inner lips steadied too, as first built), the
mouth box's PSNR with 0.3 / 0.8 / 1.2 was 28.99 / 29.31 / 29.34 dB (29.04 without the flow),
edtalk__pose_source2's 29.24 / 29.25 / 29.29 (28.91)."""


def lip_landmarks(model) -> np.ndarray:
    """Indices of the landmarks steadied: a face model's (:class:`nvp.face_model.FaceModel`) outer lip
    contour. The lips' outer edge moves with the skin, so the optical flow there is the lips' motion; the
    inner contour is where the mouth opens and closes — an occlusion, where flow means nothing and where the
    detector's own placement decides the closures. Steadying the inner lips too raised the re-created
    frames' mouth box further (dfrf__cnn2 29.48 → 29.75 dB instead of 29.61, eval_lower_face's visual
    row) but took the closures away: the tracked inner-lip gap's 5th percentile on edtalk__pose_source2
    rose from 0.056 to 0.126 cm (outer only: 0.059), and the audio-driven rows fell by up to 0.14 dB."""
    return np.unique(model.landmark_groups["lips_outer"])


def mouth_flow(
    prev: np.ndarray, prev_points: np.ndarray, cur: np.ndarray, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Optical flow between two neighbouring RGB frames ``prev`` and ``cur`` ``(H, W, 3)`` uint8 around the
    lips: the motion ``(N, 2)`` (x, y pixels) from ``prev`` to ``cur`` at ``prev_points`` ``(N, 2)``, and
    from ``cur`` back to ``prev`` at ``points`` ``(N, 2)``. DIS optical flow (OpenCV) on the box around
    both point sets only (:data:`MARGIN`, at most :data:`CROP_MAX` pixels on a side); NaN when less than 16
    pixels of that box lie inside the frame either way (lips at or beyond its edge)."""
    import cv2

    both = np.concatenate([prev_points, points])
    lo, hi = both.min(0), both.max(0)
    pad = MARGIN * (hi[0] - lo[0]) + 8
    h, w = cur.shape[:2]
    x0, y0 = int(max(np.floor(lo[0] - pad), 0)), int(max(np.floor(lo[1] - pad), 0))
    x1, y1 = int(min(np.ceil(hi[0] + pad), w)), int(min(np.ceil(hi[1] + pad), h))
    if x1 - x0 < 16 or y1 - y0 < 16:
        nothing = np.full((len(points), 2), np.nan, np.float32)
        return nothing, nothing.copy()
    scale = min(1.0, CROP_MAX / max(x1 - x0, y1 - y0, 1))
    size = (max(int(round((x1 - x0) * scale)), 8), max(int(round((y1 - y0) * scale)), 8))
    a, b = (
        cv2.resize(cv2.cvtColor(x[y0:y1, x0:x1], cv2.COLOR_RGB2GRAY), size, interpolation=cv2.INTER_AREA)
        for x in (prev, cur)
    )
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    sx, sy = size[0] / (x1 - x0), size[1] / (y1 - y0)

    def at(flow: np.ndarray, p: np.ndarray) -> np.ndarray:
        # pixel centres: crop pixel c covers frame pixels [x0 + c / s, x0 + (c + 1) / s)
        u = ((p[:, 0] - x0) * sx - 0.5).astype(np.float32)[:, None]
        v = ((p[:, 1] - y0) * sy - 0.5).astype(np.float32)[:, None]
        border = cv2.BORDER_REPLICATE
        dx, dy = (cv2.remap(flow[..., k], u, v, cv2.INTER_LINEAR, borderMode=border) for k in (0, 1))
        return np.stack([dx[:, 0] / sx, dy[:, 0] / sy], 1)

    return at(dis.calc(a, b, None), prev_points), at(dis.calc(b, a, None), points)


def fuse(points: np.ndarray, forward: np.ndarray, backward: np.ndarray, beta: float) -> np.ndarray:
    """Detected points ``(T, N, 2)`` (NaN where no face was found) steadied by the motion between frames:
    ``forward[t]`` ``(N, 2)`` moves frame ``t``'s points to frame ``t + 1``, ``backward[t]`` frame ``t``'s to
    frame ``t - 1`` (NaN where not measured). Each pass predicts a frame's points from its neighbour's
    estimate plus the flow and keeps ``beta`` of the prediction, ``1 - beta`` of the detection; a chain
    restarts from the detection wherever a flow or a neighbour is missing. Returns the mean of the forward
    and the backward pass (the detections where neither applies); ``beta = 0`` returns the detections."""
    t_count = len(points)
    passes = []
    for order, flow, step in ((range(1, t_count), forward, -1), (range(t_count - 2, -1, -1), backward, 1)):
        est = points.copy()
        for t in order:
            moved = est[t + step] + flow[t + step]
            ok = np.isfinite(moved).all(-1) & np.isfinite(points[t]).all(-1)
            est[t] = np.where(ok[:, None], points[t] + beta * (moved - points[t]), points[t])
        passes.append(est)
    return (passes[0] + passes[1]) / 2
