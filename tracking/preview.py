"""Preview video: the fitted mesh drawn over the footage."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from nvp.face_model import FaceModel, default_face_model
from nvp.geometry import pinhole, posed
from nvp.media import VideoWriter, iter_frames, probe_video, read_audio
from nvp.tracked import TrackedSequence

MESH = (200, 200, 200)
LIPS = (255, 64, 64)
EYES = (64, 200, 255)
DETECTED = (255, 255, 0)
INVALID = (255, 0, 0)


def mesh_edges(triangles: np.ndarray) -> np.ndarray:
    """Unique undirected edges ``(E, 2)`` of a triangle list ``(F, 3)``."""
    e = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    return np.unique(np.sort(e, 1), axis=0)


def draw_overlay(
    frame: np.ndarray,
    uv: np.ndarray,
    edges: np.ndarray,
    model: FaceModel,
    landmarks: np.ndarray | None = None,
    valid: bool = True,
) -> np.ndarray:
    """Draw projected mesh ``uv (V,2)`` (pixels) onto an RGB uint8 frame; returns a new frame."""
    import cv2

    out = frame.copy()
    face_px = float(np.ptp(uv[:, 0])) if np.isfinite(uv).all() else max(frame.shape[:2]) / 3
    thick = max(1, round(face_px / 250))  # lines scale with the face, not the frame
    shift = 4
    pts = np.round(uv * (1 << shift)).astype(np.int32)
    segs = pts[edges]
    overlay = out.copy()
    cv2.polylines(overlay, list(segs), False, MESH, thick, cv2.LINE_AA, shift)
    out = cv2.addWeighted(overlay, 0.45, out, 0.55, 0)
    g = model.landmark_groups
    for name, color in (("lips_outer", LIPS), ("lips_inner", LIPS), ("left_eye", EYES), ("right_eye", EYES)):
        loop = pts[model.landmark_vertices[g[name]]]
        cv2.polylines(out, [loop], True, color, thick, cv2.LINE_AA, shift)
    if landmarks is not None and np.isfinite(landmarks).all():
        for name in ("lips_outer", "lips_inner"):
            for x, y in landmarks[g[name]]:
                cv2.circle(out, (int(x * 16), int(y * 16)), thick + 1, DETECTED, -1, cv2.LINE_AA, shift)
    if not valid:
        cv2.rectangle(out, (0, 0), (out.shape[1] - 1, out.shape[0] - 1), INVALID, 3 * thick)
    return out


def write_preview(
    video: str | Path,
    seq: TrackedSequence,
    out: str | Path,
    model: FaceModel | None = None,
    progress: bool = True,
) -> None:
    """Write an mp4 of ``video`` with the fitted mesh of ``seq`` drawn on every frame (audio kept)."""
    model = model or default_face_model()
    info = probe_video(video)
    verts = model.vertices(seq.identity, seq.expression)
    uv = pinhole(posed(verts, seq.rotation, seq.translation), seq.focal, seq.center)
    edges = mesh_edges(model.triangles)
    audio = read_audio(video) if info.has_audio else None
    with VideoWriter(out, fps=seq.fps, width=seq.width, height=seq.height, audio=audio) as wr:
        frames = iter_frames(video, fps=seq.fps, max_frames=seq.num_frames)
        for i, frame in enumerate(tqdm(frames, total=seq.num_frames, desc="preview", disable=not progress)):
            wr.write(draw_overlay(frame, uv[i], edges, model, seq.landmarks[i], bool(seq.valid[i])))
