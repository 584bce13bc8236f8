"""Run the landmark detector over a whole video → ``Detections`` (streamed, bounded memory)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from nvp.errors import NoFaceError
from nvp.media import iter_frames, probe_video
from tracking.landmarks import NUM_BLENDSHAPES, NUM_LANDMARKS, LandmarkDetector
from tracking.lipflow import mouth_flow

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Detections:
    """Raw per-frame detector output for a video on its constant-rate frame grid.

    Attributes:
        fps: frame rate of the grid, Hz.
        width, height: frame size in pixels (after rotation metadata is applied).
        points: ``(T, 478, 3)`` float32 landmarks (x, y pixels; z pixels, relative); NaN where not found.
        blendshapes: ``(T, 52)`` float32 ARKit scores; NaN where not found.
        found: ``(T,)`` bool, whether a face was detected in the frame.
        lip_points: ``(N,)`` the landmarks (lips) whose motion between frames was measured, or None.
        lip_flow: ``(T, 2, N, 2)`` float32 optical flow at those landmarks of frame ``t`` (x, y pixels):
            ``[:, 0]`` to frame ``t + 1``, ``[:, 1]`` to frame ``t - 1``
            (:func:`tracking.lipflow.mouth_flow`); NaN where either frame has no face. None when not measured.
    """

    fps: float
    width: int
    height: int
    points: np.ndarray
    blendshapes: np.ndarray
    found: np.ndarray
    lip_points: np.ndarray | None = None
    lip_flow: np.ndarray | None = None

    def save(self, path: Path) -> None:
        flow = {} if self.lip_flow is None else {"lip_points": self.lip_points, "lip_flow": self.lip_flow}
        np.savez_compressed(
            path,
            fps=self.fps,
            width=self.width,
            height=self.height,
            points=self.points,
            blendshapes=self.blendshapes,
            found=self.found,
            **flow,
        )

    @classmethod
    def load(cls, path: Path) -> Detections:
        with np.load(path) as z:
            return cls(
                fps=float(z["fps"]),
                width=int(z["width"]),
                height=int(z["height"]),
                points=z["points"],
                blendshapes=z["blendshapes"],
                found=z["found"],
                lip_points=z["lip_points"] if "lip_points" in z else None,
                lip_flow=z["lip_flow"] if "lip_flow" in z else None,
            )


def detect_video(
    path: str | Path,
    *,
    stride: int = 1,
    max_frames: int | None = None,
    progress: bool = True,
    lips: np.ndarray | None = None,
) -> Detections:
    """Detect landmarks on every ``stride``-th frame of a video; with ``lips`` (landmark indices) also the
    optical flow at them between neighbouring frames (``Detections.lip_flow``).

    Raises:
        MediaError: unreadable file or no video stream.
        NoFaceError: no face in any frame.
    """
    info = probe_video(path)
    total = info.num_frames if max_frames is None else min(info.num_frames, max_frames)
    pts, bss, found, flows = [], [], [], []
    previous = None  # the last frame and its lip points, when it had a face
    with LandmarkDetector() as det:
        frames = iter_frames(path, max_frames=max_frames)
        bar = tqdm(total=total, desc=f"detect {Path(path).name}", unit="f", disable=not progress, leave=False)
        for i, rgb in enumerate(frames):
            bar.update(1)
            if i % stride:
                continue
            r = det.detect(rgb, i / info.fps)
            if lips is not None:
                flows.append(np.full((2, len(lips), 2), np.nan, np.float32))
            if r is None:
                pts.append(np.full((NUM_LANDMARKS, 3), np.nan, np.float32))
                bss.append(np.full(NUM_BLENDSHAPES, np.nan, np.float32))
                found.append(False)
                previous = None
            else:
                pts.append(r.points)
                bss.append(r.blendshapes)
                found.append(True)
                if lips is not None:
                    here = r.points[lips, :2]
                    if previous is not None:
                        flows[-2][0], flows[-1][1] = mouth_flow(*previous, rgb, here)
                    previous = rgb, here
        bar.close()
    if not any(found):
        raise NoFaceError(f"no face found in any of the {len(found)} frames of {path}")
    return Detections(
        fps=info.fps / stride,
        width=info.width,
        height=info.height,
        points=np.stack(pts),
        blendshapes=np.stack(bss),
        found=np.asarray(found),
        lip_points=None if lips is None else np.asarray(lips),
        lip_flow=np.stack(flows) if lips is not None else None,
    )


def count_faces(path: str | Path, samples: int = 8) -> int:
    """The most faces mediapipe finds in any of ``samples`` frames spread over the video (up to 3): a
    quick check that a target shows one person."""
    info = probe_video(path)
    picks = set(np.linspace(0, info.num_frames - 1, samples).round().astype(int).tolist())
    most = 0
    with LandmarkDetector(max_faces=3) as det:
        for i, rgb in enumerate(iter_frames(path, max_frames=max(picks) + 1)):
            if i in picks:
                r = det.detect(rgb, i / info.fps)
                most = max(most, r.faces if r is not None else 0)
    return most
