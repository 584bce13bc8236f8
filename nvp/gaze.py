"""Where the eyes look: a gaze track (yaw and pitch per video frame) from a request (``camera``) or a file,
and its eye rotations.

Angles are in the face's frame: yaw turns the eyes towards the face's left (the viewer's right, +X in glTF),
pitch raises them; 0 / 0 looks straight ahead, which for a face turned to the camera is into the lens.

A gaze file is CSV or JSON with a time in seconds (from the audio's first sample) and the two angles in
degrees, linearly interpolated between its samples and held before the first and after the last:

    time_s,yaw_deg,pitch_deg          [{"time_s": 0.0, "yaw_deg": 0, "pitch_deg": 0},
    0.0,0,0                            {"time_s": 2.5, "yaw_deg": 15, "pitch_deg": -5}]
    2.5,15,-5
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from nvp.errors import NvpError

MAX_ANGLE_DEG = 45.0
"""Largest yaw or pitch a gaze file may ask for (human eyes turn about 45 degrees from straight ahead)."""
FIELDS = ("time_s", "yaw_deg", "pitch_deg")
EYEBALL_RADIUS_CM = 1.2
"""An adult eyeball's radius (about 12 mm): its centre of rotation lies this far behind the eye opening."""


def eye_centres(vertices: np.ndarray, loops: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """``(2, 3)`` the face's left and right eyeball centres (the left one at larger x: the face looks at
    the camera) for its vertices ``(V, 3)`` (face-model camera frame, cm, +Z away from the camera) and the
    vertex loops of its two eye openings: the middle of each loop, moved :data:`EYEBALL_RADIUS_CM` back
    into the head."""
    v = np.asarray(vertices, np.float64)
    centres = np.stack([v[np.asarray(loop)].mean(0) for loop in loops])
    centres[:, 2] += EYEBALL_RADIUS_CM
    return centres[np.argsort(-centres[:, 0])].astype(np.float32)


def read_gaze_file(path: Path) -> np.ndarray:
    """``(N, 3)`` float64 rows ``time_s, yaw_deg, pitch_deg`` of a gaze file (see the module), sorted by
    time. Raises NvpError naming the file and the problem (unreadable, a missing column, a value that is no
    number, an angle beyond :data:`MAX_ANGLE_DEG`, no row)."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise NvpError(f"cannot read the gaze file {path}: {e}") from e
    try:
        if path.suffix.lower() == ".json":
            rows = json.loads(text)
            if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
                raise ValueError("expected a list of objects")
        else:
            rows = list(csv.DictReader(text.splitlines()))
        table = np.array([[float(r[k]) for k in FIELDS] for r in rows], np.float64).reshape(-1, 3)
    except (KeyError, ValueError, TypeError) as e:
        what = f"column {e}" if isinstance(e, KeyError) else str(e)
        raise NvpError(f"{path}: expected {', '.join(FIELDS)} on every row ({what})") from e
    if len(table) == 0:
        raise NvpError(f"{path} holds no gaze sample")
    if not np.all(np.isfinite(table)) or np.abs(table[:, 1:]).max() > MAX_ANGLE_DEG:
        raise NvpError(f"{path}: angles must be finite and within ±{MAX_ANGLE_DEG:g} degrees")
    return table[np.argsort(table[:, 0], kind="stable")]


def gaze_track(request: str | Path, num_frames: int, fps: float) -> np.ndarray:
    """``(T, 2)`` float32 yaw and pitch in radians of each video frame (frame ``j`` at ``j / fps`` s) for
    ``request``: ``"camera"`` (straight ahead) or a gaze file (:func:`read_gaze_file`)."""
    if str(request) == "camera":
        return np.zeros((num_frames, 2), np.float32)
    table = read_gaze_file(Path(request))
    t = np.arange(num_frames) / fps
    yaw = np.interp(t, table[:, 0], table[:, 1])
    pitch = np.interp(t, table[:, 0], table[:, 2])
    return np.radians(np.stack([yaw, pitch], 1)).astype(np.float32)


def gaze_quaternions(gaze: np.ndarray) -> np.ndarray:
    """``(T, 4)`` unit quaternions ``(x, y, z, w)`` (glTF's order) turning +Z (glTF's forward) to each
    frame's gaze ``(T, 2)`` (yaw about +Y, then pitch about -X): the eyes' rotations."""
    yaw, pitch = np.asarray(gaze, np.float64).T
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    cp, sp = np.cos(-pitch / 2), np.sin(-pitch / 2)
    # q = q_yaw * q_pitch with q_yaw = (0, sy, 0, cy), q_pitch = (sp, 0, 0, cp)
    q = np.stack([cy * sp, sy * cp, -sy * sp, cy * cp], 1)
    return q.astype(np.float32)


def gaze_direction(quaternions: np.ndarray) -> np.ndarray:
    """``(T, 2)`` yaw and pitch (radians) where rotations ``(T, 4)`` turn +Z: the inverse of
    :func:`gaze_quaternions`."""
    x, y, z, w = np.asarray(quaternions, np.float64).T
    # the rotated +Z: the third column of the rotation matrix
    fx = 2 * (x * z + w * y)
    fy = 2 * (y * z - w * x)
    fz = 1 - 2 * (x * x + y * y)
    return np.stack([np.arctan2(fx, fz), np.arcsin(np.clip(fy, -1, 1))], 1).astype(np.float32)
