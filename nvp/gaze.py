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
    the camera) for its vertices ``(V, 3)`` (face-model frame, cm, +Z away from the camera) and the
    vertex loops of its two eye openings: :func:`eyeball_centres` of the unposed face."""
    centres = eyeball_centres(vertices, np.eye(3), loops)
    return centres[np.argsort(-centres[:, 0])].astype(np.float32)


REQUESTS = ("footage", "camera")
"""The gaze requests that are not a file: the footage's own gaze, and into the lens."""


def gaze_file(request: str | Path) -> Path | None:
    """The gaze file a ``--gaze`` request names, or None for :data:`REQUESTS`."""
    return None if str(request) in REQUESTS else Path(request)


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
    return gaze_at(read_gaze_file(Path(request)), np.arange(num_frames) / fps)


def gaze_at(table: np.ndarray, times: np.ndarray) -> np.ndarray:
    """``(T, 2)`` float32 yaw and pitch in radians at ``times`` ``(T,)`` (seconds) of a gaze file's rows
    (:func:`read_gaze_file`): interpolated linearly, held before the first row and after the last."""
    angles = [np.interp(times, table[:, 0], table[:, c]) for c in (1, 2)]
    return np.radians(np.stack(angles, -1)).astype(np.float32)


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


IRIS_POINTS = {"left": slice(473, 478), "right": slice(468, 473)}
"""mediapipe's iris landmarks (after the 468 face-mesh points) of the face's left and right eye: the centre,
then four points on the iris's edge."""
EYES = ("left_eye", "right_eye")
"""The face model's landmark groups of the two eye openings (16-point loops), in the order of every
per-eye array here: the face's left eye first."""


def iris_circles(points: np.ndarray) -> np.ndarray:
    """``(..., 2, 3)`` float32 centre ``x, y`` and radius (pixels) of the left and right iris in mediapipe
    landmarks ``(..., 478, >=2)`` (NaN where the landmarks are)."""
    p = np.asarray(points, np.float32)[..., :2]
    circles = []
    for eye in IRIS_POINTS.values():
        iris = p[..., eye, :]
        radius = np.linalg.norm(iris[..., 1:, :] - iris[..., :1, :], axis=-1).mean(-1)
        circles.append(np.concatenate([iris[..., 0, :], radius[..., None]], -1))
    return np.stack(circles, -2)


def eyeball_centres(
    vertices: np.ndarray, rotation: np.ndarray, loops: tuple[np.ndarray, np.ndarray], spread: float = 0.0
):
    """``(..., 2, 3)`` camera-frame centres of rotation of the left and right eyeball for camera-frame
    vertices ``(..., V, 3)`` posed by ``rotation`` ``(..., 3, 3)``: the middle of each eye opening's vertex
    loop, :data:`EYEBALL_RADIUS_CM` behind it along the face's own backward axis (+Z of the model), and
    ``spread`` cm further out sideways (each towards its own side; negative: towards the nose), the
    person's own correction (:func:`eye_spread`)."""
    v = np.asarray(vertices, np.float64)
    r = np.asarray(rotation, np.float64)
    back = r[..., :, 2] * EYEBALL_RADIUS_CM  # the model's +Z in the camera
    side = r[..., :, 0] * spread  # the model's +X (the face's left) in the camera
    left, right = (v[..., np.asarray(loop), :].mean(-2) + back for loop in loops)
    return np.stack([left + side, right - side], -2)


def gaze_vectors(gaze: np.ndarray) -> np.ndarray:
    """``(..., 3)`` unit gaze directions in the face model's frame (+X the face's left, +Y down, +Z away from
    the camera; straight ahead is -Z) of yaw and pitch ``(..., 2)`` (radians, as :func:`gaze_quaternions`)."""
    yaw, pitch = np.moveaxis(np.asarray(gaze, np.float64), -1, 0)
    return np.stack([np.sin(yaw) * np.cos(pitch), -np.sin(pitch), -np.cos(yaw) * np.cos(pitch)], -1)


def gaze_angles(vectors: np.ndarray) -> np.ndarray:
    """``(..., 2)`` yaw and pitch (radians) of model-frame directions ``(..., 3)``: the inverse of
    :func:`gaze_vectors`."""
    d = np.asarray(vectors, np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return np.stack([np.arctan2(d[..., 0], -d[..., 2]), np.arcsin(np.clip(-d[..., 1], -1, 1))], -1)


def gaze_from_iris(centres: np.ndarray, iris: np.ndarray, focal: float, principal: np.ndarray) -> np.ndarray:
    """``(..., 3)`` camera-frame unit gaze directions of eyeballs centred at ``centres`` ``(..., 3)`` (cm)
    whose iris centres are seen at pixels ``iris`` ``(..., 2)`` (pinhole ``focal``, ``principal`` point):
    the ray through the pixel meets the eyeball's sphere (radius :data:`EYEBALL_RADIUS_CM`) where the iris
    is, on the side facing the camera; a ray that misses it counts at its point nearest the sphere."""
    c = np.asarray(centres, np.float64)
    ray = np.concatenate([(np.asarray(iris, np.float64) - principal) / focal, np.ones_like(c[..., :1])], -1)
    ray /= np.linalg.norm(ray, axis=-1, keepdims=True)
    along = (ray * c).sum(-1, keepdims=True)  # distance along the ray to the point nearest the centre
    miss = (c * c).sum(-1, keepdims=True) - along**2  # squared distance of that point from the centre
    depth = along - np.sqrt(np.clip(EYEBALL_RADIUS_CM**2 - miss, 0, None))
    d = ray * depth - c
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def iris_pixels(
    centres: np.ndarray, directions: np.ndarray, focal: float, principal: np.ndarray
) -> np.ndarray:
    """``(..., 2)`` pixels where eyeballs centred at ``centres`` ``(..., 3)`` looking along camera-frame
    ``directions`` ``(..., 3)`` show their iris centre: the inverse of :func:`gaze_from_iris`."""
    p = np.asarray(centres, np.float64) + EYEBALL_RADIUS_CM * np.asarray(directions, np.float64)
    return focal * p[..., :2] / p[..., 2:] + principal


def towards_camera(centres: np.ndarray) -> np.ndarray:
    """``(..., 3)`` camera-frame unit directions from eyeball ``centres`` ``(..., 3)`` into the lens."""
    c = -np.asarray(centres, np.float64)
    return c / np.linalg.norm(c, axis=-1, keepdims=True)


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(...)`` angle in degrees between directions ``a`` and ``b`` ``(..., 3)``."""
    a = np.asarray(a, np.float64) / np.linalg.norm(a, axis=-1, keepdims=True)
    b = np.asarray(b, np.float64) / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1, 1)))


def eye_loops(model) -> tuple[np.ndarray, np.ndarray]:
    """The vertex loops of the left and right eye openings of a :class:`nvp.face_model.FaceModel`."""
    return tuple(model.landmark_vertices[model.landmark_groups[k]] for k in EYES)


def footage_gaze(
    model, seq, frames: np.ndarray | None = None, spread: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Where the eyes of a tracked footage look: ``(eyeball centres, directions)``, both ``(T, 2, 3)``
    camera-frame (left eye first; directions unit, NaN where no iris was detected) of ``frames`` (default:
    all) of ``seq`` (a :class:`nvp.tracked.TrackedSequence` with ``iris``), the eyeballs ``spread`` apart
    (:func:`eyeball_centres`; default: the tracking's own, ``seq.info["eye_spread_cm"]``, else 0)."""
    frames = np.arange(seq.num_frames) if frames is None else np.asarray(frames)
    if seq.iris is None:
        raise NvpError("this tracking holds no iris landmarks (made before nvp measured gaze): track again")
    spread = float(seq.info.get(SPREAD_KEY, 0.0)) if spread is None else spread
    vertices = seq.camera_vertices(model, frames)
    centres = eyeball_centres(vertices, seq.rotation[frames], eye_loops(model), spread)
    return centres, gaze_from_iris(centres, seq.iris[frames, :, :2], seq.focal, seq.center)


def iris_size(seq) -> float:
    """The median iris radius (pixels) of a tracking with ``iris`` (0 when no frame has one)."""
    radius = seq.iris[..., 2]
    return float(np.nanmedian(radius)) if np.isfinite(radius).any() else 0.0


SPREAD_KEY = "eye_spread_cm"
"""Where a tracking keeps its person's :func:`eye_spread` (``TrackedSequence.info``)."""
MAX_SPREAD_CM = 0.4
"""The largest sideways correction of the eyeball centres :func:`eye_spread` makes (4 mm: 19 degrees)."""


def eye_spread(model, seq, frames: int = 300) -> float:
    """The sideways correction (cm, :func:`eyeball_centres`) that makes a person's two eyes look the same
    way, on the median over up to ``frames`` of their tracked frames: eyes look at one point, and the
    points people look at while talking are far enough for the two directions to be within a degree or two
    of parallel. Where the mesh puts the middle of an eye opening is not where that eye's centre of
    rotation is; off by 1 mm, each eye's direction is off by 5 degrees, the two in opposite ways (on ten
    test people the uncorrected eyes disagreed by 4-25 degrees). 0 when no frame shows both irises."""
    have = np.flatnonzero(np.isfinite(seq.iris).all((1, 2)))
    if len(have) == 0:
        return 0.0
    pick = have[np.linspace(0, len(have) - 1, min(frames, len(have))).round().astype(int)]
    vertices, rotation = seq.camera_vertices(model, pick), seq.rotation[pick]

    def apart(spread: float) -> float:  # median yaw of the left eye minus the right's, face frame
        centres = eyeball_centres(vertices, rotation, eye_loops(model), spread)
        looks = gaze_from_iris(centres, seq.iris[pick, :, :2], seq.focal, seq.center)
        yaw = gaze_angles(np.einsum("tij,tei->tej", rotation, looks))[..., 0]
        return float(np.median(yaw[:, 0] - yaw[:, 1]))

    lo, hi = -MAX_SPREAD_CM, MAX_SPREAD_CM  # apart() falls as the centres move out
    if apart(lo) <= 0:
        return lo
    if apart(hi) >= 0:
        return hi
    for _ in range(20):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if apart(mid) > 0 else (lo, mid)
    return round(0.5 * (lo + hi), 4)
