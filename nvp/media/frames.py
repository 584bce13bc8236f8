"""Decoding video frames with PyAV: in order on a fixed frame grid (:func:`iter_frames`), or any frames
in any order with one decoder running forward (:func:`frames_at`)."""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Iterator
from fractions import Fraction
from typing import Any

import numpy as np
from av.video.reformatter import VideoReformatter

from nvp.errors import MediaError
from nvp.media.probe import (
    _AV_ERRORS,
    _open_input,
    _Probe,
    _probe,
    _to_fraction,
    rotate_frame,
)

logger = logging.getLogger(__name__)


class _Slot:
    """A decoded source frame waiting to be emitted, converted to RGB at most once."""

    __slots__ = ("time", "frame", "rgb", "emitted")

    def __init__(self, time: Fraction, frame: Any) -> None:
        self.time = time
        self.frame = frame
        self.rgb: np.ndarray | None = None
        self.emitted = False


def _decode(container: Any, stream: Any) -> Iterator[Any]:
    """Decoded frames of one stream, in presentation order (split out so tests can inject failures)."""
    yield from container.decode(stream)


def iter_frames(
    path: str | os.PathLike[str],
    fps: float | None = None,
    start_frame: int = 0,
    max_frames: int | None = None,
) -> Iterator[np.ndarray]:
    """Yield a video's frames on a constant-rate time grid, one at a time.

    Frame ``i`` is the source frame shown at time ``t_i = i / fps`` (measured from the first frame): the
    source frame whose timestamp is nearest to ``t_i``, preferring the earlier (still showing) frame on a
    tie. For constant-frame-rate input at its own rate this is every frame exactly once; for variable
    frame rate input, or a different ``fps``, frames are duplicated or dropped by presentation time.
    The number of grid frames is ``round(duration_s * fps)`` (``VideoInfo.num_frames`` for the default
    rate). Frames are decoded one at a time (threaded decoder) and never all held in memory.

    Args:
        path: video file.
        fps: output frame rate in frames/s; None uses :attr:`VideoInfo.fps`.
        start_frame: index on the output grid of the first frame to yield (seeks, then decodes forward).
        max_frames: yield at most this many frames; None for all.

    Yields:
        RGB ``uint8`` arrays of shape ``(H, W, 3)``, rotated for display (``H, W`` = ``VideoInfo.height,
        VideoInfo.width``). A duplicated frame is yielded as a separate copy.

    Raises:
        MediaError: the file cannot be read or has no video stream (raised by the call itself), or fails
            to decode (raised during iteration; the message names the output frame index reached).
        ValueError: ``fps`` is not positive, or ``start_frame``/``max_frames`` are negative.
    """
    if start_frame < 0:
        raise ValueError(f"start_frame must be >= 0, got {start_frame}")
    if max_frames is not None and max_frames < 0:
        raise ValueError(f"max_frames must be >= 0 or None, got {max_frames}")
    probe = _probe(path)
    info = probe.info
    rate = probe.fps if fps is None else _to_fraction(fps)
    total = info.num_frames if fps is None else max(1, round(Fraction(info.duration_s) * rate))
    end = total if max_frames is None else min(total, start_frame + max_frames)
    return _iter_grid(probe, rate, start_frame, end)


FORWARD_GAP_S = 4.0
""":func:`frames_at` decodes on to a later chunk's first frame when it lies at most this far ahead (seconds)
of its decoder, instead of seeking: a seek decodes again from the keyframe before the frame (up to a GOP back,
10 s at x264's default), so a dub reading its footage forward decoded most frames several times (a forward
read, idle: 1080p with a 150-frame GOP 5.3 → 2.7 ms per frame, 512², 250-frame GOP, 1.8 → 0.5)."""


def frames_at(
    path: str | os.PathLike[str], indices: np.ndarray, fps: float, chunk: int = 48
) -> Iterator[np.ndarray]:
    """Yield the frames of ``path`` (on the ``fps`` grid) at ``indices`` in that order (any order, e.g. a
    ping-pong schedule, or a few frames spread over a long video), decoding the source frames spanned by
    ``chunk`` consecutive indices at a time and keeping only the ones asked for (memory: at most ``chunk``
    frames). One decoder runs on from chunk to chunk while they move forward (see :data:`FORWARD_GAP_S`);
    it seeks when a chunk starts behind it or far ahead.

    Raises:
        MediaError: the file ends before an index.
    """
    decoder, pos = None, 0  # the running decode and the grid index of the frame it yields next
    try:
        for c0 in range(0, len(indices), chunk):
            part = [int(i) for i in indices[c0 : c0 + chunk]]
            lo, hi = min(part), max(part)
            if decoder is None or not pos <= lo <= pos + FORWARD_GAP_S * fps:
                if decoder is not None:
                    decoder.close()
                decoder, pos = iter_frames(path, fps=fps, start_frame=lo), lo
            wanted, kept = set(part), {}
            while pos <= hi:
                frame = next(decoder, None)
                if frame is None:
                    raise MediaError(f"{path}: expected frames {lo}..{hi}, the file ended after {pos}")
                if pos in wanted:
                    kept[pos] = frame
                pos += 1
            for i in part:
                yield kept[i]
    finally:
        if decoder is not None:
            decoder.close()


def _iter_grid(probe: _Probe, rate: Fraction, start: int, end: int) -> Iterator[np.ndarray]:
    info = probe.info
    p = info.path
    i = start
    reformatter = VideoReformatter()  # one scaler context for all frames (faster than per-frame ones)

    def grid_time(index: int) -> Fraction:
        return Fraction(index) / rate

    def emit(slot: _Slot) -> np.ndarray:
        if slot.rgb is None:
            rgb = reformatter.reformat(slot.frame, format="rgb24").to_ndarray()
            slot.rgb = rotate_frame(rgb, info.rotation)
            slot.frame = None  # release the decoded picture
        if slot.emitted:
            return slot.rgb.copy()
        slot.emitted = True
        return slot.rgb

    with _open_input(p, "video") as container:
        stream = container.streams[probe.stream_index]
        stream.thread_type = "AUTO"
        if start > 0 and probe.first_pts is not None:
            # Land on a keyframe at or before the target; the half second of margin covers B-frame
            # reordering. Decoding then runs forward to the grid time.
            target = probe.first_pts + math.floor((grid_time(start) - Fraction(1, 2)) / probe.time_base)
            try:
                container.seek(max(target, probe.first_pts), stream=stream, backward=True)
            except _AV_ERRORS as exc:
                logger.debug("seek failed in %s (%s); decoding from the start", p, exc)
                container.seek(0)

        prev: _Slot | None = None
        decoded = 0
        frames = _decode(container, stream)
        while i < end:
            try:
                frame = next(frames, None)
            except _AV_ERRORS as exc:
                raise MediaError(
                    f"cannot read video '{p}': decoding failed at output frame {i} of {end} ({exc})"
                ) from exc
            if frame is None:
                break
            if frame.pts is not None and probe.first_pts is not None:
                t = (frame.pts - probe.first_pts) * probe.time_base
            else:
                t = Fraction(decoded) / probe.source_fps
            decoded += 1
            if prev is not None and t <= prev.time:
                logger.debug("skipping out-of-order frame at %s s in %s", float(t), p)
                continue
            cur = _Slot(t, frame)
            if prev is None:
                while i < end and grid_time(i) <= t:  # grid times before the first frame
                    yield emit(cur)
                    i += 1
            else:
                while i < end and grid_time(i) < t:
                    ti = grid_time(i)
                    yield emit(prev if ti - prev.time <= t - ti else cur)
                    i += 1
            prev = cur
        if prev is None and i < end:
            raise MediaError(f"cannot read video '{p}': no frames could be decoded")
        while i < end and prev is not None:  # the last frame stays on screen until the end
            yield emit(prev)
            i += 1
