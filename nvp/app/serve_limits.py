"""What ``nvp serve`` accepts: media types, container formats, sizes, durations, queue length, disk use
and connections at once (:class:`LimitedServer`).

Uploads are opened here, before any job sees them, with FFmpeg limited to the container formats nvp
supports (``format_whitelist``) and to plain files (``protocol_whitelist=file``): a playlist (HLS, concat,
...) uploaded as a video is refused without FFmpeg opening any file or URL it names. A file that passes
is read later by the job with nvp's ordinary media code; FFmpeg's format detection finds the same
container there (it depends only on the bytes, and uploads are stored under names without extension).
"""

from __future__ import annotations

import json
import shutil
import threading
from dataclasses import dataclass
from email.message import Message
from http import HTTPStatus
from http.server import ThreadingHTTPServer
from pathlib import Path

from nvp.app.serve_security import ApiError

VIDEO_TYPES = frozenset(
    {"video/mp4", "video/quicktime", "video/webm", "video/x-matroska", "video/x-msvideo", "video/avi"}
)
"""Media types a fit's video may declare (``Content-Type``)."""
AUDIO_TYPES = VIDEO_TYPES | frozenset(
    {
        "audio/wav", "audio/x-wav", "audio/wave", "audio/vnd.wave", "audio/mpeg", "audio/mp3", "audio/mp4",
        "audio/x-m4a", "audio/m4a", "audio/aac", "audio/flac", "audio/x-flac", "audio/ogg", "audio/webm",
        "audio/opus",
    }
)  # fmt: skip
"""Media types a dub's audio may declare (a video's sound is fine too)."""
VIDEO_FORMATS = ("mov,mp4,m4a,3gp,3g2,mj2", "matroska,webm", "avi")
"""FFmpeg demuxers a fit's video is opened with (their names as FFmpeg reports them)."""
AUDIO_FORMATS = (*VIDEO_FORMATS, "wav", "mp3", "flac", "ogg", "aac")
"""FFmpeg demuxers a dub's audio is opened with."""


@dataclass(frozen=True)
class Limits:
    """Bounds of what one ``nvp serve`` accepts (each refused with a 4xx answer that says the limit)."""

    max_upload_mb: float = 1024
    """Largest upload in MiB (413)."""
    max_video_minutes: float = 15
    """Longest video for a fit (1-3 minutes is what a fit needs) (413)."""
    max_audio_minutes: float = 10
    """Longest audio for a dub (413)."""
    max_text_chars: int = 2000
    """Longest text for ``say`` (400)."""
    max_queue: int = 8
    """Jobs queued or running at once; more are refused until one ends (429)."""
    min_free_mb: float = 1024
    """Free disk space an upload must leave on the data folder's disk (413)."""
    request_timeout_s: float = 30
    """A connection that sends or takes nothing for this long is closed (408 if a body was on its way)."""
    min_upload_kib_per_s: float = 64
    """An upload slower than this on average (after the first ``request_timeout_s``) is dropped (408)."""
    max_connections: int = 32
    """Connections served at once; more are answered 503 at once and closed."""
    max_json_bytes: int = 64 * 1024
    """Largest JSON body (``say``) (413)."""

    @property
    def max_upload(self) -> int:
        return int(self.max_upload_mb * 2**20)


def media_type(headers: Message, kind: str) -> str:
    """The declared media type of an upload of ``kind`` (``video``/``audio``); 415 when missing,
    unknown or encoded (a cross-site form can send only form and text types)."""
    raw = headers.get("Content-Type")
    if not raw:
        raise ApiError(
            HTTPStatus.UNSUPPORTED_MEDIA_TYPE,
            "declare the file's media type (Content-Type, e.g. video/mp4 or audio/wav)",
        )
    ctype = raw.split(";", 1)[0].strip().lower()
    allowed = VIDEO_TYPES if kind == "video" else AUDIO_TYPES
    if ctype not in allowed:
        raise ApiError(
            HTTPStatus.UNSUPPORTED_MEDIA_TYPE,
            f"expected a {kind} file ({', '.join(sorted(allowed))}), got {ctype[:60]!r}",
        )
    encoding = (headers.get("Content-Encoding") or "identity").strip().lower()
    if encoding != "identity":
        raise ApiError(HTTPStatus.UNSUPPORTED_MEDIA_TYPE, "send the file as it is (no Content-Encoding)")
    return ctype


def body_length(headers: Message, limit: int) -> int:
    """The declared body length: 411 without one (or with chunks), 400 if malformed, 413 over ``limit``."""
    if headers.get("Transfer-Encoding"):
        raise ApiError(HTTPStatus.LENGTH_REQUIRED, "send the body with a Content-Length (not in chunks)")
    values = headers.get_all("Content-Length") or []
    if not values:
        raise ApiError(HTTPStatus.LENGTH_REQUIRED, "send the file as the request body, with its length")
    if len(values) > 1 or not values[0].strip().isdigit() or len(values[0].strip()) > 15:
        raise ApiError(HTTPStatus.BAD_REQUEST, "the Content-Length header is not one number")
    size = int(values[0])
    if size == 0:
        raise ApiError(HTTPStatus.BAD_REQUEST, "the body is empty")
    if size > limit:
        raise ApiError(
            HTTPStatus.REQUEST_ENTITY_TOO_LARGE,
            f"the body is {_mib(size)}; the limit is {_mib(limit)}",
        )
    return size


def check_free_disk(folder: Path, size: int, limits: Limits) -> None:
    free = shutil.disk_usage(folder).free
    keep = int(limits.min_free_mb * 2**20)
    if free - size < keep:
        raise ApiError(
            HTTPStatus.REQUEST_ENTITY_TOO_LARGE,
            f"not enough disk space: {_mib(free)} free, and the server keeps {_mib(keep)} free",
        )


def _mib(n: float) -> str:
    return f"{n / 2**20:.1f} MB" if n < 10 * 2**20 else f"{n / 2**20:.0f} MB"


def inspect_media(path: Path, kind: str, limits: Limits) -> float:
    """Open an upload as a ``video`` (with sound, for a fit) or ``audio`` (for a dub) with FFmpeg limited
    to nvp's container formats and to plain files; decode its first frames. Returns its duration in s.

    Raises:
        ApiError: 422 when it is not such a file, 413 when it is longer than the limit.
    """
    import av

    formats = VIDEO_FORMATS if kind == "video" else AUDIO_FORMATS
    names = "mp4, mov, mkv, webm, avi" + ("" if kind == "video" else ", wav, mp3, m4a, flac, ogg")
    refuse = ApiError(HTTPStatus.UNPROCESSABLE_ENTITY, f"not a {kind} file nvp reads ({names})")
    try:
        with av.open(
            str(path),
            container_options={"format_whitelist": ",".join(formats), "protocol_whitelist": "file"},
            metadata_errors="replace",
        ) as container:
            if container.format.name not in formats:  # the whitelist already refuses; say it twice
                raise refuse
            cover = av.stream.Disposition.attached_pic
            video = [s for s in container.streams.video if not s.disposition & cover]
            audio = list(container.streams.audio)
            if kind == "video" and not video:
                raise ApiError(HTTPStatus.UNPROCESSABLE_ENTITY, "the file has no video")
            if not audio:
                raise ApiError(
                    HTTPStatus.UNPROCESSABLE_ENTITY,
                    "the video has no sound (a fit learns from the person's speech)"
                    if kind == "video"
                    else "the file has no sound",
                )
            duration = _duration(container)
            _decode_first_frames(container, (video[:1] if kind == "video" else []) + audio[:1])
    except (av.FFmpegError, OSError, EOFError, ValueError, IndexError) as e:
        raise refuse from e
    longest = 60 * (limits.max_video_minutes if kind == "video" else limits.max_audio_minutes)
    if duration is None or duration > longest:
        raise ApiError(
            HTTPStatus.REQUEST_ENTITY_TOO_LARGE,
            f"the {kind} is longer than the limit of {longest / 60:g} minutes"
            if duration
            else f"the {kind}'s length cannot be read",
        )
    return duration


def _decode_first_frames(container, streams: list, max_packets: int = 4000) -> None:
    """Decode packets until each of ``streams`` gave a frame; ApiError (422) if one never does."""
    waiting = {s.index: s.type for s in streams}
    for n, packet in enumerate(container.demux(*streams)):
        if n >= max_packets:
            break
        if packet.stream.index in waiting and packet.decode():
            del waiting[packet.stream.index]
            if not waiting:
                return
    if waiting:
        what = " and ".join(sorted(set(waiting.values())))
        raise ApiError(HTTPStatus.UNPROCESSABLE_ENTITY, f"the file's {what} cannot be decoded")


def _duration(container) -> float | None:
    """Seconds from the container, else its streams; None when neither says."""
    if container.duration and container.duration > 0:
        return container.duration / 1_000_000
    found = [float(s.duration * s.time_base) for s in container.streams if s.duration and s.time_base]
    return max(found) if found else None


class LimitedServer(ThreadingHTTPServer):
    """The HTTP server of ``nvp serve``: threads per connection, at most ``max_connections`` at once (more
    are answered 503 and closed)."""

    daemon_threads = True

    def __init__(self, address, handler, max_connections: int) -> None:
        self._slots = threading.BoundedSemaphore(max_connections)
        super().__init__(address, handler)

    def process_request(self, request, client_address) -> None:
        if not self._slots.acquire(blocking=False):
            body = json.dumps({"error": "the server is busy; try again"}).encode()
            head = (
                "HTTP/1.0 503 Service Unavailable\r\nContent-Type: application/json\r\n"
                f"Content-Length: {len(body)}\r\nRetry-After: 1\r\nConnection: close\r\n\r\n"
            )
            try:
                request.settimeout(1.0)
                request.sendall(head.encode() + body)
            except OSError:
                pass
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._slots.release()
            raise

    def process_request_thread(self, request, client_address) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()
