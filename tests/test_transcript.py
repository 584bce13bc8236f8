"""A transcript's phonemes aligned to speech: grapheme-to-phoneme, CTC forced alignment, lip closures."""

from __future__ import annotations

import numpy as np
import pytest

from nvp.errors import NvpError
from nvp.transcript import (
    PhonemeAlignment,
    bilabial_weights,
    ctc_align,
    phoneme_tokens,
    rounded_weights,
    text_phonemes,
)

LABELS = ("<blank>", "a", "b", "m", "aɪ", "ɔ")


def _posteriors(path: list[int], classes: int = len(LABELS), peak: float = 0.9) -> np.ndarray:
    """``(N, C)`` log-posteriors whose most probable class per row is ``path[n]``."""
    p = np.full((len(path), classes), (1 - peak) / (classes - 1))
    p[np.arange(len(path)), path] = peak
    return np.log(p)


def test_forced_alignment_finds_each_phoneme_where_the_audio_says_it():
    # blank blank b b blank a a a blank blank m blank a blank  (b, a, m, a)
    path = [0, 0, 2, 2, 0, 1, 1, 1, 0, 0, 3, 0, 1, 0]
    lp = _posteriors(path)
    spans = ctc_align(lp, [2, 1, 3, 1], lp[:, 0])
    np.testing.assert_array_equal(spans, [[2, 3], [5, 7], [10, 10], [12, 12]])


def test_forced_alignment_follows_the_text_where_the_recogniser_hears_something_else():
    # the recogniser hears 'a' where the text says 'ɔ': the alignment still places 'ɔ' there, in order
    path = [0, 2, 0, 1, 1, 0, 3, 0]
    lp = _posteriors(path)
    spans = ctc_align(lp, [2, 5, 3], lp[:, 0])
    assert spans[0, 0] == 1 and spans[2, 0] == 6
    assert 2 <= spans[1, 0] <= spans[1, 1] <= 5


def test_a_repeated_phoneme_needs_a_blank_between_and_too_long_a_text_is_refused():
    lp = _posteriors([0, 3, 0, 3, 0])
    np.testing.assert_array_equal(ctc_align(lp, [3, 3], lp[:, 0]), [[1, 1], [3, 3]])
    with pytest.raises(NvpError, match="more than"):
        ctc_align(lp[:2], [3, 3], lp[:2, 0])


def test_phonemes_become_recogniser_labels_longest_first():
    # 'aɪ' is one label; the stress mark and the length mark are not labels here
    assert phoneme_tokens(["m", "a", "ɪ", "ː", "b", "ɔ"], LABELS) == [3, 4, 2, 5]


def test_bilabials_close_the_frames_around_them():
    al = PhonemeAlignment(
        ("a", "m", "a", "b"), np.array([0.0, 0.40, 0.5, 0.90]), np.array([0.1, 0.44, 0.6, 0.92])
    )
    w = bilabial_weights(al, 25.0, 30)
    # m: 0.40-0.44 s, closed from 0.32 s (frame 8) to 0.46 s (frame 11); b: 0.82-0.94 s, frames 20-23
    np.testing.assert_array_equal(np.flatnonzero(w), [8, 9, 10, 11, 20, 21, 22, 23])
    assert w.dtype == np.float32 and w.max() == 1


def test_rounded_vowels_round_the_frames_from_a_little_before_them():
    al = PhonemeAlignment(
        ("b", "u", "t", "ɔ", "i", "w"),
        np.array([0.0, 0.10, 0.30, 0.50, 0.70, 0.90]),
        np.array([0.08, 0.20, 0.36, 0.58, 0.80, 0.98]),
    )
    w = rounded_weights(al, 25.0, 30)
    # u 0.10-0.20 s, rounded from 0.04 s: frames 1-4; ɔ 0.50-0.58 from 0.44: 11-14; w 0.90-0.98: 21-24
    np.testing.assert_array_equal(np.flatnonzero(w), [1, 2, 3, 4, 11, 12, 13, 14, 21, 22, 23, 24])
    assert not np.any(bilabial_weights(al, 25.0, 30)[5:])  # b only: 0-0.1 s


def test_text_becomes_phonemes_in_several_languages():
    pytest.importorskip("piper")
    en = text_phonemes("Bob met my mum.", "en-us")
    fr = text_phonemes("Bonjour, mon père.", "fr")
    assert en.count("b") == 2 and en.count("m") == 4
    assert fr.count("m") == 1 and fr.count("p") == 1 and "ʁ" in fr
    with pytest.raises(NvpError, match="language"):
        text_phonemes("hello", "no-such-language")
    with pytest.raises(NvpError, match="empty"):
        text_phonemes("  ")


def test_a_transcript_aligns_to_synthetic_speech_and_closes_its_bilabials():
    """End to end on the shipped recogniser: the phonemes of the text come out in order, inside the audio."""
    pytest.importorskip("piper")
    from nvp.app.demo_voice import speech_script, synth_voice
    from nvp.transcript import align_transcript

    rng = np.random.default_rng(0)
    audio = synth_voice(speech_script(3.0, rng), 3.0, rng)
    al = align_transcript("mama baba", audio, 16000, "en-us")
    assert len(al.phonemes) >= 6 and set(al.phonemes) >= {"m", "b"}
    assert np.all(np.diff(al.start) > 0) and np.all(al.end > al.start) and al.end[-1] <= 3.0 + 0.02
    w = bilabial_weights(al, 25.0, 75)
    assert 4 <= np.count_nonzero(w) < 75


def test_dub_refuses_an_unreadable_transcript_or_one_for_several_files(tmp_path):
    from test_cli import assert_one_line_error, nvp

    wav = tmp_path / "a.wav"
    wav.write_bytes(b"")
    proc = nvp(
        "dub", wav, "--person", tmp_path, "--transcript", tmp_path / "none.txt", "-o", tmp_path / "o.mp4"
    )
    assert_one_line_error(proc, "cannot read the transcript")
    (tmp_path / "t.txt").write_text("hello")
    proc = nvp(
        "dub", wav, wav, "--person", tmp_path, "--transcript", tmp_path / "t.txt", "-o", tmp_path / "out"
    )
    assert_one_line_error(proc, "one audio file")
    assert not (tmp_path / "o.mp4").exists() and not (tmp_path / "out").exists()


def test_a_long_transcript_aligns_past_the_first_hundred_states():
    tokens = [1 + (i % 3) for i in range(150)]
    path = [x for tok in tokens for x in (0, tok, tok)]
    lp = _posteriors(path)
    spans = ctc_align(lp, tokens, lp[:, 0])
    np.testing.assert_array_equal(spans[:, 0], np.arange(150) * 3 + 1)
    np.testing.assert_array_equal(spans[:, 1], np.arange(150) * 3 + 2)
