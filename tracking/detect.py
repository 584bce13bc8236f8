"""Run the landmark detector over a whole video → ``Detections`` (streamed, bounded memory)."""

from __future__ import annotations

import logging
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from nvp.errors import NoFaceError
from nvp.media import iter_frames, probe_video
from nvp.threads import available_cores
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


SEGMENT_FRAMES = 250
"""Detection runs in segments of this many frames (10 s at 25 fps), each with a fresh detector, so that a
segment's landmarks depend only on its own frames (and the :data:`WARMUP_FRAMES` before it) and can be saved
once done: a run that saves them (``saves``) and is killed goes on from the last whole segment with exactly
the result of an uninterrupted run (mediapipe's VIDEO mode carries state from frame to frame; a detector
restarted at an arbitrary frame keeps differing by about 0.6 px for the rest of the video)."""

WARMUP_FRAMES = 10
"""Frames before a segment its fresh detector sees first (and whose landmarks it drops), so that it joins
the previous segment's tracking: restarted without them the landmarks jump by up to 3 px; with 5 / 10 / 20
the largest difference from one detector over the whole video is 0.8-1.6 / 0.3-0.6 / 0.1-0.2 px in the first
frames of a segment (videoretalking__face5, 524², boundaries at frames 40, 50 and 100)."""

SAVES_FORMAT = "detections_segment"

MAX_WORKERS = 4
"""At most this many segments are detected at once (one per core): mediapipe keeps about 1.4 of 2 cores busy
with one detector; two took a 60 s 512² clip from 35.6 to 21.0 s (AMD EPYC, 2 cores, the same landmarks and
lip flow bit for bit)."""


def detections_key(path: str | Path, stride: int, max_frames: int | None, lips: np.ndarray | None) -> dict:
    """What saved segments of ``path`` must have been made with to be resumed: the video's sha256, the
    detection settings, the detector's model and nvp's version (:func:`nvp.provenance.code_version`)."""
    from nvp.artifact import file_sha256
    from nvp.provenance import code_version
    from tracking.landmarks import TASK_MD5

    return {
        "input_sha256": file_sha256(Path(path)),
        "stride": int(stride),
        "max_frames": max_frames,
        "lips": None if lips is None else [int(i) for i in lips],
        "warmup": WARMUP_FRAMES,
        "detector_md5": TASK_MD5,
        "nvp": code_version(),
    }


def _segment_path(saves: Path, j: int) -> Path:
    return saves / f"segment-{j:05d}.json"


def _segments(n: int, segment: int) -> list[tuple[int, int]]:
    return [(a, min(a + segment, n)) for a in range(0, n, segment)]


def saved_segments(saves: Path, key: dict, n: int, segment: int | None = None) -> list[dict]:
    """The whole segments in ``saves`` made with ``key`` for a video of ``n`` detected frames, in order
    from the first (up to the first missing, damaged or foreign one); each a dict of arrays."""
    from nvp.artifact import load_artifact
    from nvp.errors import FormatError

    segment = segment or SEGMENT_FRAMES
    out = []
    for j, (a, b) in enumerate(_segments(n, segment)):
        try:
            art = load_artifact(_segment_path(saves, j), SAVES_FORMAT, 1)
        except FormatError:
            break
        m = art.manifest
        if m.get("key") != key or (m.get("start"), m.get("end")) != (a, b):
            break
        out.append(art.arrays)
    return out


def detect_video(
    path: str | Path,
    *,
    stride: int = 1,
    max_frames: int | None = None,
    progress: bool = True,
    lips: np.ndarray | None = None,
    saves: Path | None = None,
    segment: int | None = None,
) -> Detections:
    """Detect landmarks on every ``stride``-th frame of a video; with ``lips`` (landmark indices) also the
    optical flow at them between neighbouring frames (``Detections.lip_flow``).

    The frames are detected in segments of ``segment`` frames (:data:`SEGMENT_FRAMES`); with ``saves`` (a
    folder) each segment is saved there when done (an atomic artifact per segment, made with
    :func:`detections_key`), and a run finds the segments an interrupted one saved and goes on after them
    (same result as an uninterrupted run). The caller removes the folder when it no longer needs it.

    Raises:
        MediaError: unreadable file or no video stream.
        NoFaceError: no face in any frame.
    """
    from nvp.artifact import save_artifact

    segment = segment or SEGMENT_FRAMES
    info = probe_video(path)
    total = info.num_frames if max_frames is None else min(info.num_frames, max_frames)
    grid = np.arange(0, total, stride)  # the video frames detected
    n = len(grid)
    key = done = None
    if saves is not None:
        key = detections_key(path, stride, max_frames, lips)
        done = saved_segments(saves, key, n, segment)
        if done:
            log.info(
                "detection goes on after %d saved frames of %s", sum(len(d["found"]) for d in done), path
            )
    parts = list(done or [])
    bar = tqdm(total=n, desc=f"detect {Path(path).name}", unit="f", disable=not progress, leave=False)
    bar.update(sum(len(p["found"]) for p in parts))
    bounds = _segments(n, segment)
    workers = max(1, min(available_cores(), MAX_WORKERS))
    lock, stop = threading.Lock(), threading.Event()

    def tick() -> bool:  # one frame done; False once the run is being stopped (an error elsewhere, Ctrl-C)
        with lock:
            bar.update(1)
        return not stop.is_set()

    pool = ThreadPoolExecutor(workers)
    try:
        short = False  # the video ends before its length said (cut short): no more segments
        while len(parts) < len(bounds) and not short:  # `workers` segments at once
            wave = range(len(parts), min(len(parts) + workers, len(bounds)))
            runs = [pool.submit(_detect_segment, path, info.fps, grid, *bounds[j], lips, tick) for j in wave]
            for j, run in zip(wave, runs, strict=True):
                part = run.result()
                a, b = bounds[j]
                if lips is not None and parts:
                    _join_flow(parts[-1], part, lips)
                part.pop("edge", None)
                parts.append(part)
                short = len(part["found"]) < b - a
                if short:
                    break
                if saves is not None:  # saved once joined to the segment before it
                    meta = {"key": key, "start": a, "end": b}
                    save_artifact(_segment_path(saves, j), SAVES_FORMAT, 1, part, meta)
    finally:
        stop.set()  # the segments still running stop at their next frame
        pool.shutdown(cancel_futures=True)
    bar.close()
    if not parts:  # an empty video
        raise NoFaceError(f"no face found in any of the 0 frames of {path}")
    found = np.concatenate([p["found"] for p in parts])
    if not found.any():
        raise NoFaceError(f"no face found in any of the {len(found)} frames of {path}")
    flow = None
    if lips is not None:
        flow = np.concatenate([p["flow"] for p in parts])
        for p, (a, _) in zip(parts[1:], bounds[1:], strict=False):  # the flow into a segment's first frame
            flow[a - 1, 0] = p["previous_forward"]
    return Detections(
        fps=info.fps / stride,
        width=info.width,
        height=info.height,
        points=np.concatenate([p["points"] for p in parts]),
        blendshapes=np.concatenate([p["blendshapes"] for p in parts]),
        found=found,
        lip_points=None if lips is None else np.asarray(lips),
        lip_flow=flow,
    )


def _detect_segment(
    path: str | Path, fps: float, grid: np.ndarray, a: int, b: int, lips: np.ndarray | None, tick
) -> dict:
    """Detect grid frames ``a:b`` with a fresh detector that first sees the :data:`WARMUP_FRAMES` before
    them. Returns the segment's arrays: ``points``, ``blendshapes``, ``found``, and with ``lips`` ``flow``
    (the flow into the segment's first frame from the one before is NaN until :func:`_join_flow`) and
    ``edge``: the frame before the segment, the first frame and its lip points, for that join (None when
    the segment starts the video or its first frame has no face). ``tick()`` after each frame; when it
    returns False the detection stops there (what it returns is then not used)."""
    first = max(a - WARMUP_FRAMES, 0)
    pts, bss, found, flows = [], [], [], []
    nl = 0 if lips is None else len(lips)
    previous = None  # the last frame and its lip points, when it had a face
    before = None  # the frame before the segment (its landmarks are the previous segment's)
    stride = int(grid[1] - grid[0]) if len(grid) > 1 else 1
    edge = None
    with LandmarkDetector() as det:
        frames = iter_frames(
            path, start_frame=int(grid[first]), max_frames=int(grid[b - 1] - grid[first]) + 1
        )
        for k, rgb in enumerate(frames):
            if k % stride:
                continue
            pos = first + k // stride
            if pos >= b:
                break
            i = int(grid[pos])
            r = det.detect(rgb, i / fps)
            if pos < a:  # warm-up: the previous segment's landmarks stand
                before = rgb if pos == a - 1 else None
                continue
            if lips is not None:
                flows.append(np.full((2, nl, 2), np.nan, np.float32))
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
                    elif pos == a and before is not None:
                        edge = (before, rgb, here)
                    previous = rgb, here
            if not tick():
                break
    part = {
        "points": np.asarray(pts, np.float32).reshape(-1, NUM_LANDMARKS, 3),
        "blendshapes": np.asarray(bss, np.float32).reshape(-1, NUM_BLENDSHAPES),
        "found": np.asarray(found, bool),
    }
    if lips is not None:
        part["flow"] = np.asarray(flows, np.float32).reshape(-1, 2, nl, 2)
        part["previous_forward"] = np.full((nl, 2), np.nan, np.float32)
        part["edge"] = edge
    return part


def _join_flow(before: dict, part: dict, lips: np.ndarray) -> None:
    """The lip flow between ``before``'s last frame and ``part``'s first (the segment after it), when both
    have a face: into ``part``'s ``previous_forward`` (the forward flow of ``before``'s last frame) and its
    first frame's backward flow — what one detector run over both segments computes."""
    if part.get("edge") is None or not len(before["found"]) or not before["found"][-1]:
        return
    prev_rgb, rgb, here = part["edge"]
    part["previous_forward"], part["flow"][0, 1] = mouth_flow(
        prev_rgb, before["points"][-1][lips, :2], rgb, here
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
