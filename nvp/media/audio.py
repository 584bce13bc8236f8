"""Audio with PyAV: reading any file's audio track (:func:`read_audio`) and the rates and layouts an mp4's
AAC track can store (:func:`storable_audio`)."""

from __future__ import annotations

import logging
import os
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
