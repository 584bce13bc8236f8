"""``nvp demo``: the shipped default run — a talking target made from a photo, fitted and dubbed."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from nvp.app.demo_clip import make_demo_clip
from nvp.app.demo_voice import AUDIO_RATE, speech_script, synth_voice
from nvp.errors import MediaError

log = logging.getLogger(__name__)


def _write_png(path: Path, rgb: np.ndarray) -> None:
    import cv2

    if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
        raise MediaError(f"cannot write image '{path}'")


def _label(rgb: np.ndarray, text: str) -> np.ndarray:
    """White caption on a dark band at the top of a copy of the frame."""
    import cv2

    out = rgb.copy()
    scale = max(out.shape[0] / 800.0, 0.35)
    (_, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    band = h + base + 8
    out[:band] = (out[:band] * 0.35).astype(np.uint8)
    cv2.putText(out, text, (6, 4 + h), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return out


DEMO_TEXT = (
    "Hello! I am a photograph that learned to talk. Everything you see was made on this computer, "
    "from a picture and a few words, without any network."
)


def _demo_speech(text: str | None, seconds: float) -> tuple[np.ndarray, int, str]:
    """What the demo person says: ``text`` with piper text to speech when it is installed, else ``seconds``
    of a synthetic voice."""
    from nvp.errors import NvpError
    from nvp.tts import synthesize

    if text:
        try:
            speech = synthesize(text)
            return speech.audio, speech.rate, f"text to speech ({speech.engine}): {text!r}"
        except NvpError as e:
            log.warning("%s; the demo speaks with a synthetic voice instead", e)
    rng = np.random.default_rng(1)
    return (
        synth_voice(speech_script(seconds, rng), seconds, rng),
        AUDIO_RATE,
        "synthetic voice (no TTS installed)",
    )


def _dub_stills(result, out_dir: Path) -> Path:
    """One PNG with three dubbed frames: the widest predicted mouth, a closed one and one in between."""
    from nvp.face_model import default_face_model
    from nvp.media import iter_frames

    model = default_face_model()
    gap = model.inner_lip_gap(np.zeros(model.num_id, np.float32), result.expression)
    picks = [int(np.argmax(gap)), int(np.argsort(gap)[len(gap) // 2]), int(np.argmin(gap))]
    frames = {}
    for i, frame in enumerate(iter_frames(result.output, max_frames=max(picks) + 1)):
        if i in picks:
            frames[i] = _label(frame, f"dub frame {i}: predicted opening {10 * gap[i]:.1f} mm")
    path = out_dir / "demo_dub_stills.png"
    _write_png(path, np.hstack([frames[i] for i in picks if i in frames]))
    return path


def run_demo(
    out_dir: str | Path,
    progress: bool = True,
    budget_minutes: float = 8.0,
    seconds: float = 20.0,
    text: str | None = DEMO_TEXT,
) -> str:
    """The shipped default: make a talking target from the astronaut photo, fit it, dub it.

    Writes ``demo_target.mp4`` (a ``seconds`` long synthetic clip), ``person/`` (the person bundle;
    renderer trained for ``budget_minutes`` with the cpu preset), ``demo_speech.wav`` and ``demo_dub.mp4``
    (the person saying ``text`` with piper text to speech when the ``tts`` extra is installed, a synthetic
    voice otherwise) and ``demo_dub_stills.png``.

    Returns:
        A short multi-line summary: where the files are and how long each step took.
    """
    from nvp.app.dub import dub
    from nvp.app.fit import FitConfig, fit
    from nvp.provenance import verify

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    target = out / "demo_target.mp4"
    clip = make_demo_clip(target, seconds=seconds, size=256) if not target.exists() else None
    t_clip = time.perf_counter() - t0
    bundle = fit(target, out / "person", FitConfig(preset="cpu", budget_minutes=budget_minutes), progress)
    t_fit = time.perf_counter() - t0 - t_clip
    import soundfile as sf

    audio, rate, what = _demo_speech(text, min(seconds, 8.0))
    sf.write(out / "demo_speech.wav", audio, rate)
    result = dub(out / "demo_speech.wav", bundle.root, out / "demo_dub.mp4", progress=progress)
    stills = _dub_stills(result, out)
    marked = verify(result.output).marked
    elapsed = time.perf_counter() - t0
    lines = [
        f"demo target: {target} (synthetic from skimage.data.astronaut"
        + (f", {clip.num_frames} frames, made in {t_clip:.0f} s)" if clip else ", reused)"),
        f"person:      {bundle.root} (fit in {t_fit / 60:.1f} min; nvp info {bundle.root})",
        f"speech:      {what}",
        f"dubbed:      {result.output} ({result.frames} frames for {result.audio_seconds:.1f} s of audio, "
        f"{result.frames / result.seconds:.1f} frames/s; synthetic-media mark: {'yes' if marked else 'NO'})",
        f"stills:      {stills}",
        f"total time:  {elapsed / 60:.1f} min",
    ]
    return "\n".join(lines)
