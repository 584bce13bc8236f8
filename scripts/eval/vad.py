"""Voice activity quality and speed: Silero (``nvp.vad``) against the old loudness gate.

    python -m scripts.eval.vad [--out out/eval_vad] [--clips N]

1. Sounds that are not speech, made here: silence, room tone, white and pink noise at three levels,
   music-like signals (a piano-like melody, sustained chords with vibrato, a drum loop, beeps, a melody over
   a drum loop). Per sound: whether the file counts as speech (``speech_activity``) and the fraction of
   video frames with voice activity >= 0.5 (the mouth would move). Both should be 0.
2. Real speech (``../shared/data/audio``, 87 clips in many languages, singing and TTS) with two 0.6 s
   pauses cut in at 1/3 and 2/3 of the clip, clean and with white noise (or the melody) mixed in at 10
   and 0 dB SNR (noise level relative to the speech's active level, the 20 ms blocks within 30 dB of its
   loud end; the noise runs through the pauses too). Per condition: clips called speech, frames of the
   pauses' core (from 0.2 s after the cut to the pause's end less the activity's lead) with activity
   >= 0.5, time from the cut until the activity is below 0.05 (closed mouth), and the fraction of speech
   frames with activity >= 0.5 (natural pauses inside the clips keep this below 1).
3. Speed of ``speech_probability`` on a 10-minute file, single run after a warm-up.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from nvp.app.report import markdown_table
from nvp.media import read_audio
from nvp.vad import (
    VOICE_LEAD_S,
    energy_voice_activity,
    rms_envelope_db,
    speech_activity,
    speech_probability,
    voice_activity,
)
from scripts.common import SHARED

SR = 16000
FPS = 25.0
GAP_S = 0.6
CLOSE_BY_S = 0.2


def energy_speech_activity(audio: np.ndarray, sr: int = SR) -> bool:
    """The old file-level test: at least 0.2 s of 20 ms blocks above -45 dBFS."""
    env = rms_envelope_db(audio, sr, 0.02)
    return int(np.count_nonzero(env > -45.0)) >= min(10, len(env))


METHODS = {
    "energy gate": (energy_speech_activity, energy_voice_activity),
    "silero": (speech_activity, voice_activity),
}


# ------------------------------------------------------------------------------ sounds made here


def _note(freq: float, dur: float, rng: np.random.Generator, partials: int = 6, decay: float = 3.0):
    t = np.arange(int(dur * SR)) / SR
    y = sum((0.6**k) * np.sin(2 * np.pi * freq * (k + 1) * t + rng.uniform(0, 6.28)) for k in range(partials))
    return y * np.exp(-decay * t) * np.minimum(1.0, t / 0.005)


def melody(seconds: float, rng: np.random.Generator) -> np.ndarray:
    """Piano-like notes of a pentatonic scale, 0.15-0.5 s each."""
    out, scale = [], 220.0 * 2 ** (np.array([0, 2, 4, 7, 9, 12, 14, 16]) / 12)
    while sum(len(x) for x in out) < seconds * SR:
        out.append(_note(float(rng.choice(scale)), float(rng.choice([0.15, 0.25, 0.5])), rng))
    return np.concatenate(out)[: int(seconds * SR)]


def chords(seconds: float, rng: np.random.Generator) -> np.ndarray:
    """Sustained three-note chords with 5 Hz vibrato, changing every second."""
    t = np.arange(int(seconds * SR)) / SR
    y = np.zeros_like(t)
    roots = 110.0 * 2 ** (rng.integers(0, 12, int(np.ceil(seconds))) / 12)
    for i, root in enumerate(roots):
        sel = (t >= i) & (t < i + 1)
        for ratio in (1.0, 1.26, 1.5):
            f = root * ratio * (1 + 0.006 * np.sin(2 * np.pi * 5 * t[sel]))
            phase = 2 * np.pi * np.cumsum(f) / SR
            y[sel] += sum(0.5**k * np.sin((k + 1) * phase) for k in range(4))
    return y


def drums(seconds: float, rng: np.random.Generator) -> np.ndarray:
    """A 120 bpm loop: kick (falling sine) on the beat, hi-hat noise on the off-beat."""
    y = np.zeros(int(seconds * SR))
    beat = SR // 2
    t = np.arange(beat // 2) / SR
    kick = np.sin(2 * np.pi * np.cumsum(150 * np.exp(-t * 20) + 40) / SR) * np.exp(-t * 12)
    hat = rng.standard_normal(len(t)) * np.exp(-t * 60) * 0.3
    for s in range(0, len(y) - beat, beat):
        y[s : s + len(kick)] += kick
        y[s + beat // 2 : s + beat // 2 + len(hat)] += hat
    return y


def beeps(seconds: float, rng: np.random.Generator) -> np.ndarray:
    """1 kHz beeps, 0.2 s on and 0.3 s off."""
    t = np.arange(int(seconds * SR)) / SR
    return np.sin(2 * np.pi * 1000 * t) * ((t % 0.5) < 0.2)


def pink(n: int, rng: np.random.Generator) -> np.ndarray:
    spec = np.fft.rfft(rng.standard_normal(n))
    spec /= np.sqrt(np.maximum(np.arange(len(spec)), 1))
    return np.fft.irfft(spec, n)


def at_level(x: np.ndarray, dbfs: float) -> np.ndarray:
    """``x`` scaled to an RMS level of ``dbfs`` (0 dBFS = RMS 1), as float32."""
    return np.clip(x * 10 ** (dbfs / 20) / (np.sqrt(np.mean(x**2)) + 1e-12), -1, 1).astype(np.float32)


def non_speech(seconds: float = 6.0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    n = int(seconds * SR)
    out = {"digital silence": np.zeros(n, np.float32), "room tone -70 dBFS": at_level(pink(n, rng), -70)}
    for lvl in (-40, -25, -10):
        out[f"white noise {lvl} dBFS"] = at_level(rng.standard_normal(n), lvl)
        out[f"pink noise {lvl} dBFS"] = at_level(pink(n, rng), lvl)
    for name, fn in (("melody", melody), ("chords", chords), ("drums", drums), ("beeps", beeps)):
        out[f"{name} -20 dBFS"] = at_level(fn(seconds, rng), -20)
    out["melody + drums -20 dBFS"] = at_level(melody(seconds, rng) + 0.5 * drums(seconds, rng), -20)
    return out


# --------------------------------------------------------------------------- speech with pauses


def active_level(audio: np.ndarray) -> float:
    """Mean power of the 20 ms blocks within 30 dB of the loud end (95th percentile)."""
    env = rms_envelope_db(audio, SR, 0.02)
    act = env[env > np.percentile(env, 95) - 30]
    return float(np.mean(10 ** (act / 10)))


def with_pauses(speech: np.ndarray) -> tuple[np.ndarray, list[tuple[float, float]]]:
    """The clip with :data:`GAP_S` of silence cut in at 1/3 and 2/3; returns audio and the pauses (s)."""
    n = len(speech)
    cuts = [n // 3, 2 * n // 3]
    gap = np.zeros(int(GAP_S * SR), np.float32)
    parts, pauses, pos = [], [], 0
    for i, c in enumerate(cuts):
        parts += [speech[pos:c], gap]
        start = (c + i * len(gap)) / SR
        pauses.append((start, start + GAP_S))
        pos = c
    parts.append(speech[pos:])
    return np.concatenate(parts), pauses


def speech_rows(clips: list[Path]) -> list[dict]:
    rng = np.random.default_rng(1)
    conds = ["clean", "white noise 10 dB", "white noise 0 dB", "melody 10 dB", "melody 0 dB"]
    acc = {
        (m, c): {"called": [], "pause_open": [], "close_s": [], "speech_on": []}
        for m in METHODS
        for c in conds
    }
    for clip in clips:
        speech = read_audio(clip, SR)
        audio, pauses = with_pauses(speech)
        level = active_level(speech)
        noises = {
            "white noise": rng.standard_normal(len(audio)),
            "melody": melody(len(audio) / SR + 1, rng)[: len(audio)],
        }
        t = np.arange(int(np.ceil(len(audio) / SR * FPS))) / FPS
        in_pause = np.zeros(len(t), bool)
        core = np.zeros(len(t), bool)
        for a, b in pauses:
            in_pause |= (t >= a) & (t < b)
            core |= (t >= a + CLOSE_BY_S) & (t < b - VOICE_LEAD_S - 1 / FPS)
        for cond in conds:
            x = audio
            if cond != "clean":
                kind, snr = cond.rsplit(" ", 2)[0], float(cond.split()[-2])
                noise = noises[kind]
                noise = noise * np.sqrt(level / 10 ** (snr / 10) / np.mean(noise**2))
                x = np.clip(audio + noise, -1, 1).astype(np.float32)
            for m, (whole, per_frame) in METHODS.items():
                act = per_frame(x, SR, FPS, len(t))
                r = acc[(m, cond)]
                r["called"].append(bool(whole(x, SR)))
                r["pause_open"].append(float(np.mean(act[core] >= 0.5)))
                for a, _ in pauses:
                    after = np.flatnonzero((t >= a) & (act < 0.05))
                    r["close_s"].append(float(after[0] / FPS - a) if len(after) else GAP_S)
                r["speech_on"].append(float(np.mean(act[~in_pause] >= 0.5)))
    rows = []
    for (m, c), r in acc.items():
        close = np.array(r["close_s"])
        rows.append(
            {
                "condition": c,
                "method": m,
                "clips called speech": f"{np.mean(r['called']):.3f}",
                "pause core frames open": f"{np.mean(r['pause_open']):.3f}",
                "closed within 0.2 s": f"{np.mean(close <= CLOSE_BY_S + 1e-9):.3f}",
                "median closing s": f"{np.median(close):.2f}",
                "speech frames on": f"{np.mean(r['speech_on']):.3f}",
            }
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path("out/eval_vad"))
    ap.add_argument("--clips", type=int, default=None, help="use only the first N speech clips")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)

    rows_ns = []
    for name, x in non_speech().items():
        row = {"sound (6 s)": name}
        for m, (whole, per_frame) in METHODS.items():
            row[f"{m}: speech?"] = str(bool(whole(x, SR)))
            row[f"{m}: frames on"] = f"{np.mean(per_frame(x, SR, FPS) >= 0.5):.3f}"
        rows_ns.append(row)
    text = "## Sounds that are not speech (made in code)\n\n" + markdown_table(rows_ns, list(rows_ns[0]))

    if SHARED.is_dir():
        clips = sorted((SHARED / "audio").iterdir())[: args.clips]
        rows_sp = speech_rows(clips)
        text += (
            f"\n## {len(clips)} real speech clips with two {GAP_S} s pauses cut in "
            "(noise through the pauses too)\n\n" + markdown_table(rows_sp, list(rows_sp[0]))
        )
    else:
        text += f"\n(no {SHARED}: real-speech part skipped)\n"
        rows_sp = []

    rng = np.random.default_rng(2)
    ten = at_level(rng.standard_normal(SR * 600), -25)
    speech_probability(ten[: SR * 5], SR)  # warm-up (loads the weights)
    t0 = time.perf_counter()
    speech_probability(ten, SR)
    dt = time.perf_counter() - t0
    text += f"\nspeech_probability on 10 minutes of audio: {dt:.2f} s ({600 / dt:.0f}x real time)\n"
    (args.out / "results.md").write_text(text)
    (args.out / "results.json").write_text(json.dumps({"non_speech": rows_ns, "speech": rows_sp}, indent=1))
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
