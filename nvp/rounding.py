"""Lip rounding from the phoneme recogniser: how much the speech at each frame is a rounded vowel (o, u, y,
ø, w, ...), in any language, and the person's own rounding learned from their footage.

The opening model and the person map move the mouth mostly along its opening; a real mouth also narrows
on rounded vowels (test people, mouth-corner width on rounded / spread vowels: 0.955 English, 0.87-0.90
Cantonese, Italian, Portuguese; nvp's output 0.988 before this, docs/experiments/lip-sync.md). The
recogniser hears rounded vowels in every language it was trained on, so the same share drives every dub.
"""

from __future__ import annotations

from functools import cache

import numpy as np

ROUNDED_PHONES = (
    *("o", "oʊ", "u", "w", "wa", "we", "wi", "wʌ", "y", "ø", "œ", "ɒ", "ɔ", "ɔɪ", "ʊ", "ʉ", "ɵ", "ʏ"),
    *("õ", "ũ", "jo", "ju"),
)
"""Phones said with rounded lips, in the recogniser's IPA set (``phoneme_labels()``): the rounded vowels
and diphthongs that start rounded, w and the w-glides, j-glides into a rounded vowel."""


@cache
def rounded_classes() -> np.ndarray:
    """Indices of :data:`ROUNDED_PHONES` among the recogniser's classes."""
    from nvp.audio_features import phoneme_labels

    labels = phoneme_labels()
    return np.array([i for i, label in enumerate(labels) if label in ROUNDED_PHONES], np.int64)


def is_recogniser_output(windows: np.ndarray) -> bool:
    """Whether feature windows ``(T, W, D)`` have one feature per recogniser class (its log-posteriors)."""
    from nvp.audio_features import phoneme_labels

    return windows.shape[-1] == len(phoneme_labels())


def rounded_share(windows: np.ndarray) -> np.ndarray:
    """``(T,)`` the recogniser's probability of a rounded phone at each video frame, from the
    ``"phonemes"`` feature windows ``(T, W, D)`` (log-posteriors) the network reads: the mean over the two
    window samples at the frame (samples ``W // 2`` and ``W // 2 + 1``, 20 ms apart)."""
    windows = np.asarray(windows)
    if not is_recogniser_output(windows):
        raise ValueError(f"expected the recogniser's log-posteriors, found {windows.shape[-1]} features")
    c = windows.shape[1] // 2
    centre = windows[:, c : c + 2][..., rounded_classes()].astype(np.float64)
    return np.exp(centre).sum(-1).mean(1).astype(np.float32)


def rounding_direction(
    residual: np.ndarray, share: np.ndarray, keep_opening: np.ndarray | None = None
) -> tuple[np.ndarray, float] | None:
    """The person's rounding: ``(direction, mean_share)``, the expression change ``(K_exp,)`` per unit of
    rounded share and the share's mean, by least squares of what the rest of the style leaves unexplained
    on their speech frames, ``residual`` ``(N, K_exp)`` (tracked minus predicted), on ``share`` ``(N,)``.
    ``keep_opening`` ``(K_exp,)``: the inner-lip gap's linear weights; the part of the direction that would
    open or close the lips is removed (the opening model decides the opening). None when the share does not
    vary (no rounded vowel heard)."""
    centred = share - share.mean()
    spread = float(centred @ centred)
    if len(share) < 2 or spread < 1e-6:
        return None
    direction = centred @ residual / spread
    if keep_opening is not None:
        g = np.asarray(keep_opening, np.float64)
        direction = direction - (direction @ g) / (g @ g) * g
    return direction.astype(np.float32), float(share.mean())
