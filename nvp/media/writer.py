"""Writing H.264/AAC MP4 files atomically with PyAV (:class:`VideoWriter`)."""

from __future__ import annotations

import logging
import os
import secrets
from collections.abc import Iterator
from fractions import Fraction
from pathlib import Path
from types import TracebackType

import av
import numpy as np
from av.video.reformatter import ColorRange, Colorspace, VideoReformatter

from nvp.artifact import DiskFullError, is_disk_full
from nvp.errors import MediaError
from nvp.media.audio import (
    AAC_RATES,
    AUDIO_LAYOUTS,
    AudioBlocks,
    aac_rate,
    storable_audio,
    storable_blocks,
    storable_channels,
)
from nvp.media.probe import (
    _AV_ERRORS,
    _to_fraction,
)

logger = logging.getLogger(__name__)

# Colour tagging of written video: BT.709, limited ("MPEG") range. AVCOL_* values are 1 for BT.709.
_AVCOL_BT709 = 1
_AVCOL_RANGE_MPEG = 1

# The AAC encoder consumes frames of exactly this many samples (the last one may be shorter).
_AAC_FRAME_SIZE = 1024

X264_SPEED = "me=dia:subme=1:partitions=i8x8,i4x4"
"""x264 settings on top of preset ``veryfast``: the diamond motion search, one sub-pixel refinement and
no inter partitions below 16x16 (issue 48). On 90 frames of a 1080p talking head (wav2lipgfpgan kim, crf
18, 2-core AMD EPYC under load, runs interleaved) the encoder and its RGB → YUV conversion took 17.5-20.4
→ 13.1-13.2 ms of CPU per frame, the file 0.69 → 0.71 MB, PSNR to the frames given 43.91 → 43.87 dB
(``superfast``: 15.5 ms, 1.57 MB; it also drops x264's macroblock tree, which is what keeps static
footage small)."""


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

    Video is H.264 (libx264, yuv420p, BT.709 tagged, preset ``veryfast`` with :data:`X264_SPEED`).
    yuv420p needs even dimensions: an odd ``width``/``height`` is padded to the next even number by
    repeating the last column/row, so the file is up to one pixel wider/taller than the frames given.

    Audio (``float`` in ``[-1, 1]``, shape ``(n,)`` mono or ``(n, channels)`` with 1 to 8 channels, at
    ``audio_rate`` Hz) is AAC-encoded, interleaved with the video as frames arrive, and trimmed or
    zero-padded to the video duration ``num_frames / fps``. ``audio_file``: instead of ``audio``, the
    audio track of that file, read block by block as the video reaches it (:class:`AudioBlocks`), never
    held whole: the same track as ``audio=read_audio(audio_file, None, mono=False)`` at its own rate.

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
        audio_file: str | os.PathLike[str] | None = None,
    ) -> None:
        if width <= 0 or height <= 0:
            raise ValueError(f"width and height must be positive, got {width}x{height}")
        if audio_rate <= 0:
            raise ValueError(f"audio_rate must be positive, got {audio_rate}")
        if audio_file is not None and (audio is not None or live):
            raise ValueError("give audio or audio_file, not both; a live writer's audio comes with add_audio")
        self._feed: Iterator[np.ndarray] | None = None  # audio_file's blocks, at the rate AAC stores
        self._source = None if audio_file is None else AudioBlocks(audio_file, None, mono=False)
        if self._source is not None:
            channels = storable_channels(self._source.channels)
            audio, audio_rate = np.zeros((0, channels), np.float32), aac_rate(self._source.rate)
            self._feed = storable_blocks(self._source, self._source.rate, self._source.channels)
        elif audio is not None and not live:
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
        # a live file's header waits for its first fragment (``delay_moov``, not ``empty_moov``): it then
        # holds the edit list that drops the AAC encoder's priming samples, as a whole file's does; with an
        # empty header the muxer moved every frame but the first by the priming delay instead (the first
        # lasted three frames at 30 fps and the file read as 29.07 fps)
        flags = "+frag_keyframe+delay_moov+default_base_moof" if live else "+faststart"
        options = (
            {"movflags": flags + "+use_metadata_tags"} if suffix.lower() in (".mp4", ".mov", ".m4v") else {}
        )
        x264 = {"crf": str(int(crf)), "preset": "veryfast", "x264-params": X264_SPEED}
        if live:
            x264.update({"tune": "zerolatency", "g": str(max(1, round(float(self.fps))))})
        try:
            self._container = av.open(self._tmp, "w", options=options)
        except _AV_ERRORS as exc:
            self._closed = True
            self._close_source()
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
        # wrapped, not copied (the scaler reads it at once; 1080p: 4.0 → 3.3 ms with the conversion below)
        rgb = av.VideoFrame.from_numpy_buffer(np.ascontiguousarray(frame), format="rgb24")
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

    def _read_audio(self, end: int) -> None:
        """Reads ``audio_file`` on until the track holds sample index ``end`` (or the file ends)."""
        more, available = [], self._audio_base + self._audio.shape[1]
        while self._feed is not None and available < end:
            block = next(self._feed, None)
            if block is None:
                self._feed = None
            else:
                more.append(block)
                available += len(block)
        if more:
            self.add_audio(np.concatenate(more))

    def _write_audio(self, end: int, final: bool) -> None:
        """Encode audio samples up to sample index ``end`` (zero-padding past the input's end)."""
        assert self._audio is not None and self._astream is not None
        self._read_audio(end)
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
        except MediaError:  # audio_file's decoding failed
            self.abort()
            raise
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
            self._write_audio(total, final=True)
            self._container.mux(self._astream.encode(None))
            rest = sum(len(block) for block in self._feed or ())  # audio_file past the video: counted only
            given = self._audio_base + self._audio.shape[1] + rest
            if abs(given - total) > self._audio_rate / self.fps:
                logger.warning(
                    "audio for '%s' is %.3f s but the video is %.3f s; %s to match",
                    self.path,
                    given / self._audio_rate,
                    total / self._audio_rate,
                    "trimmed" if given > total else "padded with silence",
                )
        self._container.close()
        if self._template is not None:
            self._template.close()
        self._close_source()

    def _close_source(self) -> None:
        if self._source is not None:
            self._source.close()

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
                self._close_source()
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
