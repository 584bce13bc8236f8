"""Media I/O with PyAV (no system ffmpeg): probing, frame iteration, audio reading and MP4 writing.

Conventions used throughout:

* Video frames are RGB ``uint8`` arrays of shape ``(H, W, 3)``, already rotated for display.
* Audio is ``float32`` mono in ``[-1, 1]``, shape ``(num_samples,)``.
* Times are in seconds, measured from the first frame (video) or first sample (audio) of the stream.
* Frame rates may be fractional (29.97 = 30000/1001); they are handled as exact fractions internally.
"""

from __future__ import annotations

import logging
import math
import os
import secrets
from collections.abc import Iterator
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from types import TracebackType
from typing import Any

import av
import numpy as np
from av.video.reformatter import ColorRange, Colorspace, VideoReformatter

from nvp.artifact import DiskFullError, is_disk_full
from nvp.errors import MediaError

logger = logging.getLogger(__name__)

__all__ = [
    "VideoInfo",
    "VideoWriter",
    "has_audio",
    "iter_frames",
    "probe_video",
    "read_audio",
    "rotate_frame",
]

# Errors that PyAV raises for unreadable files (FFmpegError also covers av's FileNotFoundError etc.).
_AV_ERRORS = (av.FFmpegError, OSError, EOFError)

# Colour tagging of written video: BT.709, limited ("MPEG") range. AVCOL_* values are 1 for BT.709.
_AVCOL_BT709 = 1
_AVCOL_RANGE_MPEG = 1

# The AAC encoder consumes frames of exactly this many samples (the last one may be shorter).
_AAC_FRAME_SIZE = 1024

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


# ----------------------------------------------------------------------------------------- public API


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


def read_audio(
    path: str | os.PathLike[str], sample_rate: int | None = 16000, mono: bool = True
) -> np.ndarray:
    """Decode the first audio stream of a file to mono (or its own channels) at ``sample_rate``.

    Works for any format FFmpeg reads (wav 16/24/32-bit, flac, mp3, m4a/aac, ogg, video files with an
    audio track), any input rate and channel count. Channels are averaged with equal weights (a stereo
    file with identical channels reads back at the same level).

    Args:
        path: audio or video file.
        sample_rate: output rate in Hz; None keeps the stream's own rate (see :func:`audio_rate`).
        mono: average the channels (default); False keeps the channels as they are.

    Returns:
        ``float32`` array of shape ``(num_samples,)`` (mono) or ``(num_samples, channels)``, values in
        ``[-1, 1]``.

    Raises:
        MediaError: the file does not exist, is unreadable or corrupt, or has no audio stream.
    """
    if sample_rate is not None and sample_rate <= 0:
        raise ValueError(f"sample_rate must be positive, got {sample_rate}")
    p = _check_exists(path, "audio")
    chunks: list[np.ndarray] = []

    def collect(frames: list[Any]) -> None:
        for f in frames:  # packed float, (samples, channels): PyAV crashes reading 8 or more planes
            samples = f.to_ndarray().reshape(f.samples, -1)
            if mono and samples.shape[1] > 1:
                samples = samples.mean(axis=1, dtype=np.float32, keepdims=True)
            chunks.append(samples)

    with _open_input(p, "audio") as container:
        if not container.streams.audio:
            raise MediaError(
                f"cannot read audio from '{p}': no audio stream (found streams: {_stream_kinds(container)})"
            )
        stream = container.streams.audio[0]
        if sample_rate is None:
            sample_rate = int(stream.codec_context.sample_rate or stream.rate)
        stated = float(stream.duration * stream.time_base) if stream.duration and stream.time_base else None
        resampler = None
        setup: tuple[str, str, int] | None = None
        try:
            for frame in container.decode(stream):
                key = (frame.format.name, frame.layout.name, frame.sample_rate)
                if resampler is None or key != setup:
                    if resampler is not None:  # input format changed mid-stream: flush, start afresh
                        collect(resampler.resample(None))
                    # Resample keeping the channels and average them here: FFmpeg's own downmix to mono
                    # scales stereo by 1/sqrt(2) per channel (+3 dB for correlated channels, clipping).
                    resampler = av.AudioResampler(format="flt", layout=frame.layout.name, rate=sample_rate)
                    setup = key
                collect(resampler.resample(frame))
            if resampler is not None:
                collect(resampler.resample(None))
        except _AV_ERRORS as exc:
            raise MediaError(f"cannot read audio from '{p}': decoding failed ({exc})") from exc
    if not chunks:
        logger.warning("audio stream of '%s' decoded to no samples", p)
        return np.zeros(0, dtype=np.float32)
    width = min(c.shape[1] for c in chunks)  # a layout change mid-stream keeps the narrower one
    audio = np.concatenate([c[:, :width] for c in chunks]).astype(np.float32, copy=False)
    if mono or width == 1:
        audio = np.ascontiguousarray(audio[:, 0]) if width == 1 else audio.mean(1)
    if stated is not None:
        # AAC/MP3 decoders return the encoder's padding after the last real sample; MP4 states the real
        # length, so drop a small excess (the start padding is already removed by FFmpeg).
        expected = round(stated * sample_rate)
        if expected < len(audio) <= expected + sample_rate // 10:
            audio = audio[:expected]
    bad = ~np.isfinite(audio)
    if bad.any():
        first = int(np.flatnonzero(bad if bad.ndim == 1 else bad.any(1))[0])
        raise MediaError(
            f"cannot use the audio of '{p}': {int(bad.sum())} samples are not numbers (NaN or infinite), "
            f"the first at {first / sample_rate:.2f} s; export it again (e.g. as 16-bit wav)"
        )
    np.clip(audio, -1.0, 1.0, out=audio)
    return audio


AAC_RATES = (7350, 8000, 11025, 12000, 16000, 22050, 24000, 32000, 44100, 48000, 64000, 88200, 96000)
"""Sample rates (Hz) AAC can store; :class:`VideoWriter` resamples other rates (:func:`storable_audio`)."""
AAC_MAX_CHANNELS = 8
"""Most audio channels the writer stores (7.1); more are mixed to mono (their order is unknown)."""


def aac_rate(rate: int) -> int:
    """The AAC rate audio at ``rate`` Hz is stored at: ``rate`` itself when AAC can store it, else the
    nearest higher one (22000 → 22050, nothing of the signal lost), else the highest (96000)."""
    higher = [r for r in AAC_RATES if r >= rate]
    return higher[0] if higher else AAC_RATES[-1]


def storable_audio(audio: np.ndarray, rate: int) -> tuple[np.ndarray, int]:
    """``(audio, rate)`` as an mp4's AAC track can hold them: resampled to :func:`aac_rate` (FFmpeg's
    resampler) when AAC cannot store ``rate``, and mixed to mono when it has more channels than
    :data:`AAC_MAX_CHANNELS`; returned unchanged otherwise. ``audio``: ``(n,)`` or ``(n, channels)``
    float32."""
    a = np.asarray(audio, dtype=np.float32)
    if a.ndim == 2 and a.shape[1] > AAC_MAX_CHANNELS:
        logger.warning("the audio has %d channels, more than an mp4 keeps: mixed to mono", a.shape[1])
        a = a.mean(1)
    new = aac_rate(int(rate))
    if new == rate or len(a) == 0:
        return a, int(rate)
    logger.info("audio at %d Hz, which AAC cannot store, resampled to %d Hz", rate, new)
    channels = 1 if a.ndim == 1 else a.shape[1]
    layout = AUDIO_LAYOUTS[channels]
    resampler = av.AudioResampler(format="flt", layout=layout, rate=new)
    frames = a.reshape(len(a), channels)
    out: list[np.ndarray] = []
    step = int(rate)  # a second per frame
    for start in range(0, len(frames), step):
        chunk = np.ascontiguousarray(frames[start : start + step]).reshape(1, -1)
        frame = av.AudioFrame.from_ndarray(chunk, format="flt", layout=layout)
        frame.sample_rate, frame.pts, frame.time_base = int(rate), start, Fraction(1, int(rate))
        out += [f.to_ndarray().reshape(f.samples, channels) for f in resampler.resample(frame)]
    out += [f.to_ndarray().reshape(f.samples, channels) for f in resampler.resample(None)]
    b = np.concatenate(out) if out else np.zeros((0, channels), np.float32)
    return (b[:, 0] if a.ndim == 1 else b).astype(np.float32), new


# ------------------------------------------------------------------------------------------------ writer


class VideoWriter:
    """Write RGB frames (and optionally an audio track) to an H.264/AAC MP4, atomically.

    Use as a context manager::

        with VideoWriter("out.mp4", fps=25, width=512, height=512, audio=wav) as w:
            for frame in frames:
                w.write(frame)

    Everything is written to a hidden temporary file next to ``path`` (``.<name>.nvp-<pid>-<n>.tmp.mp4``),
    which is moved onto ``path`` only when :meth:`close` succeeds. If the ``with`` block raises (or
    :meth:`abort` is called) the temporary file is deleted and ``path`` is left untouched; the temporary
    file of a writer that was killed (its process gone) is removed by the next writer to the same path.
    A full disk is reported as :class:`nvp.artifact.DiskFullError` ("disk full while writing PATH").

    Video is H.264 (libx264, yuv420p, BT.709 tagged, preset ``veryfast``). yuv420p needs even
    dimensions: an odd ``width``/``height`` is padded to the next even number by repeating the last
    column/row, so the file is up to one pixel wider/taller than the frames given.

    Audio (``float`` in ``[-1, 1]``, shape ``(n,)`` mono or ``(n, channels)`` with 1 to 8 channels, at
    ``audio_rate`` Hz) is AAC-encoded, interleaved with the video as frames arrive, and trimmed or
    zero-padded to the video duration ``num_frames / fps``.

    ``metadata`` is stored as container tags (arbitrary keys are kept in MP4 via ``use_metadata_tags``)
    and can be read back with ``av.open(path).metadata``.

    ``live=True`` (``nvp live``) writes a fragmented MP4 straight to ``path``, a fragment per second
    (x264 ``zerolatency``: no frame is held back), so players can read the file while it grows; audio
    then arrives with :meth:`add_audio` (``audio`` gives only its channels, e.g. an empty ``(0,)`` array).
    :meth:`abort` then finishes the file instead of deleting it: what was streamed stays playable.

    ``template``: a file written by another writer of the same size and rate; then no frame is encoded,
    :meth:`append` copies such files' video one after the other (a long job's resumable parts).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        fps: float,
        width: int,
        height: int,
        audio: np.ndarray | None = None,
        audio_rate: int = 16000,
        crf: int = 18,
        metadata: dict[str, str] | None = None,
        live: bool = False,
        template: str | os.PathLike[str] | None = None,
    ) -> None:
        if width <= 0 or height <= 0:
            raise ValueError(f"width and height must be positive, got {width}x{height}")
        if audio_rate <= 0:
            raise ValueError(f"audio_rate must be positive, got {audio_rate}")
        if audio is not None and not live:
            audio, audio_rate = storable_audio(audio, audio_rate)
        elif audio is not None and aac_rate(audio_rate) != audio_rate:
            raise MediaError(
                f"cannot write video '{path}': AAC cannot store audio at {audio_rate} Hz "
                f"(it stores {', '.join(map(str, AAC_RATES))} Hz)"
            )
        self.path = os.fspath(path)
        self.fps = _to_fraction(fps)
        self.width = int(width)
        self.height = int(height)
        self.num_frames = 0
        self._pad_w = self.width % 2
        self._pad_h = self.height % 2
        self._audio = _prepare_audio(audio) if audio is not None else None
        self._audio_rate = int(audio_rate)
        self._audio_pos = 0  # samples sent to the encoder so far
        self._audio_base = 0  # stream index of self._audio's first held sample (add_audio drops sent ones)
        self._closed = False
        self._reformatter = VideoReformatter()
        self.live = live
        self._template = None

        target = Path(self.path)
        suffix = target.suffix or ".mp4"
        _remove_stale_temporaries(target, suffix)
        self._tmp = (
            self.path
            if live
            else str(target.with_name(f".{target.stem}.nvp-{os.getpid()}-{secrets.token_hex(4)}.tmp{suffix}"))
        )
        flags = "+frag_keyframe+empty_moov+default_base_moof" if live else "+faststart"
        options = (
            {"movflags": flags + "+use_metadata_tags"} if suffix.lower() in (".mp4", ".mov", ".m4v") else {}
        )
        x264 = {"crf": str(int(crf)), "preset": "veryfast"}
        if live:
            x264.update({"tune": "zerolatency", "g": str(max(1, round(float(self.fps))))})
        try:
            self._container = av.open(self._tmp, "w", options=options)
        except _AV_ERRORS as exc:
            self._closed = True
            raise MediaError(f"cannot write video '{self.path}': {exc}") from exc
        try:
            for key, value in (metadata or {}).items():
                self._container.metadata[str(key)] = str(value)
            if template is None:
                vs = self._container.add_stream("libx264", rate=self.fps, options=x264)
                vs.width = self.width + self._pad_w
                vs.height = self.height + self._pad_h
                vs.pix_fmt = "yuv420p"
                cc = vs.codec_context
                cc.time_base = 1 / self.fps
                cc.colorspace = _AVCOL_BT709
                cc.color_primaries = _AVCOL_BT709
                cc.color_trc = _AVCOL_BT709
                cc.color_range = _AVCOL_RANGE_MPEG
            else:  # parts encoded beforehand are copied (:meth:`append`), with the template's parameters
                self._template = av.open(os.fspath(template))
                vs = self._container.add_stream_from_template(self._template.streams.video[0])
            self._vstream = vs
            self._astream = None
            if self._audio is not None:
                channels = self._audio.shape[0]
                layout = AUDIO_LAYOUTS[channels]
                self._astream = self._container.add_stream("aac", rate=self._audio_rate, layout=layout)
                self._astream.bit_rate = 64000 * channels
                self._astream.codec_context.time_base = Fraction(1, self._audio_rate)
        except _AV_ERRORS as exc:
            self.abort()
            raise MediaError(f"cannot write video '{self.path}': {exc}") from exc
        except BaseException:
            self.abort()
            raise

    # -- context manager

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def __del__(self) -> None:  # never leave a stray temporary file behind
        try:
            if not getattr(self, "_closed", True):
                self.abort()
        except Exception:  # best effort at garbage collection
            pass

    # -- writing

    def write(self, frame: np.ndarray) -> None:
        """Append one frame.

        Args:
            frame: RGB ``uint8`` array of shape ``(height, width, 3)``.

        Raises:
            ValueError: wrong shape or dtype, or the writer is closed.
            MediaError: the encoder or muxer failed.
        """
        if self._closed or self._template is not None:
            raise ValueError(f"VideoWriter for '{self.path}' is closed or copies parts (append)")
        expected = (self.height, self.width, 3)
        if not isinstance(frame, np.ndarray) or frame.shape != expected:
            found = frame.shape if isinstance(frame, np.ndarray) else type(frame).__name__
            raise ValueError(f"frame shape mismatch: expected {expected}, found {found}")
        if frame.dtype != np.uint8:
            raise ValueError(f"frame dtype mismatch: expected uint8, found {frame.dtype}")
        if self._pad_w or self._pad_h:
            frame = np.pad(frame, ((0, self._pad_h), (0, self._pad_w), (0, 0)), mode="edge")
        rgb = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")
        yuv = self._reformatter.reformat(
            rgb, format="yuv420p", dst_colorspace=Colorspace.ITU709, dst_color_range=ColorRange.MPEG
        )
        yuv.pts = self.num_frames
        yuv.time_base = self._vstream.codec_context.time_base
        try:
            self._container.mux(self._vstream.encode(yuv))
            self.num_frames += 1
            if self._astream is not None:
                end = int(Fraction(self.num_frames * self._audio_rate) / self.fps)
                self._write_audio(end, final=False)
        except _AV_ERRORS as exc:
            self._raise_write_error(exc, f"encoding frame {self.num_frames} failed")

    def append(self, part: str | os.PathLike[str]) -> None:
        """Append the video of ``part``, a file another writer made with the same size and rate (the
        writer's ``template`` is one of them), without encoding it again: its packets are copied, their
        times moved to follow the frames written so far. The audio is encoded alongside as with
        :meth:`write`."""
        if self._closed or self._template is None:
            raise ValueError(f"VideoWriter for '{self.path}' is closed or encodes frames (write)")
        try:
            with av.open(os.fspath(part)) as src:
                stream = src.streams.video[0]
                packets = [pk for pk in src.demux(stream) if pk.size > 0]
                if not packets:
                    raise MediaError(f"cannot append '{part}' to '{self.path}': it holds no frames")
                ticks = Fraction(1) / (self.fps * stream.time_base)  # per frame, in the part's time base
                shift = round(self.num_frames * ticks) - min(pk.pts for pk in packets)
                for pk in packets:
                    pk.pts += shift
                    if pk.dts is not None:
                        pk.dts += shift
                    pk.stream = self._vstream
                    self._container.mux(pk)
            self.num_frames += len(packets)
            if self._astream is not None:
                self._write_audio(int(Fraction(self.num_frames * self._audio_rate) / self.fps), final=False)
        except _AV_ERRORS as exc:
            self._raise_write_error(exc, f"copying {part} failed")

    def add_audio(self, samples: np.ndarray) -> None:
        """Append audio (``(n,)`` or ``(n, channels)``, the channels given at creation) to the track; it is
        encoded as the video reaches it."""
        if self._audio is None:
            raise ValueError("this writer has no audio track")
        more = _prepare_audio(samples)
        if more.shape[0] != self._audio.shape[0]:
            raise ValueError(f"expected {self._audio.shape[0]} audio channels, found {more.shape[0]}")
        self._audio = np.concatenate([self._audio[:, self._audio_pos - self._audio_base :], more], 1)
        self._audio_base = self._audio_pos

    def _write_audio(self, end: int, final: bool) -> None:
        """Encode audio samples up to sample index ``end`` (zero-padding past the input's end)."""
        assert self._audio is not None and self._astream is not None
        channels, held = self._audio.shape
        available = self._audio_base + held  # stream index just past the last sample given
        layout = AUDIO_LAYOUTS[channels]
        while self._audio_pos < end:
            n = min(_AAC_FRAME_SIZE, end - self._audio_pos)
            if n < _AAC_FRAME_SIZE and not final:
                break
            chunk = np.zeros((channels, n), dtype=np.float32)
            stop = min(available, self._audio_pos + n)
            if stop > self._audio_pos:
                b = self._audio_base
                chunk[:, : stop - self._audio_pos] = self._audio[:, self._audio_pos - b : stop - b]
            packed = np.ascontiguousarray(chunk.T).reshape(1, -1)  # the encoder's resampler makes planes
            af = av.AudioFrame.from_ndarray(packed, format="flt", layout=layout)
            af.sample_rate = self._audio_rate
            af.pts = self._audio_pos
            af.time_base = Fraction(1, self._audio_rate)
            self._container.mux(self._astream.encode(af))
            self._audio_pos += n

    def close(self) -> None:
        """Flush the encoders, finish the file and move it onto ``path``. Idempotent.

        Raises:
            MediaError: no frames were written, or finishing the file failed (``path`` is then untouched).
        """
        if self._closed:
            return
        if self.num_frames == 0:
            self.abort()
            raise MediaError(f"cannot write video '{self.path}': no frames were written")
        try:
            self._finish()
            self._closed = True
            if not self.live:
                os.replace(self._tmp, self.path)
        except (*_AV_ERRORS, ValueError, OSError) as exc:
            self.abort()
            self._raise_write_error(exc, "finishing the file failed")
        logger.debug("wrote %s: %d frames at %s fps", self.path, self.num_frames, self.fps)

    def _finish(self) -> None:
        """Flush the encoders (audio trimmed or padded to the video's length) and close the container."""
        if self._template is None:
            self._container.mux(self._vstream.encode(None))
        if self._astream is not None and self._audio is not None:
            total = round(Fraction(self.num_frames * self._audio_rate) / self.fps)
            given = self._audio_base + self._audio.shape[1]
            if abs(given - total) > self._audio_rate / self.fps:
                logger.warning(
                    "audio for '%s' is %.3f s but the video is %.3f s; %s to match",
                    self.path,
                    given / self._audio_rate,
                    total / self._audio_rate,
                    "trimmed" if given > total else "padded with silence",
                )
            self._write_audio(total, final=True)
            self._container.mux(self._astream.encode(None))
        self._container.close()
        if self._template is not None:
            self._template.close()

    def _raise_write_error(self, exc: BaseException, what: str) -> None:
        if is_disk_full(exc):
            self.abort()
            raise DiskFullError(f"disk full while writing {self.path}") from exc
        raise MediaError(f"cannot write video '{self.path}': {what} ({exc})") from exc

    def abort(self) -> None:
        """Discard everything written so far: close and delete the temporary file; ``path`` is untouched.
        A live writer finishes its file instead (what was streamed stays playable)."""
        if self.live and self.num_frames > 0:
            if not self._closed:
                self._closed = True
                try:
                    self._finish()
                except Exception:  # keep whatever fragments made it to disk
                    logger.debug("error while finishing live file %s", self.path, exc_info=True)
            return
        if not self._closed:
            self._closed = True
            try:
                self._container.close()
                if self._template is not None:
                    self._template.close()
            except Exception:  # the file is deleted anyway
                logger.debug("error while closing aborted writer for %s", self.path, exc_info=True)
        try:
            os.remove(self._tmp)
        except FileNotFoundError:
            pass
        except OSError:
            logger.warning("could not delete temporary file %s", self._tmp, exc_info=True)


AUDIO_LAYOUTS = {1: "mono", 2: "stereo", 3: "2.1", 4: "quad", 5: "5.0", 6: "5.1", 7: "6.1", 8: "7.1"}
"""AAC channel layouts the writer uses for 1 to 8 channels (FFmpeg's standard layouts)."""


def _remove_stale_temporaries(target: Path, suffix: str) -> None:
    """Delete ``.<name>.nvp-<pid>-*.tmp<suffix>`` files beside ``target`` whose writer process is gone."""
    for tmp in target.parent.glob(f".{target.stem}.nvp-*.tmp{suffix}"):
        try:
            pid = int(tmp.name.split(".nvp-", 1)[1].split("-", 1)[0])
            os.kill(pid, 0)
        except ProcessLookupError:
            tmp.unlink(missing_ok=True)
        except (ValueError, IndexError, PermissionError):
            continue


def _prepare_audio(audio: np.ndarray) -> np.ndarray:
    """Writer audio as float32 ``(channels, samples)`` in [-1, 1]."""
    a = np.asarray(audio)
    if a.ndim == 1:
        a = a[None, :]
    elif a.ndim == 2 and a.shape[1] in AUDIO_LAYOUTS:
        a = a.T
    else:
        raise ValueError(f"audio shape mismatch: expected (n,) or (n, 1..8 channels), found {a.shape}")
    if np.issubdtype(a.dtype, np.integer):
        a = a.astype(np.float32) / float(np.iinfo(a.dtype).max)
    return np.ascontiguousarray(np.clip(a.astype(np.float32, copy=False), -1.0, 1.0))
