"""Drill of a demanding new user (issue 45): outputs over inputs, damaged bundles, bad media, ``kill -9`` at
points of ``nvp fit`` and ``nvp dub``, run as the command line on real clips from ``../shared/data``.

    python -m scripts.tools.drill_bundle                      # every case (about 120 runs of nvp; long)
    python -m scripts.tools.drill_bundle --list               # the cases
    python -m scripts.tools.drill_bundle --cases dub_nan fit_kill_track   # cases whose name contains a word
    python -m scripts.tools.drill_bundle --steps 20 --dub-damaged --keep

Each case runs nvp as a user would (``python -m nvp.app.cli``, a subprocess) and judges what it sees:

* traceback: a Python traceback on stderr, or a process that died of a signal it was not sent;
* one line: an error is exactly one ``nvp <command>: ...`` line on stderr with exit 2;
* data lost: a watched file (the person bundle's, the inputs') changed, vanished, or a file appeared in a
  bundle;
* fine: ``nvp info`` exits 0 on a damaged bundle, or ``nvp dub`` makes a video from one;
* resumed: after ``kill -9`` the same command finishes (exit 0), says "resuming" when work was kept, and
  keeps the facts of the stages done before the kill.

Prints one table row per case and the totals; exit 1 when any case failed. Nothing is written outside a
temporary folder (``--keep`` keeps it). Reads ../shared/data; says so and exits 0 when it is missing.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scripts.common import SHARED

DATA = SHARED
VIDEO = DATA / "video" / "videoretalking__face5.mp4"  # 4.9 s, 524x524, one speaker facing the camera
OTHER = DATA / "video" / "videoretalking__face3.mp4"  # another person, 5 s
AUDIO = DATA / "audio" / "videoretalking__1.wav"  # 5 s English, 44.1 kHz stereo
AUDIO_22000 = DATA / "audio" / "voca__test_sentence.wav"  # 22,000 Hz: a rate AAC cannot store
LONG_AUDIO = DATA / "audio" / "latentsync__demo2_audio.wav"  # 19.8 s: two parts of a dub
TIMEOUT = 1800


@dataclass
class Row:
    """What one case saw."""

    case: str
    kind: str
    runs: int = 0
    exits: list[int] = field(default_factory=list)
    traceback: bool = False
    lost: bool = False
    fine: bool = False
    resumed: bool | None = None
    ok: bool = True
    note: str = ""
    seconds: float = 0.0

    def fail(self, why: str) -> None:
        self.ok = False
        self.note = (self.note + "; " if self.note else "") + why


@dataclass
class Drill:
    """Shared state: the temporary folder, the settings, the finished person bundle made once."""

    work: Path
    steps: int
    dub_damaged: bool
    _bundle: Path | None = None
    setup: Row | None = None

    # -- running nvp

    def nvp(self, row: Row, *args, timeout: float = TIMEOUT) -> subprocess.CompletedProcess:
        """Run ``nvp -q ARGS``; records the exit and any traceback in ``row``."""
        proc = subprocess.run(
            [sys.executable, "-m", "nvp.app.cli", "-q", *map(str, args)],
            capture_output=True,
            text=True,
            timeout=timeout,
            cwd=self.work,
        )
        self._saw(row, proc.returncode, proc.stderr)
        return proc

    def _saw(self, row: Row, code: int, stderr: str, killed: bool = False) -> None:
        row.runs += 1
        row.exits.append(code)
        if "Traceback (most recent call last)" in stderr or (code < 0 and not killed):
            row.traceback = True
            row.fail(f"traceback/crash (exit {code}): {last_line(stderr)}")

    def start(self, *args) -> subprocess.Popen:
        return subprocess.Popen(
            [sys.executable, "-m", "nvp.app.cli", "-q", *map(str, args)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=self.work,
        )

    def refused(self, row: Row, proc: subprocess.CompletedProcess, *words: str) -> None:
        """The run must end with one error line holding ``words`` and exit 2."""
        lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("nvp ")]
        if proc.returncode != 2 or len(lines) != 1:
            row.fail(
                f"expected one error line and exit 2, got exit {proc.returncode}: {last_line(proc.stderr)}"
            )
            return
        missing = [w for w in words if w.lower() not in lines[0].lower()]
        if missing:
            row.fail(f"error line lacks {missing}: {lines[0]}")
        else:
            row.note = row.note or lines[0].split(": ", 1)[-1].replace(f"{self.work}/", "")[:110]

    def succeeded(self, row: Row, proc: subprocess.CompletedProcess) -> bool:
        if proc.returncode != 0:
            row.fail(f"exit {proc.returncode}: {last_line(proc.stderr)}")
            return False
        return True

    # -- material

    @property
    def bundle(self) -> Path:
        """A finished person bundle of VIDEO, fitted once."""
        if self._bundle is None:
            out = self.work / "base" / "person"
            row = self.setup = Row("setup_fit_the_drill_person", "setup")
            t0 = time.perf_counter()
            proc = self.nvp(row, "fit", VIDEO, "-o", out, "--steps", self.steps)
            row.seconds = time.perf_counter() - t0
            if proc.returncode != 0:
                raise SystemExit(f"the drill's person bundle could not be fitted: {proc.stderr}")
            self._bundle = out
        return self._bundle

    def copy_bundle(self, name: str) -> Path:
        dst = self.work / name
        shutil.copytree(self.bundle, dst)
        return dst

    def folder(self, name: str) -> Path:
        f = self.work / name
        f.mkdir(parents=True, exist_ok=True)
        return f


def last_line(text: str) -> str:
    lines = [ln for ln in text.strip().splitlines() if ln.strip()]
    return lines[-1][:160] if lines else ""


def snapshot(*paths: Path) -> dict[str, str]:
    """relative path → sha256 of every file under ``paths`` (files or folders)."""
    out = {}
    for p in paths:
        files = [p] if p.is_file() else sorted(f for f in p.rglob("*") if f.is_file())
        for f in files:
            out[str(f)] = hashlib.sha256(f.read_bytes()).hexdigest()
    return out


def watch(row: Row, before: dict[str, str], *paths: Path) -> None:
    """Data lost: a watched file changed or vanished, or a file appeared under a watched folder."""
    after = snapshot(*paths)
    changed = sorted(k for k in before if after.get(k) != before[k])
    added = sorted(set(after) - set(before))
    if changed or added:
        row.lost = True
        row.fail(f"data lost: {len(changed)} changed/missing, {len(added)} added ({(changed + added)[0]})")


def write_wav(path: Path, audio: np.ndarray, rate: int, subtype: str | None = None) -> Path:
    import soundfile as sf

    sf.write(path, audio, rate, subtype=subtype)
    return path


def speech_of(path: Path, rate: int = 16000) -> np.ndarray:
    from nvp.media import read_audio

    return read_audio(path, rate)


def clip(path: Path, frames, fps: float, audio: np.ndarray | None, rate: int) -> Path:
    from nvp.media import VideoWriter

    frames = list(frames)
    h, w = frames[0].shape[:2]
    with VideoWriter(path, fps, w, h, audio=audio, audio_rate=rate) as vw:
        for f in frames:
            vw.write(f)
    return path


# ------------------------------------------------------------------------------------------------ cases


def output_cases() -> dict[str, Callable[[Drill, Row], None]]:
    """An output over an input or inside a person bundle: refused in one line, nothing changes."""

    def case(args_of, *words):
        def run(d: Drill, row: Row) -> None:
            r = d.copy_bundle(f"{row.case}/R")
            inputs = d.folder(f"{row.case}/in")
            audio = Path(shutil.copy(AUDIO, inputs / "a.wav"))
            video = Path(shutil.copy(VIDEO, inputs / "v.mp4"))
            (inputs / "link").symlink_to(r)
            (inputs / "list.txt").write_text("a.wav\n")
            before = snapshot(r, inputs)
            d.refused(row, d.nvp(row, *args_of(r, inputs, audio, video)), *words)
            watch(row, before, r, inputs)

        return run

    inside = "inside the person bundle"
    return {
        "out_dub_onto_bundle_footage": case(
            lambda r, i, a, v: ("dub", a, "--person", r, "-o", r / "target.mp4"), inside
        ),
        "out_dub_new_file_in_bundle": case(
            lambda r, i, a, v: ("dub", a, "--person", r, "-o", r / "renderer" / "x.mp4"), inside
        ),
        "out_dub_through_a_link": case(
            lambda r, i, a, v: ("dub", a, "--person", r, "-o", i / "link" / "target.mp4"), inside
        ),
        "out_dub_onto_its_audio": case(
            lambda r, i, a, v: ("dub", a, "--person", r, "-o", a), "also an input"
        ),
        "out_dub_onto_its_list": case(
            lambda r, i, a, v: ("dub", "--list", i / "list.txt", "--person", r, "-o", i / "list.txt"),
            "also an input",
        ),
        "out_dub_several_into_bundle": case(
            lambda r, i, a, v: ("dub", a, v, "--person", r, "-o", r / "dubs"), inside
        ),
        "out_say_into_bundle": case(
            lambda r, i, a, v: ("say", "hello there", "--person", r, "-o", r / "x.mp4"), inside
        ),
        "out_say_wav_into_bundle": case(
            lambda r, i, a, v: ("say", "hello", "--person", r, "-o", i / "x.mp4", "--wav", r / "s.wav"),
            inside,
        ),
        "out_predict_into_bundle": case(
            lambda r, i, a, v: ("predict", a, "--style", r, "-o", r / "x.npz"), inside
        ),
        "out_fit_onto_its_video": case(lambda r, i, a, v: ("fit", v, "-o", v, "--steps", 1), "input video"),
        "out_fit_into_a_bundle": case(lambda r, i, a, v: ("fit", v, "-o", r / "sub", "--steps", 1), inside),
        "out_fit_bundle_over_its_footage": case(
            lambda r, i, a, v: ("fit", r / "target.mp4", "-o", r, "--steps", 1), "holds the input"
        ),
        "out_fit_other_video_over_finished": case(
            lambda r, i, a, v: ("fit", OTHER, "-o", r, "--steps", 1), "another video", "--force"
        ),
    }


def damaged_cases(d: Drill) -> dict[str, Callable[[Drill, Row], None]]:
    """Every file of a bundle cut short, emptied or filled with junk of the same size: never "fine"."""
    m = json.loads((d.bundle / "bundle.json").read_text())
    names = ["bundle.json", *sorted(m.get("checksums", {}))]
    cases = {}
    for rel in names:
        for damage in ("truncate", "empty", "junk"):

            def run(dr: Drill, row: Row, rel=rel, damage=damage) -> None:
                r = dr.copy_bundle(f"{row.case}/R")
                f = r / rel
                data = f.read_bytes()
                junk = np.random.default_rng(len(data)).integers(0, 256, len(data), dtype=np.uint8).tobytes()
                f.write_bytes({"truncate": data[: len(data) // 2], "empty": b"", "junk": junk}[damage])
                info = dr.nvp(row, "info", r)
                if info.returncode == 0:
                    row.fine = True
                    row.fail("nvp info said fine")
                else:
                    dr.refused(row, info, "bundle" if rel == "bundle.json" else rel)
                if dr.dub_damaged:
                    out = dr.folder(row.case) / "x.mp4"
                    dub = dr.nvp(row, "dub", AUDIO, "--person", r, "-o", out)
                    if dub.returncode == 0:
                        row.fine = True
                        row.fail("nvp dub made a video")
                    else:
                        dr.refused(row, dub, "damaged" if rel != "bundle.json" else "bundle")

            cases[f"damaged_{rel.replace('/', '_')}_{damage}"] = run
    return cases


def input_cases() -> dict[str, Callable[[Drill, Row], None]]:
    """Bad media and text: refused up front in one line (or handled), nothing left behind."""

    def dub_refused(make, *words, quick: float = 60.0):
        def run(d: Drill, row: Row) -> None:
            folder = d.folder(row.case)
            audio = make(folder)
            t0 = time.perf_counter()
            d.refused(row, d.nvp(row, "dub", audio, "--person", d.bundle, "-o", folder / "o.mp4"), *words)
            if time.perf_counter() - t0 > quick:
                row.fail(f"refused only after {time.perf_counter() - t0:.0f} s (work started first?)")
            left = sorted(p.name for p in folder.iterdir() if p != audio)
            if left:
                row.fail(f"left behind: {left}")

        return run

    def nan(folder: Path) -> Path:
        a = speech_of(AUDIO)
        a[16000:16010] = np.nan
        return write_wav(folder / "nan.wav", a, 16000, "FLOAT")

    def inf(folder: Path) -> Path:
        a = speech_of(AUDIO)
        a[24000] = np.inf
        return write_wav(folder / "inf.wav", a, 16000, "FLOAT")

    def silence(folder: Path) -> Path:
        return write_wav(folder / "silence.wav", np.zeros(48000, np.float32), 16000)

    def text(folder: Path) -> Path:
        p = folder / "notes.wav"
        p.write_text("this is not audio\n" * 50)
        return p

    def empty(folder: Path) -> Path:
        p = folder / "empty.wav"
        p.write_bytes(b"")
        return p

    def dub_works(make):
        def run(d: Drill, row: Row) -> None:
            from nvp.media import probe_video

            folder = d.folder(row.case)
            audio = make(folder)
            out = folder / "o.mp4"
            if d.succeeded(row, d.nvp(row, "dub", audio, "--person", d.bundle, "-o", out)):
                info = probe_video(out)
                row.note = f"{info.num_frames} frames, audio {info.audio_sample_rate} Hz"
            left = sorted(p.name for p in folder.iterdir() if p not in (audio, out))
            if left:
                row.fail(f"left behind: {left}")

        return run

    def rate_22000(folder: Path) -> Path:
        return Path(shutil.copy(AUDIO_22000, folder / "voca.wav"))

    def ten_channels(folder: Path) -> Path:
        a = speech_of(AUDIO)
        return write_wav(folder / "ten.wav", np.repeat(a[:, None], 10, 1) * 0.5, 16000)

    def say_refused(text_, *words):
        def run(d: Drill, row: Row) -> None:
            folder = d.folder(row.case)
            d.refused(row, d.nvp(row, "say", text_, "--person", d.bundle, "-o", folder / "o.mp4"), *words)
            if any(folder.iterdir()):
                row.fail("left files behind")

        return run

    def fit_refused(make, *words, warn: str | None = None):
        def run(d: Drill, row: Row) -> None:
            folder = d.folder(row.case)
            video = make(folder)
            proc = d.nvp(row, "fit", video, "-o", folder / "p", "--steps", 1)
            d.refused(row, proc, *words)
            if ".partial" in proc.stderr or "target.mp4" in proc.stderr:
                row.fail("a message names nvp's internal copy")
            if warn is not None and warn not in proc.stderr:
                row.fail(f"no warning '{warn}'")
            left = sorted(p.name for p in folder.iterdir() if p != video)
            if left:
                row.fail(f"left behind: {left}")

        return run

    def frames_of(video: Path):
        from nvp.media import iter_frames

        return list(iter_frames(video))

    def faceless_cut_short(folder: Path) -> Path:
        rng = np.random.default_rng(0)
        noise = (rng.integers(0, 255, (100, 96, 128, 3))).astype(np.uint8)
        whole = clip(folder / "whole.mp4", noise, 25, speech_of(AUDIO)[:64000], 16000)
        cut = folder / "wall.mp4"
        cut.write_bytes(whole.read_bytes()[: int(whole.stat().st_size * 0.8)])
        whole.unlink()
        return cut

    def no_audio(folder: Path) -> Path:
        return clip(folder / "mute.mp4", frames_of(VIDEO), 25, None, 16000)

    def silent(folder: Path) -> Path:
        return clip(folder / "silent.mp4", frames_of(VIDEO), 25, np.zeros(16000 * 5, np.float32), 16000)

    def too_short(folder: Path) -> Path:
        return clip(folder / "short.mp4", frames_of(VIDEO)[:12], 25, speech_of(AUDIO)[:8000], 16000)

    def not_video(folder: Path) -> Path:
        p = folder / "notes.mp4"
        p.write_text("hello, this is not a video\n" * 20)
        return p

    def fit_warns(make, warning: str):
        def run(d: Drill, row: Row) -> None:
            folder = d.folder(row.case)
            video = make(folder)
            proc = d.nvp(row, "fit", video, "-o", folder / "p", "--steps", d.steps)
            if d.succeeded(row, proc) and warning not in proc.stderr:
                row.fail(f"no warning '{warning}'")
            elif warning in proc.stderr:
                row.note = next(ln for ln in proc.stderr.splitlines() if warning in ln)[:100]

        return run

    def tiny(folder: Path) -> Path:
        import cv2

        small = [cv2.resize(f, (64, 64), interpolation=cv2.INTER_AREA) for f in frames_of(VIDEO)]
        return clip(folder / "tiny.mp4", small, 25, speech_of(AUDIO, 16000), 16000)

    def gap(folder: Path) -> Path:
        frames = frames_of(VIDEO)
        grey = [np.full_like(frames[0], 90)] * 50  # 2 s without a face
        audio = speech_of(VIDEO, 16000)
        both = np.concatenate(
            [audio[: len(audio) // 2], np.zeros(32000, np.float32), audio[len(audio) // 2 :]]
        )
        half = len(frames) // 2
        return clip(folder / "gap.mp4", frames[:half] + grey + frames[half:], 25, both, 16000)

    return {
        "in_dub_nan_samples": dub_refused(nan, "not numbers"),
        "in_dub_inf_samples": dub_refused(inf, "not numbers"),
        "in_dub_silence": dub_refused(silence, "no speech"),
        "in_dub_not_audio": dub_refused(text, "cannot read"),
        "in_dub_empty_file": dub_refused(empty, "cannot read"),
        "in_dub_22000_hz": dub_works(rate_22000),
        "in_dub_ten_channels": dub_works(ten_channels),
        "in_say_chinese": say_refused("我们今天用中文说话。", "CJK script"),
        "in_say_arabic": say_refused("مرحبا بالعالم، كيف حالك؟", "Arabic script"),
        "in_fit_faceless_cut_short": fit_refused(faceless_cut_short, "no face", "wall.mp4", warn="cut short"),
        "in_fit_no_audio": fit_refused(no_audio, "no audio"),
        "in_fit_silent": fit_refused(silent, "no speech"),
        "in_fit_too_short": fit_refused(too_short, "lasts only"),
        "in_fit_not_a_video": fit_refused(not_video, "cannot read"),
        "in_fit_tiny_64px": fit_warns(tiny, "px across"),
        "in_fit_2s_without_face": fit_warns(gap, "no face in"),
    }


# -- kill -9


def stages_of(out: Path) -> dict:
    try:
        return json.loads((out.with_name(out.name + ".partial") / "progress.json").read_text()).get(
            "stages", {}
        )
    except (OSError, ValueError):
        return {}


def kill_when(d: Drill, row: Row, args: tuple, ready: Callable[[], bool], limit: float = TIMEOUT) -> bool:
    """Start ``nvp ARGS``, ``kill -9`` it as soon as ``ready()``; False when it ended first."""
    p = d.start(*args)
    t0 = time.perf_counter()
    while p.poll() is None and time.perf_counter() - t0 < limit:
        if ready():
            p.send_signal(signal.SIGKILL)
            _, err = p.communicate()
            d._saw(row, p.returncode, err, killed=True)
            return True
        time.sleep(0.05)
    _, err = p.communicate()
    d._saw(row, p.returncode, err)
    row.fail(f"the run ended before the kill point (exit {p.returncode})")
    return False


def fit_kill_cases() -> dict[str, Callable[[Drill, Row], None]]:
    """``kill -9`` a fit at five points (tracking twice: before and after it saved landmarks), twice in a
    row, and with its saved landmarks or its renderer checkpoint damaged after the kill; the same command
    then finishes, says it resumes in one line, keeps the work (a damaged checkpoint: one error line that
    names it first, then, deleted, the fit goes on without it)."""

    def case(
        point: str,
        ready_of: Callable[[Path], bool],
        steps: int | None = None,
        video=None,
        again: Callable[[Path], bool] | None = None,
        then: Callable[[Drill, Row, Path], bool] | None = None,
    ):
        """``again``: a second kill point of the rerun; ``then``: what happens to the work folder between the
        last kill and the rerun (damage; False: stop there)."""

        def run(d: Drill, row: Row) -> None:
            out = d.folder(row.case) / "p"
            target = VIDEO if video is None else video(d.folder(row.case))
            args = ("fit", target, "-o", out, "--steps", steps or d.steps)
            if not kill_when(d, row, args, lambda: ready_of(out)):
                return
            if again is not None and not kill_when(d, row, args, lambda: again(out)):
                return
            kept = stages_of(out)
            if then is not None and not then(d, row, out):
                return
            proc = d.nvp(row, *args)
            if not d.succeeded(row, proc):
                row.resumed = False
                return
            m = json.loads((out / "bundle.json").read_text())
            redone = [s for s, facts in kept.items() if m["stages"].get(s) != facts]
            said = [ln for ln in proc.stderr.splitlines() if "resuming" in ln]
            row.resumed = not redone and (bool(said) or not kept)
            if redone:
                row.fail(f"stages done before the kill were redone: {redone}")
            if kept and len(said) != 1:
                row.fail(f"the rerun said it resumed in {len(said)} lines, not one")
            if point == "renderer" and "from its last checkpoint" not in proc.stderr:
                row.fail("renderer training did not go on from its checkpoint")
            if point == "saved tracking" and "tracking goes on from frame 250 of" not in proc.stderr:
                row.fail("tracking did not go on from its last saved frame")
            if point == "damaged saved tracking" and "tracking goes on" in proc.stderr:
                row.fail("tracking went on from damaged landmarks")
            seen = f"killed in {point}; kept {','.join(kept) or '-'}" + (
                f"; says ({said[0].rsplit(' (', 1)[-1]}" if said else ""
            )
            row.note = seen + (f"; {row.note}" if row.note else "")  # (a failure's reason stays in view)
            info = d.nvp(row, "info", out)
            d.succeeded(row, info)

        return run

    def partial(out: Path) -> Path:
        return out.with_name(out.name + ".partial")

    def junk_landmarks(d: Drill, row: Row, out: Path) -> bool:  # the saved landmarks' arrays filled with junk
        seg = partial(out) / "tracking" / "segment-00000.json"
        arrays = seg.parent / json.loads(seg.read_text())["arrays"]
        arrays.write_bytes(
            np.random.default_rng(0).integers(0, 256, arrays.stat().st_size, np.uint8).tobytes()
        )
        return True

    def junk_checkpoint(
        d: Drill, row: Row, out: Path
    ) -> bool:  # refused in one line, then deleted by the user
        ckpt = partial(out) / "renderer" / "checkpoint.pt"
        ckpt.write_bytes(np.random.default_rng(0).integers(0, 256, ckpt.stat().st_size, np.uint8).tobytes())
        target = out.parent / "longer.mp4" if (out.parent / "longer.mp4").exists() else VIDEO
        proc = d.nvp(row, "fit", target, "-o", out, "--steps", 400)
        d.refused(row, proc, "checkpoint.pt", "damaged", "delete it")
        ckpt.unlink()
        return row.ok

    def during(stage: str, before: str):
        return lambda out: before in stages_of(out) and stage not in stages_of(out)

    def training(out: Path) -> bool:
        return (out.with_name(out.name + ".partial") / "renderer" / "checkpoint.pt").exists()

    def tracking_saved(out: Path) -> bool:  # the first segment of landmarks (250 frames) is saved
        return (out.with_name(out.name + ".partial") / "tracking" / "segment-00000.json").exists()

    def three_times(folder: Path) -> Path:  # VIDEO forwards, backwards, forwards: 366 frames, 14.6 s
        from nvp.media import iter_frames

        frames = list(iter_frames(VIDEO))
        speech = speech_of(VIDEO)
        return clip(folder / "longer.mp4", frames + frames[::-1] + frames, 25, np.tile(speech, 3), 16000)

    return {
        "fit_kill_tracking": case("track", during("track", "target")),
        "fit_kill_tracking_saved": case("saved tracking", tracking_saved, video=three_times),
        "fit_kill_style": case("style", during("style", "track")),
        "fit_kill_renderer": case("renderer", training, steps=400),
        "fit_kill_register": case("register", during("register", "renderer")),
        "fit_kill_mouths": case("mouths", during("mouths", "register")),
        "fit_kill_twice_tracking_then_style": case(
            "saved tracking, then style", tracking_saved, video=three_times, again=during("style", "track")
        ),
        "fit_kill_tracking_saved_damaged": case(
            "damaged saved tracking", tracking_saved, video=three_times, then=junk_landmarks
        ),
        "fit_kill_renderer_checkpoint_damaged": case(
            "damaged renderer checkpoint", training, steps=400, then=junk_checkpoint
        ),
    }


def dub_kill_cases() -> dict[str, Callable[[Drill, Row], None]]:
    """``kill -9`` a dub at three points: the same command then finishes and leaves nothing beside."""

    def case(point: str, ready_of: Callable[[Path], bool], resumes: bool):
        def run(d: Drill, row: Row) -> None:
            from nvp.app.dub import parts_folder

            out = d.folder(row.case) / "o.mp4"
            args = ("dub", LONG_AUDIO, "--person", d.bundle, "-o", out)
            if not kill_when(d, row, args, lambda: ready_of(out)):
                return
            proc = d.nvp(row, *args)
            if not d.succeeded(row, proc):
                row.resumed = False
                return
            says = "resuming" in proc.stderr
            row.resumed = says or not resumes
            if resumes and not says:
                row.fail("the rerun did not say it resumed")
            left = sorted(p.name for p in out.parent.iterdir() if p != out)
            if parts_folder(out).exists() or left:
                row.fail(f"left behind: {left}")
            row.note = f"killed {point}; " + (last_line(proc.stderr) if says else "started again")

        return run

    def parts(out: Path) -> Path:
        return out.with_name(f".{out.name}.nvp-parts")

    return {
        "dub_kill_first_part": case("in the first part", lambda o: (parts(o) / "key.json").exists(), False),
        "dub_kill_second_part": case(
            "after the first part", lambda o: (parts(o) / "part-00000.json").exists(), True
        ),
        "dub_kill_join": case(
            "while joining",
            lambda o: (
                any(o.parent.glob(f".{o.stem}.nvp-*.tmp.mp4")) and (parts(o) / "part-00001.json").exists()
            ),
            True,
        ),
    }


def all_cases(d: Drill | None) -> dict[str, Callable[[Drill, Row], None]]:
    return {
        **output_cases(),
        **input_cases(),
        **(damaged_cases(d) if d is not None else {"damaged_<file>_<truncate|empty|junk>": None}),
        **fit_kill_cases(),
        **dub_kill_cases(),
    }


# ------------------------------------------------------------------------------------------------ main


def table(rows: list[Row]) -> str:
    yn = {True: "yes", False: "no", None: "-"}
    out = [
        "| case | runs | exits | traceback | data lost | fine when damaged | resumed | s | result |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        out.append(
            f"| {r.case} | {r.runs} | {','.join(map(str, r.exits))} | {yn[r.traceback]} | {yn[r.lost]} | "
            f"{yn[r.fine] if r.kind == 'damaged' else '-'} | {yn[r.resumed]} | {r.seconds:.0f} | "
            f"{'ok' if r.ok else 'FAIL'}: {r.note} |"
        )
    kills = [r for r in rows if r.resumed is not None]
    out.append(
        f"\n{len(rows)} cases, {sum(r.runs for r in rows)} runs of nvp: "
        f"{sum(r.traceback for r in rows)} tracebacks, {sum(r.lost for r in rows)} with data lost, "
        f"{sum(r.fine for r in rows)} damaged bundles said fine, "
        f"{sum(bool(r.resumed) for r in kills)} of {len(kills)} kills resumed; "
        f"{sum(not r.ok for r in rows)} cases failed"
    )
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="*", help="run the cases whose names contain one of these words")
    ap.add_argument("--list", action="store_true", help="list the cases and exit")
    ap.add_argument("--steps", type=int, default=20, help="renderer steps of the drill's fits")
    ap.add_argument("--dub-damaged", action="store_true", help="also dub every damaged bundle")
    ap.add_argument("--keep", action="store_true", help="keep the temporary folder")
    args = ap.parse_args(argv)
    if args.list:
        print("\n".join(all_cases(None)))
        return 0
    missing = [p for p in (VIDEO, OTHER, AUDIO, AUDIO_22000, LONG_AUDIO) if not p.exists()]
    if missing:
        print(f"no drill data: {missing[0]} does not exist (the drill reads {DATA})")
        return 0
    work = Path(tempfile.mkdtemp(prefix="nvp-drill-"))
    d = Drill(work, args.steps, args.dub_damaged)
    wanted = args.cases
    rows: list[Row] = []
    try:
        assert d.bundle.is_dir()  # the drill's person, fitted once (its own row: setup)
        cases = all_cases(d)
        chosen = [n for n in cases if not wanted or any(w in n for w in wanted)]
        for name in chosen:
            kind = name.split("_", 1)[0]
            row = Row(name, {"out": "output", "in": "input"}.get(kind, kind))
            t0 = time.perf_counter()
            try:
                cases[name](d, row)
            except subprocess.TimeoutExpired:
                row.fail("timed out")
            except Exception as e:  # the drill's own failure: reported, the others still run
                row.fail(f"drill error: {type(e).__name__}: {e}")
            row.seconds = time.perf_counter() - t0
            rows.append(row)
            print(f"{name}: {'ok' if row.ok else 'FAIL'} ({row.seconds:.0f} s) {row.note}", file=sys.stderr)
    finally:
        if args.keep:
            print(f"kept {work}", file=sys.stderr)
        else:
            shutil.rmtree(work, ignore_errors=True)
    if d.setup is not None:
        rows.insert(0, d.setup)
    print(table(rows))
    return 0 if all(r.ok for r in rows) else 1


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
