"""``TrackedSequence``: the tracker's output, one entry per video frame on a constant-rate grid."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from nvp.artifact import load_artifact, save_artifact
from nvp.errors import FormatError
from nvp.geometry import pinhole, posed

if TYPE_CHECKING:
    from nvp.face_model import FaceModel

FORMAT_VERSION = 1
MANIFEST = "tracked.json"
ARRAY_FIELDS = (
    "center",
    "identity",
    "rotation",
    "translation",
    "expression",
    "landmarks",
    "valid",
    "fit_error",
)


@dataclass(frozen=True)
class TrackedSequence:
    """Face-model fit of a video.

    Camera: OpenCV pinhole, square pixels; a model vertex ``X`` (cm, object frame) maps to the camera as
    ``R_t X + t_t`` and to pixels as ``focal * (x, y) / z + center``.

    Attributes:
        fps: frame rate of the frame grid, Hz.
        width, height: image size in pixels.
        focal: focal length in pixels.
        center: ``(2,)`` principal point in pixels.
        identity: ``(K_id,)`` identity coefficients (one per video).
        rotation: ``(T, 3, 3)`` object-to-camera rotations.
        translation: ``(T, 3)`` object-to-camera translations, cm.
        expression: ``(T, K_exp)`` expression coefficients.
        landmarks: ``(T, L, 2)`` detected landmarks in pixels (row 0 = top); NaN where no face was found.
        valid: ``(T,)`` bool; False where no face was found or the fit was poor (such frames hold values
            bridged from their valid neighbours).
        fit_error: ``(T,)`` RMS reprojection error of the fitted model to the landmarks, pixels (NaN where
            no face was found).
        face_model_sha256: hash of the face model the coefficients belong to.
        info: free-form provenance (config, timings), JSON-serialisable.
        iris: ``(T, 2, 3)`` centre ``x, y`` and radius (pixels) of the face's left and right iris as detected
            (:func:`nvp.gaze.iris_circles`; NaN where no face was found), or None (tracked before nvp kept
            them): where the eyes look (:func:`nvp.gaze.gaze_from_iris`).
    """

    fps: float
    width: int
    height: int
    focal: float
    center: np.ndarray
    identity: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    expression: np.ndarray
    landmarks: np.ndarray
    valid: np.ndarray
    fit_error: np.ndarray
    face_model_sha256: str
    info: dict = field(default_factory=dict)
    iris: np.ndarray | None = None

    def __post_init__(self) -> None:
        t = self.rotation.shape[0]
        checks = {
            "rotation": (self.rotation.shape, (t, 3, 3)),
            "translation": (self.translation.shape, (t, 3)),
            "expression": (self.expression.shape[:1], (t,)),
            "landmarks": (self.landmarks.shape[:1] + self.landmarks.shape[2:], (t, 2)),
            "valid": (self.valid.shape, (t,)),
            "fit_error": (self.fit_error.shape, (t,)),
        }
        if self.iris is not None:
            checks["iris"] = (self.iris.shape, (t, 2, 3))
        for name, (found, expected) in checks.items():
            if tuple(found) != expected:
                raise FormatError(f"TrackedSequence.{name}: expected shape {expected}, found {found}")

    @property
    def num_frames(self) -> int:
        return self.rotation.shape[0]

    def head(self, num_frames: int) -> TrackedSequence:
        """The first ``num_frames`` frames (same camera and identity)."""
        return self.frames(slice(0, int(num_frames)))

    def frames(self, index: slice | np.ndarray) -> TrackedSequence:
        """The frames ``index`` selects (a slice, indices or a ``(T,)`` bool mask), in that order (same
        camera and identity)."""
        per_frame = ("rotation", "translation", "expression", "landmarks", "valid", "fit_error")
        iris = None if self.iris is None else self.iris[index]
        return dataclasses.replace(self, iris=iris, **{k: getattr(self, k)[index] for k in per_frame})

    def camera_vertices(
        self, model: FaceModel, frames: np.ndarray, expression: np.ndarray | None = None
    ) -> np.ndarray:
        """``(B, V, 3)`` camera-frame vertices of ``model`` with this sequence's identity, posed like
        ``frames`` ``(B,)``, with ``expression`` ``(B, K_exp)`` (default: the tracked expressions of
        ``frames``)."""
        frames = np.asarray(frames)
        expression = self.expression[frames] if expression is None else expression
        v = model.vertices(self.identity, expression)
        return posed(v, self.rotation[frames], self.translation[frames])

    def pixels(self, points: np.ndarray) -> np.ndarray:
        """Pixels ``(..., V, 2)`` of camera-frame points ``(..., V, 3)`` (row 0 = top of the image)."""
        return pinhole(points, self.focal, self.center)

    def save(self, out_dir: str | Path) -> Path:
        """Write ``tracked.json`` + ``tracked.npz`` into ``out_dir`` (:mod:`nvp.artifact`; other files in
        ``out_dir``, e.g. a preview, are kept). Returns the manifest path."""
        arrays = {k: getattr(self, k) for k in ARRAY_FIELDS}
        if self.iris is not None:
            arrays["iris"] = self.iris
        fields = {
            "fps": self.fps,
            "width": self.width,
            "height": self.height,
            "focal": self.focal,
            "num_frames": self.num_frames,
            "valid_frames": int(self.valid.sum()),
            "face_model_sha256": self.face_model_sha256,
            "info": self.info,
        }
        return save_artifact(
            Path(out_dir) / MANIFEST, "tracked_sequence", FORMAT_VERSION, arrays, fields, True
        )

    @classmethod
    def load(cls, path: str | Path) -> TrackedSequence:
        """Load from a tracking directory (or its ``tracked.json``)."""
        path = Path(path)
        js = path if path.suffix == ".json" else path / MANIFEST
        art = load_artifact(js, "tracked_sequence", FORMAT_VERSION)
        m = art.manifest
        missing = set(ARRAY_FIELDS) - set(art.arrays)
        if missing:
            raise FormatError(f"{art.path}: arrays {', '.join(sorted(missing))} missing")
        return cls(
            fps=float(m["fps"]),
            width=int(m["width"]),
            height=int(m["height"]),
            focal=float(m["focal"]),
            face_model_sha256=m["face_model_sha256"],
            info=m.get("info", {}),
            iris=art.arrays.get("iris"),
            **{k: art.arrays[k] for k in ARRAY_FIELDS},
        )
