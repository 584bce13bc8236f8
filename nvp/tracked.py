"""``TrackedSequence``: the tracker's output, one entry per video frame on a constant-rate grid."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nvp.errors import FormatError

FORMAT_VERSION = 1
MANIFEST = "tracked.json"
ARRAYS = "tracked.npz"


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
        for name, (found, expected) in checks.items():
            if tuple(found) != expected:
                raise FormatError(f"TrackedSequence.{name}: expected shape {expected}, found {found}")

    @property
    def num_frames(self) -> int:
        return self.rotation.shape[0]

    def head(self, num_frames: int) -> TrackedSequence:
        """The first ``num_frames`` frames (same camera and identity)."""
        n = int(num_frames)
        per_frame = ("rotation", "translation", "expression", "landmarks", "valid", "fit_error")
        return dataclasses.replace(self, **{k: getattr(self, k)[:n] for k in per_frame})

    def save(self, out_dir: str | Path) -> Path:
        """Write ``tracked.json`` + ``tracked.npz`` into ``out_dir`` atomically (temp dir, then rename)."""
        out_dir = Path(out_dir)
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
        try:
            np.savez_compressed(
                tmp / ARRAYS,
                center=self.center,
                identity=self.identity,
                rotation=self.rotation,
                translation=self.translation,
                expression=self.expression,
                landmarks=self.landmarks,
                valid=self.valid,
                fit_error=self.fit_error,
            )
            manifest = {
                "format": "nvp.tracked_sequence",
                "version": FORMAT_VERSION,
                "arrays": ARRAYS,
                "fps": self.fps,
                "width": self.width,
                "height": self.height,
                "focal": self.focal,
                "num_frames": self.num_frames,
                "valid_frames": int(self.valid.sum()),
                "face_model_sha256": self.face_model_sha256,
                "info": self.info,
            }
            (tmp / MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n")
            if out_dir.exists():
                # replace only our own files; other outputs in out_dir (e.g. a preview) are kept
                for name in (ARRAYS, MANIFEST):
                    os.replace(tmp / name, out_dir / name)
                shutil.rmtree(tmp)
            else:
                os.replace(tmp, out_dir)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return out_dir / MANIFEST

    @classmethod
    def load(cls, path: str | Path) -> TrackedSequence:
        """Load from a tracking directory (or its ``tracked.json``)."""
        path = Path(path)
        js = path / MANIFEST if path.is_dir() else path
        try:
            m = json.loads(js.read_text())
        except (OSError, ValueError) as e:
            raise FormatError(f"cannot read tracking manifest {js}: {e}") from e
        if m.get("format") != "nvp.tracked_sequence" or m.get("version") != FORMAT_VERSION:
            raise FormatError(
                f"{js}: expected nvp.tracked_sequence version {FORMAT_VERSION}, "
                f"found {m.get('format')} version {m.get('version')}"
            )
        try:
            with np.load(js.parent / m["arrays"]) as z:
                a = {k: z[k] for k in z.files}
        except (OSError, ValueError, KeyError) as e:
            raise FormatError(f"cannot read tracking arrays next to {js}: {e}") from e
        return cls(
            fps=float(m["fps"]),
            width=int(m["width"]),
            height=int(m["height"]),
            focal=float(m["focal"]),
            face_model_sha256=m["face_model_sha256"],
            info=m.get("info", {}),
            **a,
        )
