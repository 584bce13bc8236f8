"""What the text says, and when: a transcript's phonemes aligned to its speech, for the mouth.

When the words are known (``nvp say`` made the speech from them; a dubbing studio has the script:
``nvp dub --transcript FILE``), every p, b and m is known too, and those close the lips in every language.
The text becomes phonemes with espeak-ng's grapheme-to-phoneme rules for its language (the copy that
ships inside the ``piper-tts`` wheel of the optional ``tts`` extra: 118 languages, no system package), the
phonemes are aligned to the audio by a CTC forced alignment (Viterbi) against the phoneme recogniser's
log-posteriors (:func:`nvp.audio_features.extract_features`, ``"phonemes"``: an IPA phone set of many
languages), and each aligned bilabial becomes a span of video frames where the lips close
(:func:`bilabial_weights`), each rounded vowel one where they round (:func:`rounded_weights`).
"""

from __future__ import annotations

import unicodedata
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from nvp.errors import NvpError

if TYPE_CHECKING:
    from nvp.audio_features import AudioFeatures

BILABIALS = frozenset({"p", "b", "m", "pʰ", "p͈", "ɓ", "ʙ"})
"""Recogniser labels (and espeak-ng phonemes) during which the lips are closed."""
CLOSE_BEFORE_S = 0.08
"""How long before a bilabial's aligned span the lips are already closed. The recogniser marks a stop by its
release (the burst after the closure); a p/b closure lasts about 50-100 ms, an m's is the nasal itself."""
CLOSE_AFTER_S = 0.02
"""How long after a bilabial's aligned span the lips stay closed."""
ROUND_BEFORE_S = 0.06
"""How long before a rounded vowel's aligned span the lips are already rounded: rounding is anticipated
(it spreads onto the consonants before the vowel, 100 ms and more in English and French), the recogniser
marks the vowel itself."""

IGNORED = frozenset("ˈˌ.,;:!?-—–'\"()[]…¡¿ \t\n")
"""espeak-ng output that is no phone: stress marks, punctuation, spaces."""
NON_PHONES = ("<pad>", "<sos>", "<eos>", "<unk>", " ", "%", ",", "<wb>", "<blank>")
"""Recogniser labels that are no phone: their probability counts as the CTC blank's."""


@dataclass(frozen=True)
class PhonemeAlignment:
    """Phonemes of a transcript and where the audio says them.

    Attributes:
        phonemes: ``(P,)`` the recogniser's labels, in the order spoken.
        start, end: ``(P,)`` float seconds from the audio's first sample: the span of posterior rows each
            phoneme was aligned to (``end`` exclusive).
    """

    phonemes: tuple[str, ...]
    start: np.ndarray
    end: np.ndarray


def text_phonemes(text: str, language: str = "en-us") -> list[str]:
    """espeak-ng's phonemes (IPA, one string per phone symbol, stress and punctuation dropped) of ``text`` in
    ``language`` (an espeak-ng voice name: ``en-us``, ``fr``, ``de``, ``cmn``, ``hi`` …).

    Raises:
        NvpError: no text, the ``tts`` extra not installed, or a language espeak-ng does not know.
    """
    if not text.strip():
        raise NvpError("expected a transcript with some words, found an empty text")
    try:
        from piper.phonemize_espeak import EspeakPhonemizer
    except ImportError as e:
        raise NvpError(
            "a transcript needs espeak-ng's phonemizer from the optional tts extra: pip install 'nvp[tts]'"
        ) from e
    try:
        sentences = EspeakPhonemizer().phonemize(language, text)
    except Exception as e:  # espeakbridge raises RuntimeError for an unknown voice
        raise NvpError(f"espeak-ng does not know the language {language!r} ({e})") from e
    return [p for sentence in sentences for p in sentence if p not in IGNORED]


def phoneme_tokens(phonemes: list[str], labels: tuple[str, ...]) -> list[int]:
    """Indices into the recogniser's ``labels`` of espeak-ng ``phonemes``: longest match first (``aɪ``,
    ``d͡ʒ`` are one label), symbols the recogniser has no label for (length marks, most diacritics) left
    out."""
    index = {unicodedata.normalize("NFD", name): i for i, name in enumerate(labels) if name not in NON_PHONES}
    longest = max(len(k) for k in index)
    chars = unicodedata.normalize("NFD", "".join(phonemes))
    tokens, i = [], 0
    while i < len(chars):
        for n in range(min(longest, len(chars) - i), 0, -1):
            if chars[i : i + n] in index:
                tokens.append(index[chars[i : i + n]])
                i += n
                break
        else:
            i += 1
    return tokens


def ctc_align(log_posteriors: np.ndarray, tokens: list[int], blank: np.ndarray) -> np.ndarray:
    """``(P, 2)`` int first and last posterior row of each token on the most probable CTC path that spells
    ``tokens`` (forced alignment, Viterbi).

    Args:
        log_posteriors: ``(N, C)`` per-row log-probabilities of the recogniser's classes.
        tokens: ``P`` class indices in the order spoken (repeats allowed: a blank must separate them).
        blank: ``(N,)`` per-row log-probability of "no phone here".
    Raises:
        NvpError: the audio has fewer rows than the path needs (the text is too long for it).
    """
    lp = np.asarray(log_posteriors, np.float64)
    n, p = len(lp), len(tokens)
    states = 2 * p + 1  # blank, token 0, blank, token 1, …, blank
    tok = np.asarray(tokens, int)
    needed = p + int(np.sum(tok[1:] == tok[:-1]))
    if p == 0 or n < needed:
        raise NvpError(f"the transcript has {p} phonemes, more than {n / 50:.1f} s of audio can say")
    emit = np.empty((n, states))
    emit[:, 0::2] = np.asarray(blank, np.float64)[:, None]
    emit[:, 1::2] = lp[:, tok]
    # a token may follow the token two states back (skipping the blank) unless both are the same
    skip = np.zeros(states, bool)
    skip[3::2] = tok[1:] != tok[:-1]
    score = np.full(states, -np.inf)
    score[:2] = emit[0, :2]
    back = np.zeros((n, states), np.int8)  # 0 stay, 1 from the previous state, 2 from two back
    for t in range(1, n):
        prev1 = np.concatenate([[-np.inf], score[:-1]])
        prev2 = np.where(skip, np.concatenate([[-np.inf, -np.inf], score[:-2]]), -np.inf)
        cand = np.stack([score, prev1, prev2])
        back[t] = np.argmax(cand, 0)
        score = cand[back[t], np.arange(states)] + emit[t]
    s = states - 1 if score[-1] >= score[-2] else states - 2
    path = np.empty(n, int)
    for t in range(n - 1, -1, -1):
        path[t] = s
        s -= int(back[t, s])
    spans = np.full((p, 2), -1)
    for t, st in enumerate(path):
        if st % 2:
            k = st // 2
            spans[k, 1] = t
            if spans[k, 0] < 0:
                spans[k, 0] = t
    return spans


def align_transcript(
    text: str,
    audio: np.ndarray,
    sample_rate: int,
    language: str = "en-us",
    posteriors: AudioFeatures | None = None,
) -> PhonemeAlignment:
    """The phonemes of ``text`` aligned to mono ``audio`` ``(S,)`` at ``sample_rate`` Hz; ``posteriors``:
    the recogniser's ``"phonemes"`` features of ``audio`` when already made (not made again)."""
    from nvp.audio_features import extract_features, phoneme_labels

    labels = phoneme_labels()
    tokens = phoneme_tokens(text_phonemes(text, language), labels)
    if not tokens:
        raise NvpError(f"the transcript {text[:40]!r} has no phoneme the recogniser knows")
    feats = extract_features(audio, sample_rate, kind="phonemes") if posteriors is None else posteriors
    lp = np.asarray(feats.values, np.float64)
    other = [i for i, name in enumerate(labels) if name in NON_PHONES]
    blank = np.logaddexp.reduce(lp[:, other], axis=1)
    spans = ctc_align(lp, tokens, blank)
    return PhonemeAlignment(
        phonemes=tuple(labels[i] for i in tokens),
        start=(spans[:, 0] / feats.rate).astype(np.float64),
        end=((spans[:, 1] + 1) / feats.rate).astype(np.float64),
    )


def phone_weights(
    alignment: PhonemeAlignment,
    fps: float,
    num_frames: int,
    phones: frozenset[str] | tuple[str, ...],
    before_s: float,
    after_s: float,
) -> np.ndarray:
    """``(T,)`` float32 in [0, 1]: 1 on the video frames (frame ``i`` covers ``[i, i + 1) / fps`` s) that
    overlap the aligned span of one of ``phones``, widened by ``before_s`` before and ``after_s`` after, and
    0 elsewhere."""
    w = np.zeros(num_frames, np.float32)
    for name, a, b in zip(alignment.phonemes, alignment.start, alignment.end, strict=True):
        if name in phones:
            first = int(np.floor(max(a - before_s, 0.0) * fps))
            last = int(np.ceil((b + after_s) * fps)) - 1
            w[max(first, 0) : min(last + 1, num_frames)] = 1.0
    return w


def bilabial_weights(alignment: PhonemeAlignment, fps: float, num_frames: int) -> np.ndarray:
    """:func:`phone_weights` of the bilabials' closures: their aligned spans widened by
    :data:`CLOSE_BEFORE_S` before and :data:`CLOSE_AFTER_S` after."""
    return phone_weights(alignment, fps, num_frames, BILABIALS, CLOSE_BEFORE_S, CLOSE_AFTER_S)


def rounded_weights(alignment: PhonemeAlignment, fps: float, num_frames: int) -> np.ndarray:
    """:func:`phone_weights` of the rounded vowels and glides (:data:`nvp.rounding.ROUNDED_PHONES`): their
    aligned spans from :data:`ROUND_BEFORE_S` before."""
    from nvp.rounding import ROUNDED_PHONES

    return phone_weights(alignment, fps, num_frames, ROUNDED_PHONES, ROUND_BEFORE_S, 0.0)
