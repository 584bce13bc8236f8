"""The remaining CLI commands end to end on tiny synthetic clips: track → train-renderer → render,
train-audio2exp (and its refusals), eval's happy path."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest
import torch
from test_audio2exp import CFG, fake_sample
from test_cli import assert_one_line_error, nvp

from nvp.app.train_audio2exp import Audio2ExpTrainConfig, train, usable_sets
from nvp.errors import NvpError
from nvp.media import probe_video
from nvp.provenance import verify


def test_track_train_renderer_and_render(demo_clip, tmp_path):
    track = tmp_path / "track"
    assert nvp("track", demo_clip.path, "-o", track).returncode == 0
    proc = nvp("train-renderer", track, demo_clip.path, "-o", tmp_path / "r", "--steps", 3)
    assert proc.returncode == 0, proc.stderr
    manifest = json.loads((tmp_path / "r" / "renderer.json").read_text())
    assert manifest["steps"] == 3 and manifest["format"] == "nvp.renderer"
    out = tmp_path / "re.mp4"
    proc = nvp("render", track, tmp_path / "r", demo_clip.path, "-o", out, "--start-frame", 5, "--frames", 10)
    assert proc.returncode == 0, proc.stderr
    assert probe_video(out).num_frames == 10 and verify(out).marked
    assert_one_line_error(nvp("render", track, tmp_path / "r", demo_clip.path, "-o", tmp_path), "is a folder")


@pytest.fixture(scope="module")
def corpus(demo_clip, tmp_path_factory):
    from nvp.app.demo_clip import make_demo_clip

    folder = tmp_path_factory.mktemp("corpus")
    shutil.copyfile(demo_clip.path, folder / "a.mp4")
    make_demo_clip(folder / "b.mp4", seconds=1.2, size=256, seed=3)
    return folder


def test_pretrain_renderer_command_and_a_training_that_starts_from_it(corpus, demo_clip, tmp_path):
    out = tmp_path / "generic"
    proc = nvp("pretrain-renderer", corpus, "-o", out, "--steps", 3, "--max-frames", 8)
    assert proc.returncode == 0, proc.stderr
    m = json.loads((out / "renderer.json").read_text())
    assert m["videos"] == ["a.mp4", "b.mp4"] and m["steps"] == 3 and m["train_frames"] == 16
    assert np.load(out / "renderer.npz")["composite.out.weight"].dtype == np.float16  # a starting point
    track = tmp_path / "track"
    assert nvp("track", demo_clip.path, "-o", track).returncode == 0
    proc = nvp("train-renderer", track, demo_clip.path, "-o", tmp_path / "r", "--steps", 2, "--init", out)
    assert proc.returncode == 0, proc.stderr
    assert json.loads((tmp_path / "r" / "renderer.json").read_text())["init"] == str(out)
    # one usable video is not a corpus
    proc = nvp("pretrain-renderer", corpus, "-o", tmp_path / "x", "--steps", 3, "--exclude", "b.mp4")
    assert_one_line_error(proc, "at least 2 usable videos")
    assert not (tmp_path / "x" / "renderer.json").exists()


def test_train_audio2exp_command(corpus, tmp_path):
    out = tmp_path / "a2e"
    args = ("--val", "b.mp4", "--steps", 4, "--val-every", 2, "--augment", "noise10")
    proc = nvp("train-audio2exp", corpus, "-o", out, *args)
    assert proc.returncode == 0, proc.stderr
    best = json.loads((out / "best.json").read_text())
    assert best["split"] == {"train": ["a.mp4"], "validation": ["b.mp4"], "excluded": []}
    assert best["train_config"]["augments"] == ["noise10"] and best["net"]["closure_head"]
    noisy = [p.name for p in (out / "cache" / "features").glob("*_noise10.json")]
    assert len(noisy) == 1 and noisy[0].startswith("a-")  # training videos only
    # every validation video unusable: refused before training, nothing written
    proc = nvp("train-audio2exp", corpus, "-o", tmp_path / "x", "--val", "b.mp4", "--exclude", "b.mp4")
    assert_one_line_error(proc, "no validation video")
    assert not (tmp_path / "x" / "best.json").exists()


def test_short_validation_videos_are_checked_before_training(face_model):
    train_set = [fake_sample(face_model, "t", 0)]
    short = fake_sample(face_model, "short", 1)
    short = dataclasses.replace(short, windows=short.windows[:8], tracked=short.tracked.head(8))
    good = fake_sample(face_model, "good", 2)
    assert [s.name for s in usable_sets(train_set, [short, good], 0.8)[1]] == ["good"]
    with pytest.raises(NvpError, match="no validation video"):
        usable_sets(train_set, [short], 0.8)


def test_a_resumed_training_with_dropout_equals_an_uninterrupted_one(face_model, tmp_path):
    train_set = [fake_sample(face_model, f"v{i}", i) for i in range(2)]
    val_set = [fake_sample(face_model, "val", 9)]
    net = dataclasses.replace(CFG, dropout=0.3)
    cfg = Audio2ExpTrainConfig(steps=20, batch=8, lr=3e-3, val_every=10, net=net)
    train(train_set, val_set, face_model, cfg, tmp_path / "a", progress=False)
    train(train_set, val_set, face_model, dataclasses.replace(cfg, steps=10), tmp_path / "b", progress=False)
    torch.manual_seed(12345)  # whatever happened in between, the resume restores the dropout generator
    train(train_set, val_set, face_model, cfg, tmp_path / "b", progress=False)
    a = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=True)["net"]
    b = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=True)["net"]
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=1e-5, atol=1e-6)


def test_eval_happy_path(tmp_path):
    from nvp.app.demo_clip import make_demo_clip

    clip = make_demo_clip(tmp_path / "talk.mp4", seconds=5.0, size=128, seed=1).path
    out = tmp_path / "e"
    proc = nvp("eval", clip, "-o", out, "--steps", 2, "--side-by-side")
    assert proc.returncode == 0, proc.stderr
    r = json.loads((out / "eval.json").read_text())
    assert r["frames"]["test"] == 25 and np.isfinite(r["visual"]["psnr_full"])
    assert all(np.isfinite(r[k]["hf_ratio_mouth"]) for k in ("visual", "audio"))  # where nvp paints
    assert all(-1 <= r[k]["hf_in_place_mouth"] <= 1 for k in ("visual", "audio"))  # a correlation
    assert all(r[k]["hf_ratio_lips"] >= 0 for k in ("visual", "audio"))  # where in the box it is lost
    assert (out / "eval.md").exists() and (out / "eval.png").exists()
    assert verify(out / "side_by_side.mp4").marked
    before = (out / "person" / "bundle.json").stat().st_mtime
    assert nvp("eval", clip, "-o", out, "--steps", 2).returncode == 0
    assert (out / "person" / "bundle.json").stat().st_mtime == before  # the finished fit was reused


def test_training_with_audio_copies_reads_them_and_stays_reproducible(face_model, tmp_path):
    clean = [fake_sample(face_model, f"v{i}", i) for i in range(2)]
    val_set = [fake_sample(face_model, "val", 9)]
    cfg = Audio2ExpTrainConfig(steps=10, batch=8, lr=3e-3, val_every=10, net=CFG)
    noisy = [dataclasses.replace(s, augmented=(s.windows + 5.0,)) for s in clean]
    a = train(clean, val_set, face_model, cfg, tmp_path / "a", progress=False)
    b = train(noisy, val_set, face_model, cfg, tmp_path / "b", progress=False)
    c = train(noisy, val_set, face_model, cfg, tmp_path / "c", progress=False)
    assert b["log"][-1]["train_loss"] != a["log"][-1]["train_loss"]  # the copies were read
    assert b["log"] == [dict(r, seconds=br["seconds"]) for r, br in zip(c["log"], b["log"], strict=True)]


def test_a_live_run_that_dropped_frames_suggests_the_rate_this_machine_rendered():
    from types import SimpleNamespace

    from nvp.app.cli.live import slower_hint

    def run(dropped: int, audio_s: float = 8.0) -> str:
        return slower_hint(SimpleNamespace(frames=240, dropped=dropped, seconds=10.0, audio_seconds=audio_s))

    assert run(100) == "; this machine rendered 14.0 frames/s: try --fps 12"  # 140 of 240 in 10 s
    assert run(0) == run(4) == ""  # none or a few dropped: nothing to suggest
    assert run(100, audio_s=2.0) == ""  # too short: the start-up would weigh as much as the frames
