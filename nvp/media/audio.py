"""Audio with PyAV: reading any file's audio track, whole (:func:`read_audio`) or block by block
(:class:`AudioBlocks`), and the rates and layouts an mp4's AAC track can store (:func:`storable_audio`,
:func:`storable_blocks`)."""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Iterator
from fractions import Fraction
from typing import Any

import av
import numpy as np

from nvp.errors import MediaError
from nvp.media.probe import (
    _AV_ERRORS,
    _check_exists,
    _open_input,
    _stream_kinds,
)

logger = logging.getLogger(__name__)


def read_audio(
    path: str | os.PathLike[str], sample_rate: int | None = 16000, mono: bool = True
) -> np.ndarray:
    """Decode the first audio stream of a file to mono (or its own channels) at ``sample_rate``.

    Works for any format FFmpeg reads (wav 16/24/32-bit, flac, mp3, m4a/aac, ogg, video files with an
    audio track), any input rate and channel count. Channels are averaged with equal weights (a stereo
    file with identical channels reads back at the same level). :class:`AudioBlocks` gives the same
    samples block by block.

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
    with _open_input(p, "audio") as container:
        stream = _audio_stream(container, p)
        if sample_rate is None:
            sample_rate = _own_rate(stream)
        stated = _stated_seconds(stream)
        try:
            for samples in _resampled(container.decode(stream), sample_rate):
                chunks.append(_mono(samples) if mono else samples)
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
    _check_numbers(audio, p, sample_rate)
    np.clip(audio, -1.0, 1.0, out=audio)
    return audio


class AudioBlocks:
    """The first audio stream of ``path`` decoded block by block: iterating yields ``float32`` blocks,
    ``(n,)`` (``mono``, or a mono stream) or ``(n, channels)``, at ``sample_rate`` Hz (None: the stream's
    own) — one after the other the samples :func:`read_audio` returns with the same arguments (its
    padding trimmed, values clipped), without ever holding the whole track. One difference: a stream
    whose channel layout changes mid-stream (rare) keeps its first layout, FFmpeg mixing the others to it
    (:func:`read_audio` keeps the narrower one's channels).

    ``channels``: per block (1 when ``mono``); ``source_rate``: the stream's own rate; ``stated_seconds``:
    its length as the container states it (None when it does not); after iterating, ``source_samples``: its
    length at that rate (``len(read_audio(path, None))``). Iterate once; the file closes at the end, or with
    :meth:`close` (or ``with``).

    Raises:
        MediaError: as :func:`read_audio` (samples that are not numbers: when the block holding them is
            reached).
    """

    def __init__(self, path: str | os.PathLike[str], sample_rate: int | None = 16000, mono: bool = True):
        if sample_rate is not None and sample_rate <= 0:
            raise ValueError(f"sample_rate must be positive, got {sample_rate}")
        self.path = _check_exists(path, "audio")
        self._container = _open_input(self.path, "audio")
        try:
            self._stream = _audio_stream(self._container, self.path)
            self.layout = self._stream.codec_context.layout.name
            source_channels = self._stream.codec_context.layout.nb_channels
        except BaseException:
            self.close()
            raise
        self.source_rate = _own_rate(self._stream)
        self.rate = self.source_rate if sample_rate is None else int(sample_rate)
        self.mono = mono
        self.channels = 1 if mono else source_channels
        if self.channels < 1:
            self.close()
            raise MediaError(f"cannot read audio from '{self.path}': its channel layout is not stated")
        self.source_samples = 0
        self.stated_seconds = _stated_seconds(self._stream)

    def __enter__(self) -> AudioBlocks:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._container.close()

    def __iter__(self) -> Iterator[np.ndarray]:
        stated = self.stated_seconds
        try:
            frames = self._counted(self._container.decode(self._stream), stated)
            chunks = _resampled(frames, self.rate, None if self.mono else self.layout)
            if self.mono:
                chunks = map(_mono, chunks)
            expected = None if stated is None else round(stated * self.rate)
            start = 0
            for block in _without_padding(chunks, expected, self.rate // 10):
                _check_numbers(block, self.path, self.rate, start)
                np.clip(block, -1.0, 1.0, out=block)
                start += len(block)
                yield block[:, 0] if block.shape[1] == 1 else block
        except _AV_ERRORS as exc:
            raise MediaError(f"cannot read audio from '{self.path}': decoding failed ({exc})") from exc
        finally:
            self.close()

    def _counted(self, frames: Iterable[Any], stated: float | None) -> Iterator[Any]:
        """``frames`` as they come, their samples counted in ``source_samples`` (without the padding
        :func:`read_audio` drops at the stream's own rate)."""
        for frame in frames:
            self.source_samples += frame.samples
            yield frame
        if stated is not None:
            expected = round(stated * self.source_rate)
            if expected < self.source_samples <= expected + self.source_rate // 10:
                self.source_samples = expected


def _audio_stream(container: Any, p: str) -> Any:
    """The first audio stream of an open file (MediaError when it has none)."""
    if not container.streams.audio:
        raise MediaError(
            f"cannot read audio from '{p}': no audio stream (found streams: {_stream_kinds(container)})"
        )
    return container.streams.audio[0]


def _own_rate(stream: Any) -> int:
    return int(stream.codec_context.sample_rate or stream.rate)


def _stated_seconds(stream: Any) -> float | None:
    """The stream's length as its container states it, if it does."""
    return float(stream.duration * stream.time_base) if stream.duration and stream.time_base else None


def _resampled(frames: Iterable[Any], rate: int, layout: str | None = None) -> Iterator[np.ndarray]:
    """Decoded ``frames`` as packed float32 ``(n, channels)`` arrays at ``rate`` (FFmpeg's resampler,
    started afresh when the input's format changes mid-stream), each frame's channels kept, or mixed to
    ``layout``. Packed: PyAV crashes reading 8 or more planes."""
    resampler, setup = None, None
    for frame in frames:
        key = (frame.format.name, frame.layout.name, frame.sample_rate)
        if resampler is None or key != setup:
            if resampler is not None:  # input format changed mid-stream: flush, start afresh
                yield from _packed(resampler.resample(None))
            # Resample keeping the channels (mono: averaged by the caller): FFmpeg's own downmix to mono
            # scales stereo by 1/sqrt(2) per channel (+3 dB for correlated channels, clipping).
            resampler = av.AudioResampler(format="flt", layout=layout or frame.layout.name, rate=rate)
            setup = key
        yield from _packed(resampler.resample(frame))
    if resampler is not None:
        yield from _packed(resampler.resample(None))


def _packed(frames: list[Any]) -> Iterator[np.ndarray]:
    for f in frames:
        yield f.to_ndarray().reshape(f.samples, -1)


def _mono(samples: np.ndarray) -> np.ndarray:
    """``(n, channels)`` → ``(n, 1)``, the channels averaged with equal weights."""
    return samples.mean(axis=1, dtype=np.float32, keepdims=True) if samples.shape[1] > 1 else samples


def _without_padding(chunks: Iterable[np.ndarray], expected: int | None, slack: int) -> Iterator[np.ndarray]:
    """``chunks`` as they come, except a tail of at most ``slack`` samples past the first ``expected``,
    which is dropped: AAC/MP3 decoders return the encoder's padding after the last real sample, and MP4
    states the real length (the start padding is already removed by FFmpeg). Holds at most ``slack``
    samples back."""
    seen, held, over = 0, [], 0
    for chunk in chunks:
        if expected is None or seen + len(chunk) <= expected:
            seen += len(chunk)
            yield chunk
            continue
        cut = max(0, expected - seen)
        if cut:
            yield chunk[:cut]
        seen += len(chunk)
        held.append(chunk[cut:])
        over += len(chunk) - cut
        if over > slack:  # more than padding: all of it is audio
            yield from held
            expected, held = None, []
    # what is still held is at most `slack` samples past `expected`: padding


def _check_numbers(audio: np.ndarray, p: str, rate: int, start: int | None = None) -> None:
    """MediaError when ``audio``, the whole track or a block from sample ``start`` on, holds samples that
    are not numbers."""
    bad = ~np.isfinite(audio)
    if bad.any():
        first = (start or 0) + int(np.flatnonzero(bad if bad.ndim == 1 else bad.any(1))[0])
        some = "samples are" if start is not None else f"{int(bad.sum())} samples are"
        raise MediaError(
            f"cannot use the audio of '{p}': {some} not numbers (NaN or infinite), "
            f"the first at {first / rate:.2f} s; export it again (e.g. as 16-bit wav)"
        )


AUDIO_LAYOUTS = {1: "mono", 2: "stereo", 3: "2.1", 4: "quad", 5: "5.0", 6: "5.1", 7: "6.1", 8: "7.1"}
"""AAC channel layouts the writer uses for 1 to 8 channels (FFmpeg's standard layouts)."""


AAC_RATES = (7350, 8000, 11025, 12000, 16000, 22050, 24000, 32000, 44100, 48000, 64000, 88200, 96000)
"""Sample rates (Hz) AAC can store; :class:`VideoWriter` resamples other rates (:func:`storable_audio`)."""
AAC_MAX_CHANNELS = 8
"""Most audio channels the writer stores (7.1); more are mixed to mono (their order is unknown)."""


def aac_rate(rate: int) -> int:
    """The AAC rate audio at ``rate`` Hz is stored at: ``rate`` itself when AAC can store it, else the
    nearest higher one (22000 → 22050, nothing of the signal lost), else the highest (96000)."""
    higher = [r for r in AAC_RATES if r >= rate]
    return higher[0] if higher else AAC_RATES[-1]


def storable_channels(channels: int) -> int:
    """The channels an mp4's AAC track stores of audio with ``channels``: all of them, or 1 (a mono mix)
    when there are more than :data:`AAC_MAX_CHANNELS`."""
    return channels if channels <= AAC_MAX_CHANNELS else 1


def storable_audio(audio: np.ndarray, rate: int) -> tuple[np.ndarray, int]:
    """``(audio, rate)`` as an mp4's AAC track can hold them: resampled to :func:`aac_rate` (FFmpeg's
    resampler) when AAC cannot store ``rate``, and mixed to mono when it has more channels than
    :data:`AAC_MAX_CHANNELS`; returned unchanged otherwise. ``audio``: ``(n,)`` or ``(n, channels)``
    float32. :func:`storable_blocks` does the same block by block."""
    a = np.asarray(audio, dtype=np.float32)
    channels = 1 if a.ndim == 1 else a.shape[1]
    kept = storable_channels(channels)
    if (aac_rate(int(rate)) == rate and kept == channels) or len(a) == 0:
        return (a.mean(1) if kept < channels else a), int(rate)
    seconds = (a[start : start + int(rate)] for start in range(0, len(a), int(rate)))
    parts = list(storable_blocks(seconds, int(rate), channels))
    b = np.concatenate(parts) if parts else np.zeros((0,) if kept == 1 else (0, kept), np.float32)
    if a.ndim == 2 and channels == 1:
        b = b.reshape(len(b), 1)  # (n, 1) stays (n, 1)
    return b.astype(np.float32, copy=False), aac_rate(int(rate))


def storable_blocks(blocks: Iterable[np.ndarray], rate: int, channels: int) -> Iterator[np.ndarray]:
    """Audio given in ``blocks`` (``(n,)`` or ``(n, channels)`` float32 at ``rate`` Hz, e.g. from
    :class:`AudioBlocks`) as an mp4's AAC track can hold it, block by block: what :func:`storable_audio`
    makes of the whole, mixed to :func:`storable_channels`, at :func:`aac_rate` (``(n,)`` blocks when
    mono)."""
    new, kept = aac_rate(rate), storable_channels(channels)
    if kept < channels:
        logger.warning("the audio has %d channels, more than an mp4 keeps: mixed to mono", channels)
    if new != rate:
        logger.info("audio at %d Hz, which AAC cannot store, resampled to %d Hz", rate, new)
    layout = AUDIO_LAYOUTS[kept]
    resampler = None if new == rate else av.AudioResampler(format="flt", layout=layout, rate=new)
    start = 0
    for block in blocks:
        block = block.mean(1) if kept < channels else block
        if resampler is None:
            yield block
            continue
        frame = av.AudioFrame.from_ndarray(np.ascontiguousarray(block).reshape(1, -1), "flt", layout)
        frame.sample_rate, frame.pts, frame.time_base = rate, start, Fraction(1, rate)
        start += len(block)
        yield from _storable_shape(resampler.resample(frame), kept)
    if resampler is not None:
        yield from _storable_shape(resampler.resample(None), kept)


def _storable_shape(frames: list[Any], channels: int) -> Iterator[np.ndarray]:
    for b in _packed(frames):
        yield b[:, 0] if channels == 1 else b
