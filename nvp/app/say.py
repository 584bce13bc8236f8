"""``nvp say``: a fitted person says a text (offline text to speech, then :func:`nvp.app.dub.dub`)."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import soundfile as sf

from nvp import tts
from nvp.app.dub import DubResult, dub
from nvp.artifact import check_output_file
from nvp.bundle import check_output_place
from nvp.errors import NvpError


def say(
    text: str,
    person: Path,
    output: Path,
    wav: Path | None = None,
    voice: str | None = None,
    engine: str = "auto",
    slower: float = 1.0,
    device: str = "cpu",
    progress: bool = True,
    style: Path | None = None,
    gaze: str | Path = "footage",
) -> tuple[tts.Speech, DubResult]:
    """Speak ``text`` (``voice``, ``engine`` and ``slower`` as :func:`nvp.tts.synthesize` takes them) and
    dub ``person`` with it into ``output``; ``wav``: also keep the speech there. With piper, the text's own
    phonemes align the lips (the transcript of :func:`nvp.app.dub.dub`); ``gaze`` as the dub takes it.
    Returns the speech and the dub."""
    check_output_file(output)
    if wav is not None:
        check_output_file(wav)
    for out in (output, wav):  # never over an input, nor inside a person bundle
        if out is not None:
            check_output_place(out, (person, style))
    if wav is not None and Path(wav).resolve() == Path(output).resolve():
        raise NvpError(f"-o and --wav both name {output}; give the speech another name")
    speech = tts.synthesize(text, length_scale=slower, voice=voice, engine=engine)
    with tempfile.TemporaryDirectory() as tmp:
        made = Path(tmp) / "speech.wav"
        sf.write(made, speech.audio, speech.rate)
        r = dub(
            made,
            person,
            output,
            device=device,
            progress=progress,
            style=style,
            details={"speech": f"text to speech ({speech.engine}, voice {speech.voice})"},
            transcript=(text, speech.language) if tts.have_piper() else None,  # its phonemizer aligns
            gaze=gaze,
        )
        if wav is not None:
            shutil.copyfile(made, wav)
    return speech, r
