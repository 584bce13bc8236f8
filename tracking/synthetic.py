"""Synthetic tracking data with known answers: the face model posed, projected and perturbed."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from nvp.gaze import eye_loops, eyeball_centres, gaze_vectors, iris_pixels
from tracking.detect import Detections


def synthetic_sequence(
    model, *, frames=60, fps=25.0, size=512, focal=1024.0, noise_px=1.0, seed=0, missing=()
):
    """Known identity, pose and expression, projected to 2D landmarks with Gaussian pixel noise.

    The eyes look around (yaw and pitch up to 15 degrees, both eyes alike): the 10 iris points are the
    projected iris centre (:func:`nvp.gaze.iris_pixels`) and four points on a 0.55 cm circle around it.

    Returns (Detections, truth dict). Truth holds identity (K_id,), rotation (T,3,3), translation (T,3),
    expression (T,K_exp), focal, object-space vertices (T,V,3) and gaze (T,2) (yaw, pitch in radians).
    """
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / fps
    identity = rng.normal(0, 1.0, model.num_id).astype(np.float32)
    expression = np.zeros((frames, model.num_exp), np.float32)
    for k in range(model.num_exp):
        amp = 1.0 if k < 12 else 0.3
        f1, ph = rng.uniform(0.5, 4.0), rng.uniform(0, 2 * np.pi)
        expression[:, k] = amp * np.sin(2 * np.pi * f1 * t + ph)
    angles = np.stack(
        [8 * np.sin(2 * np.pi * 0.3 * t), 20 * np.sin(2 * np.pi * 0.2 * t + 1), 5 * np.sin(t)], 1
    )
    rotation = Rotation.from_euler("xyz", angles, degrees=True).as_matrix().astype(np.float32)
    depth = 60.0
    translation = np.stack([np.sin(t) * 2, np.cos(t) * 1.5, depth + np.sin(0.7 * t) * 3], 1).astype(
        np.float32
    )
    verts = model.vertices(identity, expression)
    cam = np.einsum("tij,tvj->tvi", rotation, verts) + translation[:, None]
    uv = cam[..., :2] / cam[..., 2:3] * focal + size / 2.0
    uv = uv + rng.normal(0, noise_px, uv.shape)
    z = (cam[..., 2] - cam[..., 2].mean(1, keepdims=True)) * focal / depth
    pts = np.concatenate([uv, z[..., None]], -1)[:, model.landmark_vertices]
    gaze = np.radians(np.stack([15 * np.sin(2 * np.pi * 0.4 * t), 10 * np.sin(2 * np.pi * 0.25 * t)], 1))
    centres = eyeball_centres(cam, rotation, eye_loops(model))
    looks = np.einsum("tij,tj->ti", rotation, gaze_vectors(gaze))[:, None].repeat(2, 1)
    principal = np.array([size / 2.0, size / 2.0])
    iris = []
    for eye in (1, 0):  # mediapipe's order: the right iris (468-472), then the left (473-477)
        middle = iris_pixels(centres[:, eye], looks[:, eye], focal, principal)
        edge = 0.55 * focal / centres[:, eye, 2:3]
        ring = [middle + edge * np.array(d) for d in ((1, 0), (0, -1), (-1, 0), (0, 1))]
        iris += [middle, *ring]
    iris = np.stack(iris, 1) + rng.normal(0, noise_px, (frames, 10, 2))
    iris = np.concatenate([iris, np.zeros((frames, 10, 1))], -1)
    points = np.concatenate([pts, iris], 1).astype(np.float32)
    found = np.ones(frames, bool)
    found[list(missing)] = False
    points[~found] = np.nan
    det = Detections(
        fps=fps,
        width=size,
        height=size,
        points=points,
        blendshapes=np.full((frames, 52), np.nan, np.float32),
        found=found,
    )
    truth = dict(
        identity=identity,
        rotation=rotation,
        translation=translation,
        expression=expression,
        focal=focal,
        vertices=verts,
        gaze=gaze.astype(np.float32),
    )
    return det, truth


def synthetic_tracked(model, *, frames=12, size=96, focal=200.0, seed=0):
    """A ``TrackedSequence`` holding the exact truth of :func:`synthetic_sequence` (for renderer tests and
    benchmarks that need a posed face without running the tracker)."""
    from nvp.gaze import iris_circles
    from nvp.tracked import TrackedSequence

    det, truth = synthetic_sequence(model, frames=frames, size=size, focal=focal, noise_px=0.0, seed=seed)
    return TrackedSequence(
        fps=25.0,
        width=size,
        height=size,
        focal=float(focal),
        center=np.array([size / 2, size / 2], np.float32),
        identity=truth["identity"],
        rotation=truth["rotation"],
        translation=truth["translation"],
        expression=truth["expression"],
        landmarks=np.zeros((frames, 478, 2), np.float32),
        valid=np.ones(frames, bool),
        fit_error=np.zeros(frames, np.float32),
        face_model_sha256=model.sha256,
        iris=iris_circles(det.points),
    )
