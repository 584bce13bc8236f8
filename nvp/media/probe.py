"""Probing media files with PyAV: a video's size, frame rate, rotation and streams (:func:`probe_video`),
and the helpers every reader shares (opening a file, its display rotation, exact frame rates)."""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

import av
import numpy as np

from nvp.errors import MediaError

logger = logging.getLogger(__name__)

# Errors that PyAV raises for unreadable files (FFmpegError also covers av's FileNotFoundError etc.).
_AV_ERRORS = (av.FFmpegError, OSError, EOFError)

# Timestamp jitter tolerated before a stream counts as variable frame rate: a frame interval may differ
# from the median interval by max(one time-base tick, this fraction of the median).
_VFR_TOLERANCE = 0.05


@dataclass(frozen=True)
class VideoInfo:
    """What :func:`probe_video` learned about a video file."""

    path: str
    """The path that was probed, as given."""
    width: int
    """Display width in pixels, i.e. after applying :attr:`rotation`."""
    height: int
    """Display height in pixels, i.e. after applying :attr:`rotation`."""
    fps: float
    """Average frame rate in frames/s; for variable frame rate video, the mean rate (frames / duration)."""
    num_frames: int
    """Number of frames on the constant-rate grid, ``round(duration_s * fps)``: what :func:`iter_frames`
    yields with the default ``fps``."""
    duration_s: float
    """Duration of the video stream in seconds, from the first frame's start to the last frame's end."""
    rotation: int
    """0, 90, 180 or 270: degrees clockwise that stored frames must be rotated by for display."""
    variable_frame_rate: bool
    """True if frame timestamps are irregular (variable frame rate or dropped frames)."""
    has_audio: bool
    """True if the file has an audio stream."""
    audio_sample_rate: int | None
    """Sample rate in Hz of the first audio stream, or None without audio."""
    codec: str
    """FFmpeg name of the video codec, e.g. ``"h264"``, ``"hevc"``, ``"mpeg4"``."""


@dataclass(frozen=True)
class _Probe:
    """VideoInfo plus the stream details that :func:`iter_frames` needs."""

    info: VideoInfo
    stream_index: int
    time_base: Fraction
    first_pts: int | None  # None if the stream has no timestamps
    fps: Fraction  # exact version of info.fps
    source_fps: Fraction  # nominal rate of the stored frames, used when frames carry no timestamps


# --------------------------------------------------------------------------------------------- helpers


def _to_fraction(fps: float | Fraction) -> Fraction:
    """Exact fraction for a frame rate given as a float (29.97 -> 2997/100, 30000/1001 -> 30000/1001)."""
    if isinstance(fps, Fraction):
        return fps
    if not math.isfinite(fps) or fps <= 0:
        raise ValueError(f"fps must be a positive finite number, got {fps!r}")
    return Fraction(fps).limit_denominator(100_000)


def _check_exists(path: str | os.PathLike[str], what: str) -> str:
    p = os.fspath(path)
    if not os.path.exists(p):
        raise MediaError(f"cannot read {what} '{p}': file does not exist")
    if os.path.isdir(p):
        raise MediaError(f"cannot read {what} '{p}': expected a media file, found a directory")
    return p


def _open_input(path: str, what: str) -> Any:
    try:
        return av.open(path, metadata_errors="replace")
    except _AV_ERRORS as exc:
        raise MediaError(f"cannot read {what} '{path}': not a readable media file ({exc})") from exc


def _stream_kinds(container: Any) -> str:
    kinds = [s.type for s in container.streams]
    return ", ".join(kinds) if kinds else "none"


def _video_stream(container: Any) -> Any | None:
    """The first real video stream (cover art in audio files is not video)."""
    for stream in container.streams.video:
        if not stream.disposition & av.stream.Disposition.attached_pic:
            return stream
    return None


def _normalize_rotation(degrees: float) -> int:
    """Round an angle to the nearest multiple of 90 and bring it into {0, 90, 180, 270}."""
    rounded = int(round(degrees / 90.0)) * 90 % 360
    if abs(((degrees - rounded) + 180) % 360 - 180) > 1:
        logger.warning("rotation of %.1f degrees is not a multiple of 90; using %d", degrees, rounded)
    return rounded


def rotate_frame(frame: np.ndarray, rotation: int) -> np.ndarray:
    """Rotate an image clockwise by ``rotation`` degrees (0, 90, 180 or 270).

    Args:
        frame: array of shape ``(H, W, ...)``.
        rotation: clockwise angle in degrees, as in :attr:`VideoInfo.rotation`.

    Returns:
        A C-contiguous array of shape ``(W, H, ...)`` for 90/270, ``(H, W, ...)`` otherwise. For
        ``rotation == 0`` the input is returned unchanged.
    """
    if rotation % 90:
        raise ValueError(f"rotation must be a multiple of 90 degrees, got {rotation}")
    k = (rotation // 90) % 4
    if k == 0:
        return frame
    # np.rot90 with positive k turns counter-clockwise, so negate for clockwise.
    return np.ascontiguousarray(np.rot90(frame, k=-k))


def _rotation_from_frame(frame: Any, stream: Any) -> int:
    """Clockwise display rotation from the frame's display matrix, else the legacy ``rotate`` tag."""
    ccw = frame.rotation  # av_display_rotation_get: counter-clockwise degrees, 0 without a matrix
    if ccw:
        return _normalize_rotation(-ccw)
    tag = stream.metadata.get("rotate")
    if tag:
        try:
            return _normalize_rotation(float(tag))  # the old "rotate" tag is clockwise already
        except ValueError:
            logger.warning("ignoring unparseable rotate tag %r", tag)
    return 0


def _scan_timestamps(container: Any, stream: Any) -> tuple[list[int], list[int], int]:
    """Demux (no decoding) the video stream: sorted presentation timestamps, their durations, and the
    number of packets (including packets without a timestamp)."""
    entries: list[tuple[int, int]] = []
    count = 0
    for packet in container.demux(stream):
        if packet.size == 0 and packet.pts is None:
            continue  # the flush packet demux() yields at the end
        if packet.is_discard:
            continue
        count += 1
        if packet.pts is not None:
            entries.append((packet.pts, packet.duration or 0))
    entries.sort()
    return [e[0] for e in entries], [e[1] for e in entries], count


def _is_variable(pts: list[int]) -> bool:
    if len(pts) < 3:
        return False
    diffs = np.diff(np.asarray(pts, dtype=np.int64))
    diffs = diffs[diffs > 0]
    if diffs.size < 2:
        return False
    median = float(np.median(diffs))
    tolerance = max(1.0, _VFR_TOLERANCE * median)
    return bool(np.any(np.abs(diffs - median) > tolerance))


def _probe(path: str | os.PathLike[str]) -> _Probe:
    p = _check_exists(path, "video")
    try:
        with _open_input(p, "video") as container:
            stream = _video_stream(container)
            if stream is None:
                raise MediaError(
                    f"cannot read video '{p}': no video stream (found streams: {_stream_kinds(container)})"
                )
            scan = _scan_timestamps(container, stream)
            index = stream.index
        # Second pass, first frame only: stored size and display matrix (PyAV exposes the matrix only on
        # decoded frames). Reopening is cheaper and more robust than seeking back.
        with _open_input(p, "video") as container:
            stream = container.streams[index]
            return _probe_stream(p, container, stream, scan)
    except _AV_ERRORS as exc:
        raise MediaError(f"cannot read video '{p}': corrupt or unsupported ({exc})") from exc


def _probe_stream(p: str, container: Any, stream: Any, scan: tuple[list[int], list[int], int]) -> _Probe:
    codec = stream.codec_context.name
    time_base = Fraction(stream.time_base) if stream.time_base else Fraction(1, 1_000_000)
    audio_streams = list(container.streams.audio)
    audio_rate = int(audio_streams[0].sample_rate) if audio_streams else None
    nominal = stream.guessed_rate or stream.average_rate or stream.base_rate
    average = stream.average_rate

    first = next(iter(container.decode(stream)), None)
    if first is None:
        raise MediaError(f"cannot read video '{p}': the video stream ({codec}) has no decodable frames")
    rotation = _rotation_from_frame(first, stream)
    stored_w, stored_h = first.width, first.height

    pts, durations, count = scan

    if pts:
        first_pts = pts[0]
        if len(pts) >= 2:
            positive = [d for d in np.diff(pts).tolist() if d > 0]
            typical = int(np.median(positive)) if positive else 0
        else:
            typical = 0
        last_duration = durations[-1] or typical
        if last_duration == 0 and nominal:
            last_duration = max(1, round(1 / (Fraction(nominal) * time_base)))
        duration = (pts[-1] + last_duration - first_pts) * time_base
        variable = _is_variable(pts)
        n_source = len(pts)
    else:
        # No timestamps at all (e.g. raw elementary streams): assume the nominal rate.
        first_pts = None
        if not nominal:
            raise MediaError(f"cannot read video '{p}': the video stream has neither timestamps nor a rate")
        duration = Fraction(count) / Fraction(nominal)
        variable = False
        n_source = count
    if duration <= 0 or n_source == 0:
        raise MediaError(f"cannot read video '{p}': the video stream has no frames")
    announced = int(stream.frames or 0)
    if announced > 1 and n_source < 0.97 * announced - 1:
        logger.warning(
            "'%s' holds %d video frames but its container announces %d: the file looks cut short; "
            "reading the %d that are there",
            p,
            n_source,
            announced,
            n_source,
        )

    mean_rate = Fraction(n_source) / duration
    fps = mean_rate.limit_denominator(100_000)
    for candidate in (average, nominal):  # prefer the exact rate the container states, if consistent
        if candidate and abs(float(candidate) - float(mean_rate)) <= 0.01 * float(mean_rate):
            fps = Fraction(candidate)
            break
    num_frames = max(1, round(duration * fps))

    width, height = (stored_h, stored_w) if rotation in (90, 270) else (stored_w, stored_h)
    info = VideoInfo(
        path=p,
        width=width,
        height=height,
        fps=float(fps),
        num_frames=num_frames,
        duration_s=float(duration),
        rotation=rotation,
        variable_frame_rate=variable,
        has_audio=bool(audio_streams),
        audio_sample_rate=audio_rate,
        codec=codec,
    )
    logger.debug("probed %s: %s", p, info)
    source_fps = Fraction(nominal) if nominal else fps
    return _Probe(info, stream.index, time_base, first_pts, fps, source_fps)


def probe_video(path: str | os.PathLike[str]) -> VideoInfo:
    """Read a video's size, frame rate, duration, rotation and audio presence.

    Only the first frame is decoded (for its display matrix); the rest is read at packet level, so this
    is fast even for long files.

    Args:
        path: video file (any container/codec FFmpeg can read).

    Returns:
        A :class:`VideoInfo`; ``width``/``height`` are the display size after rotation.

    Raises:
        MediaError: the file does not exist, is not a readable media file, is corrupt, or has no video
            stream.
    """
    return _probe(path).info


def audio_rate(path: str | os.PathLike[str]) -> int:
    """Sample rate in Hz of a file's first audio stream."""
    p = _check_exists(path, "audio")
    with _open_input(p, "audio") as container:
        if not container.streams.audio:
            raise MediaError(f"'{p}' has no audio stream (found streams: {_stream_kinds(container)})")
        s = container.streams.audio[0]
        return int(s.codec_context.sample_rate or s.rate)


def has_audio(path: str | os.PathLike[str]) -> bool:
    """True if the media file has at least one audio stream.

    Raises:
        MediaError: the file does not exist or is not a readable media file.
    """
    p = _check_exists(path, "media file")
    with _open_input(p, "media file") as container:
        return len(container.streams.audio) > 0
