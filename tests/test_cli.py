"""The nvp command line: one clear message and a non-zero exit for bad input; end-to-end tracking."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import soundfile as sf

from nvp.media import VideoWriter, probe_video
from nvp.tracked import TrackedSequence


def nvp(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "nvp.app.cli", "-q", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=300,
    )


def assert_one_line_error(proc, *words):
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("nvp ")]
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    for w in words:
        assert w in lines[0].lower(), lines[0]


def test_missing_file(tmp_path):
    assert_one_line_error(nvp("track", tmp_path / "nope.mp4", "-o", tmp_path / "out"), "does not exist")
    assert not (tmp_path / "out").exists()


def test_not_a_video(tmp_path):
    bad = tmp_path / "notes.mp4"
    bad.write_text("hello, this is not a video\n" * 20)
    assert_one_line_error(nvp("track", bad, "-o", tmp_path / "out"), "cannot read")


def test_audio_only_file(tmp_path):
    wav = tmp_path / "speech.wav"
    sf.write(wav, np.zeros(16000, np.float32), 16000)
    assert_one_line_error(nvp("track", wav, "-o", tmp_path / "out"), "no video stream")


def test_video_without_a_face(tmp_path):
    path = tmp_path / "wall.mp4"
    with VideoWriter(path, fps=25, width=96, height=64) as w:
        for i in range(10):
            w.write(np.full((64, 96, 3), 20 * i, np.uint8))
    proc = nvp("track", path, "-o", tmp_path / "out")
    assert_one_line_error(proc, "no face")
    assert not (tmp_path / "out").exists()


def test_track_demo_clip_end_to_end(demo_clip, tmp_path):
    proc = nvp("track", demo_clip.path, "-o", tmp_path / "track", "--preview", tmp_path / "preview.mp4")
    assert proc.returncode == 0, proc.stderr
    assert "tracked" in proc.stdout
    seq = TrackedSequence.load(tmp_path / "track")
    assert seq.num_frames == demo_clip.num_frames
    assert seq.valid.mean() > 0.9
    assert np.nanmedian(seq.fit_error) < 2.0
    info = probe_video(tmp_path / "preview.mp4")
    assert info.num_frames == demo_clip.num_frames and info.has_audio


def test_help_lists_commands():
    proc = subprocess.run([sys.executable, "-m", "nvp.app.cli", "--help"], capture_output=True, text=True)
    assert proc.returncode == 0 and "track" in proc.stdout


def test_option_defaults_are_the_functions_own():
    """Where a default cannot come from a light config dataclass (the module imports torch, and building
    the parser must not), the parser's copy equals the one the work uses."""
    import inspect

    from nvp.app.cli import build_parser
    from nvp.app.demo import run_demo
    from nvp.app.pretrain_renderer import pretrain_renderer
    from nvp.app.train_audio2exp import Audio2ExpTrainConfig

    parse = build_parser().parse_args
    a2e = parse(["train-audio2exp", "corpus", "-o", "out"])
    cfg = Audio2ExpTrainConfig()
    assert (a2e.steps, a2e.val_every, a2e.seed, a2e.closure_weight, a2e.features) == (
        cfg.steps,
        cfg.val_every,
        cfg.seed,
        cfg.closure_weight,
        cfg.kind,
    )
    budget = inspect.signature(pretrain_renderer).parameters["budget_minutes"].default
    assert parse(["pretrain-renderer", "corpus", "-o", "out"]).budget_minutes == budget
    assert parse(["demo"]).budget_minutes == inspect.signature(run_demo).parameters["budget_minutes"].default
