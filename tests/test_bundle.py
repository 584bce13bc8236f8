"""Person bundles and `nvp fit` never lose data, resume only the same input, and survive kills and damage."""

from __future__ import annotations

import errno
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
from test_cli import assert_one_line_error, nvp

from nvp.bundle import PersonBundle, partial_dir, recover, replaced_dir
from nvp.errors import FormatError, NvpError


@pytest.fixture(scope="module")
def fitted(demo_clip, tmp_path_factory):
    """A tiny finished bundle (2 renderer steps), copied by the tests that damage it."""
    from nvp.app.fit import FitConfig, fit

    out = tmp_path_factory.mktemp("bundle") / "person"
    return fit(demo_clip.path, out, FitConfig(steps=2), progress=False).root


def copy_of(bundle, tmp_path, name="p"):
    dst = tmp_path / name
    shutil.copytree(bundle, dst)
    return dst


def clip_with_audio(path, frames, audio, rate=16000, size=64, seed=0):
    """A faceless clip (noise frames) with the given audio."""
    from nvp.media import VideoWriter

    rng = np.random.default_rng(seed)
    with VideoWriter(path, 25, size, size, audio=audio, audio_rate=rate) as w:
        for _ in range(frames):
            w.write(rng.integers(0, 255, (size, size, 3), dtype=np.uint8))
    return path


def test_fit_refuses_a_foreign_folder_and_keeps_its_contents(demo_clip, tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "thesis.txt").write_text("years of work")
    assert_one_line_error(nvp("fit", demo_clip.path, "-o", out, "--steps", 1), "not empty")
    assert (out / "thesis.txt").read_text() == "years of work" and sorted(p.name for p in out.iterdir()) == [
        "thesis.txt"
    ]


def test_fit_refuses_to_write_over_its_input_or_a_file(demo_clip, tmp_path):
    video = tmp_path / "v.mp4"
    shutil.copyfile(demo_clip.path, video)
    before = video.read_bytes()
    assert_one_line_error(nvp("fit", video, "-o", video, "--steps", 1), "input video")
    assert video.read_bytes() == before and not (tmp_path / "v.mp4.old").exists()
    notes = tmp_path / "notes.txt"
    notes.write_text("x")
    assert_one_line_error(nvp("fit", video, "-o", notes, "--steps", 1), "is a file")
    assert notes.read_text() == "x"


def test_resume_restarts_when_the_input_changed(demo_clip, tmp_path, monkeypatch):
    from nvp.app import fit as app_fit
    from nvp.app.demo_clip import make_demo_clip

    other = make_demo_clip(tmp_path / "b.mp4", seconds=1.2, size=256, seed=7).path

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(app_fit, "_train_renderer", interrupted)
    cfg = app_fit.FitConfig(steps=2)
    with pytest.raises(KeyboardInterrupt):
        app_fit.fit(demo_clip.path, tmp_path / "p", cfg, progress=False)
    monkeypatch.undo()
    bundle = app_fit.fit(other, tmp_path / "p", cfg, progress=False)
    assert bundle.manifest["target"]["source"] == str(other)
    assert (bundle.root / "target.mp4").read_bytes() == other.read_bytes()
    from nvp.bundle import input_hash

    assert bundle.manifest["input_sha256"] == input_hash(other) != input_hash(demo_clip.path)


def test_a_faceless_fit_does_not_poison_the_next_one(demo_clip, tmp_path):
    from nvp.app.demo_voice import AUDIO_RATE, speech_script, synth_voice

    rng = np.random.default_rng(0)
    voice = synth_voice(speech_script(2.0, rng), 2.0, rng)
    faceless = clip_with_audio(tmp_path / "wall.mp4", 50, voice, AUDIO_RATE)
    assert_one_line_error(nvp("fit", faceless, "-o", tmp_path / "p", "--steps", 1), "face")
    proc = nvp("fit", demo_clip.path, "-o", tmp_path / "p", "--steps", 1)
    assert proc.returncode == 0, proc.stderr
    assert PersonBundle.load(tmp_path / "p").manifest["target"]["source"] == str(demo_clip.path)


def test_fit_refuses_silence_and_too_short_videos(demo_clip, tmp_path):
    silent = clip_with_audio(tmp_path / "silent.mp4", 50, np.zeros(32000, np.float32))
    assert_one_line_error(nvp("fit", silent, "-o", tmp_path / "p", "--steps", 1), "no speech", "1-3 minutes")
    rng = np.random.default_rng(0)
    short = clip_with_audio(tmp_path / "short.mp4", 12, 0.3 * rng.standard_normal(8000).astype(np.float32))
    assert_one_line_error(nvp("fit", short, "-o", tmp_path / "q", "--steps", 1), "lasts only 0.5 s")
    assert not (tmp_path / "p").exists() and not (tmp_path / "q").exists()


def test_fitting_again_reuses_a_finished_bundle(fitted, demo_clip, tmp_path, monkeypatch):
    import tracking.track
    from nvp.app.fit import FitConfig, fit

    p = copy_of(fitted, tmp_path)

    def no_work(*a, **k):
        raise AssertionError("a finished fit must not be repeated")

    monkeypatch.setattr(tracking.track, "track_video", no_work)
    assert fit(demo_clip.path, p, FitConfig(steps=2), progress=False).root == p


MEMBERS = ["tracked/tracked.npz", "style.npz", "renderer/renderer.npz"]
EVERY_FILE = [
    "tracked/tracked.json",
    "style.json",
    "renderer/renderer.json",
    "renderer/mouths.json",
    "renderer/mouths.npz",
    "target.mp4",
]


def damage_file(f, damage):
    """Cut ``f`` short, empty it, or fill it with junk of the same size."""
    data = f.read_bytes()
    junk = np.random.default_rng(1).integers(0, 256, len(data), dtype=np.uint8).tobytes()
    f.write_bytes({"truncate": data[: len(data) // 2], "empty": b"", "junk": junk}[damage])


@pytest.mark.parametrize("member", MEMBERS)
@pytest.mark.parametrize("damage", ["truncate", "empty"])
def test_a_damaged_bundle_is_reported_not_crashed_on(fitted, tmp_path, member, damage):
    p = copy_of(fitted, tmp_path)
    damage_file(p / member, damage)
    with pytest.raises(FormatError, match="damaged"):
        PersonBundle.load(p)


def test_a_damaged_bundle_is_one_line_from_the_command_line(fitted, tmp_path):
    """The real processes: one line, no traceback, no output (the in-process test below covers every file
    and damage through the same error path)."""
    p = copy_of(fitted, tmp_path)
    damage_file(p / "renderer/renderer.npz", "truncate")
    assert_one_line_error(nvp("info", p), "damaged")
    wav = tmp_path / "s.wav"
    sf.write(wav, 0.3 * np.random.default_rng(0).standard_normal(16000).astype(np.float32), 16000)
    assert_one_line_error(nvp("dub", wav, "--person", p, "-o", tmp_path / "x.mp4"), "damaged")
    assert not (tmp_path / "x.mp4").exists()


@pytest.mark.parametrize("member", EVERY_FILE + MEMBERS)
@pytest.mark.parametrize("damage", ["truncate", "empty", "junk"])
def test_info_and_dub_check_every_file_of_the_bundle_and_name_the_damaged_one(
    fitted, tmp_path, capsys, member, damage
):
    p = copy_of(fitted, tmp_path)
    assert (p / member).is_file()
    assert run_cli(capsys, "info", p)[0] == 0  # undamaged: fine
    damage_file(p / member, damage)
    assert_refused(run_cli(capsys, "info", p), "the bundle is damaged", member)
    wav = tmp_path / "s.wav"
    sf.write(wav, 0.3 * np.random.default_rng(0).standard_normal(16000).astype(np.float32), 16000)
    assert_refused(
        run_cli(capsys, "dub", wav, "--person", p, "-o", tmp_path / "x.mp4"), "the bundle is damaged", member
    )
    assert not (tmp_path / "x.mp4").exists()


def tree(folder):
    return sorted((p.relative_to(folder), p.is_file() and p.read_bytes()) for p in folder.rglob("*"))


def test_every_interrupted_publish_is_finished_by_the_next_run(fitted, demo_clip, tmp_path):
    from nvp.app.fit import FitConfig, fit

    # killed after bundle.json was written into the partial folder, before the swap (old bundle in place)
    root = copy_of(fitted, tmp_path, "p")
    new = copy_of(fitted, tmp_path, "p.partial")
    (new / "marker").write_text("new")
    before = tree(tmp_path)
    assert not (PersonBundle.load(root).root / "marker").exists()  # the old one, read as it is
    assert tree(tmp_path) == before  # reading a bundle never changes the disk
    recover(root)
    assert (root / "marker").exists() and not partial_dir(root).exists() and not replaced_dir(root).exists()
    # killed after the old bundle was moved aside, before the new one was renamed
    root2 = tmp_path / "q"
    copy_of(fitted, tmp_path, "q.replaced")
    (copy_of(fitted, tmp_path, "q.partial") / "marker").write_text("new")
    before = tree(tmp_path)
    with pytest.raises(FormatError, match="run the same nvp fit again to finish"):
        PersonBundle.load(root2)
    assert tree(tmp_path) == before
    assert fit(demo_clip.path, root2, FitConfig(steps=2), progress=False).root == root2  # finishes, reuses
    assert (root2 / "marker").exists() and not replaced_dir(root2).exists()
    # killed while the old bundle was being removed: half of it left
    old = copy_of(fitted, tmp_path, "q.replaced")
    shutil.rmtree(old / "renderer")
    recover(root2)
    assert not old.exists() and PersonBundle.load(root2)


def test_disk_full_while_fitting_says_so(demo_clip, tmp_path, monkeypatch):
    from nvp.app import fit as app_fit

    def full(src, dst, *a, **k):
        with open(dst, "wb") as f:
            f.write(b"x" * 10)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(app_fit.shutil, "copyfile", full)
    with pytest.raises(NvpError, match="disk full while writing .*target.mp4"):
        app_fit.fit(demo_clip.path, tmp_path / "p", app_fit.FitConfig(steps=1), progress=False)
    assert not list((tmp_path / "p.partial").glob(".*tmp*"))  # no half-written file left


def test_caches_are_keyed_by_content_and_damaged_entries_recomputed(demo_clip, tmp_path):
    from nvp.app.corpus import cache_key, features_cached

    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir(), b.mkdir()
    shutil.copyfile(demo_clip.path, a / "talk.mp4")
    with open(b / "talk.mp4", "wb") as f:
        f.write(demo_clip.path.read_bytes() + b"\0")  # same name, other content
    assert cache_key(a / "talk.mp4") != cache_key(b / "talk.mp4")
    w = features_cached(a / "talk.mp4", tmp_path / "cache", "mel", 25.0, 30)
    (npz,) = (tmp_path / "cache" / "features").glob("*.npz")
    npz.write_bytes(npz.read_bytes()[:100])  # a kill while it was written (before artifacts were atomic)
    np.testing.assert_array_equal(features_cached(a / "talk.mp4", tmp_path / "cache", "mel", 25.0, 30), w)


def test_cached_tracking_made_with_other_tracker_settings_is_recomputed(demo_clip, tmp_path, monkeypatch):
    import nvp.app.corpus as corpus
    import tracking.track

    calls = []
    real = tracking.track.track_video

    def counted(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(tracking.track, "track_video", counted)
    video = tmp_path / "talk.mp4"
    shutil.copyfile(demo_clip.path, video)
    first = corpus.tracked_cached(video, tmp_path / "cache", progress=False)
    again = corpus.tracked_cached(video, tmp_path / "cache", progress=False)
    assert len(calls) == 1 and np.array_equal(first.expression, again.expression)
    stale = dict(first.info, fit_config=dict(first.info["fit_config"], lip_flow=0.0))  # an older tracker
    replace(first, info=stale).save(tmp_path / "cache" / "tracks" / corpus.cache_key(video))
    corpus.tracked_cached(video, tmp_path / "cache", progress=False)
    assert len(calls) == 2


def run_cli(capsys, *args):
    """``nvp -q ARGS`` in this process (faster than a subprocess): (exit code, stderr)."""
    from nvp.app.cli import main

    code = main(["-q", *map(str, args)])
    return code, capsys.readouterr().err


def assert_refused(result, *words):
    code, err = result
    assert code == 2, err
    lines = [ln for ln in err.splitlines() if ln.startswith("nvp ")]
    assert len(lines) == 1 and "Traceback" not in err, err
    for w in words:
        assert w in lines[0], lines[0]


def test_no_output_lands_on_an_input_or_inside_a_person_bundle(fitted, demo_clip, tmp_path, capsys):
    p = copy_of(fitted, tmp_path)
    before = {f: f.read_bytes() for f in p.rglob("*") if f.is_file()}
    wav = tmp_path / "s.wav"
    sf.write(wav, 0.3 * np.random.default_rng(0).standard_normal(16000).astype(np.float32), 16000)
    (tmp_path / "link").symlink_to(p)
    inside = "inside the person bundle"
    assert_refused(run_cli(capsys, "dub", wav, "--person", p, "-o", p / "target.mp4"), inside)
    assert_refused(run_cli(capsys, "dub", wav, "--person", p, "-o", p / "renderer" / "new.mp4"), inside)
    assert_refused(run_cli(capsys, "dub", wav, "--person", p, "-o", tmp_path / "link" / "target.mp4"), inside)
    assert_refused(run_cli(capsys, "dub", wav, wav.with_name("t.wav"), "--person", p, "-o", p), inside)
    assert_refused(run_cli(capsys, "predict", wav, "--style", p, "-o", p / "x.npz"), inside)
    assert_refused(run_cli(capsys, "say", "hello", "--person", p, "-o", p / "x.mp4"), inside)
    assert_refused(
        run_cli(capsys, "say", "hello", "--person", p, "-o", tmp_path / "x.mp4", "--wav", p / "s.wav")
    )
    assert_refused(run_cli(capsys, "fit", demo_clip.path, "-o", p / "sub", "--steps", 1), inside)
    assert_refused(run_cli(capsys, "fit", p / "target.mp4", "-o", p, "--steps", 1), "holds the input")
    lst = tmp_path / "list.txt"
    lst.write_text("s.wav\n")
    assert_refused(run_cli(capsys, "dub", "--list", lst, "--person", p, "-o", lst), "also an input")
    assert lst.read_text() == "s.wav\n"
    assert {f: f.read_bytes() for f in p.rglob("*") if f.is_file()} == before
    assert sorted(tmp_path.iterdir()) == sorted([p, wav, tmp_path / "link", lst])


def test_fit_refuses_to_replace_the_bundle_of_another_video_unless_forced(
    fitted, demo_clip, tmp_path, capsys, monkeypatch
):
    from nvp.app import fit as app_fit

    p = copy_of(fitted, tmp_path)
    before = {f: f.read_bytes() for f in p.rglob("*") if f.is_file()}
    other = tmp_path / "other.mp4"
    other.write_bytes(demo_clip.path.read_bytes() + b"\0")  # another video, as far as its content goes
    assert_refused(
        run_cli(capsys, "fit", other, "-o", p, "--steps", 2), "another video", "clip.mp4", "--force"
    )
    assert {f: f.read_bytes() for f in p.rglob("*") if f.is_file()} == before
    assert not partial_dir(p).exists()

    class Building(Exception):
        pass

    def builder(*a, **k):
        raise Building

    monkeypatch.setattr(app_fit, "BundleBuilder", builder)
    with pytest.raises(Building):  # --force goes on to build
        app_fit.fit(other, p, app_fit.FitConfig(steps=2), progress=False, force=True)
    with pytest.raises(Building):  # the same video with other settings is fitted again without --force
        app_fit.fit(demo_clip.path, p, app_fit.FitConfig(steps=3), progress=False)


@pytest.mark.parametrize("member", ["renderer/mouths.npz", "target.mp4", "style.npz"])
def test_a_bundle_made_before_checksums_is_still_checked_file_by_file(fitted, tmp_path, member):
    import json

    p = copy_of(fitted, tmp_path)
    m = json.loads((p / "bundle.json").read_text())
    del m["checksums"]
    (p / "bundle.json").write_text(json.dumps(m))
    PersonBundle.load(p)
    damage_file(p / member, "junk")
    with pytest.raises(FormatError, match=f"the bundle is damaged: {member}"):
        PersonBundle.load(p)


def speech(seconds, rate=22050, seed=0):
    """Synthetic voiced speech (the demo's voice), which the voice-activity detector takes for speech."""
    from nvp.app.demo_voice import speech_script, synth_voice

    rng = np.random.default_rng(seed)
    return synth_voice(speech_script(seconds, rng), seconds, rng, rate).astype(np.float32)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_dub_refuses_audio_with_samples_that_are_not_numbers_before_any_work(
    fitted, tmp_path, capsys, monkeypatch, bad
):
    import renderer.render

    audio = speech(1.0)
    audio[11025:11030] = bad
    wav = tmp_path / "s.wav"
    sf.write(wav, audio, 22050, subtype="FLOAT")
    monkeypatch.setattr(renderer.render, "FrameRenderer", lambda *a, **k: pytest.fail("rendered"))
    out = tmp_path / "o.mp4"
    assert_refused(
        run_cli(capsys, "dub", wav, "--person", fitted, "-o", out), "not numbers", "0.50 s", "s.wav"
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.wav"]  # no output, no parts folder


def test_dub_of_audio_at_a_rate_aac_cannot_store_streams_it_resampled_into_the_join(
    fitted, tmp_path, monkeypatch
):
    from nvp.app.dub import dub
    from nvp.media import VideoWriter, probe_video, read_audio

    wav = tmp_path / "s.wav"
    sf.write(wav, speech(1.0, 22000), 22000)  # voca's test sentence is at 22,000 Hz
    given = []
    real_writer = VideoWriter.__init__

    def writer(self, *a, **k):
        if k.get("audio_file") is not None or k.get("audio") is not None:
            given.append((k.get("audio_file"), k.get("audio")))
        real_writer(self, *a, **k)

    monkeypatch.setattr(VideoWriter, "__init__", writer)
    r = dub(wav, fitted, tmp_path / "o.mp4", progress=False)
    assert given == [(wav, None)]  # the join reads the track from the file, not from an array held whole
    assert probe_video(r.output).audio_sample_rate == 22050
    assert abs(len(read_audio(r.output, 22050)) - 22050) < 22050 / 25 + 1024
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o.mp4", "s.wav"]  # no parts left


def test_audio_of_any_rate_and_up_to_ten_channels_reads_and_writes(tmp_path):
    from nvp.media import VideoWriter, probe_video, read_audio, storable_audio

    for channels, rate in [(1, 22000), (2, 100000), (8, 48000), (10, 16000)]:
        wav = tmp_path / f"a{channels}.wav"
        data = 0.1 * np.random.default_rng(channels).standard_normal((rate // 2, channels))
        sf.write(wav, data.astype(np.float32), rate)
        audio = read_audio(wav, None, mono=False)  # PyAV crashed reading 8 or more planar channels
        np.testing.assert_allclose(audio.reshape(len(data), -1), data, atol=1e-4)
        stored, stored_rate = storable_audio(audio, rate)
        assert stored_rate in (22050, 96000, 48000, 16000) and stored_rate >= min(rate, 96000)
        assert stored.ndim == (1 if channels in (1, 10) else 2)
        out = tmp_path / f"v{channels}.mp4"
        with VideoWriter(out, 25, 32, 32, audio=audio, audio_rate=rate) as w:
            for _ in range(12):
                w.write(np.zeros((32, 32, 3), np.uint8))
        assert probe_video(out).audio_sample_rate == stored_rate


def test_fit_warns_about_a_small_face_and_long_stretches_without_one(
    demo_clip, tmp_path, monkeypatch, caplog
):
    import cv2

    from nvp.app import fit as app_fit
    from nvp.media import VideoWriter, audio_rate, iter_frames, probe_video, read_audio

    fps, rate = probe_video(demo_clip.path).fps, audio_rate(demo_clip.path)
    frames, audio = list(iter_frames(demo_clip.path)), read_audio(demo_clip.path, None)
    small = tmp_path / "small.mp4"  # a 64x64 video: a face about 40 px across
    with VideoWriter(small, fps, 64, 64, audio=audio, audio_rate=rate) as w:
        for f in frames:
            w.write(cv2.resize(f, (64, 64), interpolation=cv2.INTER_AREA))
    gap = tmp_path / "gap.mp4"  # 1.2 s without a face between two of the clip
    with VideoWriter(gap, fps, 256, 256, audio=np.concatenate([audio] * 3), audio_rate=rate) as w:
        for f in frames + [np.full_like(frames[0], 90)] * len(frames) + frames:
            w.write(f)

    class Training(Exception):
        pass

    def training(*a, **k):
        raise Training

    monkeypatch.setattr(app_fit, "_train_renderer", training)
    for video in (small, gap, demo_clip.path):
        caplog.clear()
        with pytest.raises(Training):  # the warnings come before the renderer trains
            app_fit.fit(video, tmp_path / f"p_{video.stem}", app_fit.FitConfig(steps=1), progress=False)
        small_face = [r.getMessage() for r in caplog.records if "px across" in r.getMessage()]
        no_face = [r.getMessage() for r in caplog.records if "no face in" in r.getMessage()]
        assert bool(small_face) == (video == small) and bool(no_face) == (video == gap), caplog.text
        if video == small:
            assert str(small) in small_face[0] and "needs a face of 60 px" in small_face[0]
        if video == gap:
            assert f"no face in {gap} at 1.2-2.4 s" in no_face[0]


def test_a_faceless_fit_leaves_nothing_and_names_the_users_file(tmp_path, caplog):
    from nvp.app.demo_voice import AUDIO_RATE, speech_script, synth_voice
    from nvp.app.fit import FitConfig, fit
    from nvp.errors import NoFaceError

    rng = np.random.default_rng(0)
    whole = clip_with_audio(
        tmp_path / "whole.mp4", 75, synth_voice(speech_script(3.0, rng), 3.0, rng), AUDIO_RATE
    )
    wall = tmp_path / "wall.mp4"  # cut short: its container announces more frames than it holds
    wall.write_bytes(whole.read_bytes()[: int(whole.stat().st_size * 0.8)])
    with pytest.raises(NoFaceError) as e:
        fit(wall, tmp_path / "p", FitConfig(steps=1), progress=False)
    assert str(wall) in str(e.value) and ".partial" not in str(e.value) and "target.mp4" not in str(e.value)
    cut = [r.getMessage() for r in caplog.records if "cut short" in r.getMessage()]
    assert cut and all(str(wall) in m and ".partial" not in m for m in cut), cut
    assert sorted(p.name for p in tmp_path.iterdir()) == ["wall.mp4", "whole.mp4"]  # no p.partial/ left


def test_a_dub_that_fails_on_its_input_leaves_no_parts_an_interrupted_one_keeps_them(
    fitted, tmp_path, monkeypatch, capsys
):
    from nvp.app.dub import dub, parts_folder
    from nvp.errors import MediaError
    from nvp.media import VideoWriter

    wav = tmp_path / "s.wav"
    sf.write(wav, speech(1.0), 22050)
    out = tmp_path / "o.mp4"

    def refused(self, part):
        raise MediaError(f"cannot write video '{self.path}': the encoder refused it")

    monkeypatch.setattr(VideoWriter, "append", refused)
    with pytest.raises(MediaError):
        dub(wav, fitted, out, progress=False)
    assert not parts_folder(out).exists() and not out.exists()

    def interrupted(self, part):
        raise KeyboardInterrupt

    monkeypatch.setattr(VideoWriter, "append", interrupted)
    with pytest.raises(KeyboardInterrupt):
        dub(wav, fitted, out, progress=False)
    assert (parts_folder(out) / "key.json").exists() and not out.exists()  # the next run resumes
    monkeypatch.undo()
    capsys.readouterr()
    dub(wav, fitted, out, progress=False)
    assert "(all 25 frames rendered, joining)" in capsys.readouterr().err  # not "at frame 250 of 25"
    assert out.exists() and not parts_folder(out).exists()


def test_a_dub_whose_audio_changes_before_the_join_keeps_its_parts_for_the_same_audio(
    fitted, tmp_path, monkeypatch, capsys
):
    from nvp.app.dub import DubParts, dub, parts_folder

    wav, out = tmp_path / "s.wav", tmp_path / "o.mp4"
    sf.write(wav, speech(1.0), 22050)
    kept = wav.read_bytes()
    real_write = DubParts.write

    def write_then_change(self, *a, **k):  # the join reads the audio from the file again
        real_write(self, *a, **k)
        sf.write(wav, speech(1.0, seed=1), 22050)

    monkeypatch.setattr(DubParts, "write", write_then_change)
    with pytest.raises(NvpError, match="s.wav was moved or changed while it was dubbed"):
        dub(wav, fitted, out, progress=False)
    assert (parts_folder(out) / "part-00000.mp4").exists() and not out.exists()
    monkeypatch.undo()
    wav.write_bytes(kept)
    capsys.readouterr()
    dub(wav, fitted, out, progress=False)
    assert "(all 25 frames rendered, joining)" in capsys.readouterr().err
    assert out.exists() and not parts_folder(out).exists()


def test_a_resumed_fit_says_so_and_one_left_by_another_nvp_starts_again(
    demo_clip, tmp_path, monkeypatch, capsys, caplog
):
    import json

    import tracking.track
    from nvp.app import fit as app_fit
    from nvp.provenance import code_version

    class Training(Exception):
        pass

    def training(*a, **k):
        raise Training

    tracked = []
    real_track = tracking.track.track_video
    monkeypatch.setattr(
        tracking.track, "track_video", lambda *a, **k: (tracked.append(1), real_track(*a, **k))[1]
    )
    monkeypatch.setattr(app_fit, "_train_renderer", training)
    p, cfg = tmp_path / "p", app_fit.FitConfig(steps=1)
    with pytest.raises(Training):
        app_fit.fit(demo_clip.path, p, cfg, progress=False)
    assert "resuming" not in capsys.readouterr().err
    with pytest.raises(Training):
        app_fit.fit(demo_clip.path, p, cfg, progress=False)
    err = capsys.readouterr().err
    assert "resuming the interrupted fit" in err and "target, track, style done" in err and len(tracked) == 1
    progress = partial_dir(p) / "progress.json"
    assert json.loads(progress.read_text())["nvp"] == code_version()
    old = json.loads(progress.read_text())
    progress.write_text(json.dumps({**old, "nvp": "0.0.9"}))  # left by another nvp
    with pytest.raises(Training):
        app_fit.fit(demo_clip.path, p, cfg, progress=False)
    assert "made by nvp 0.0.9; starting again" in caplog.text and len(tracked) == 2


def test_the_dub_resume_key_holds_nvps_commit_and_the_render_settings(fitted, tmp_path):
    from nvp.app.dub import _resume_key
    from nvp.provenance import code_version

    wav = tmp_path / "s.wav"
    sf.write(wav, speech(1.0), 22050)
    b = PersonBundle.load(fitted)
    key = _resume_key(wav, b, None, 25, device="cpu")
    assert key["nvp"] == code_version() and key["device"] == "cpu" and "bf16" in key
    if (Path(__file__).parents[1] / ".git").exists():
        assert "+g" in key["nvp"]  # a checkout: its commit, not only the release
    assert _resume_key(wav, b, None, 25, device="cuda") != key
    # the eyes asked for: into the lens, or a gaze file's content (not its name)
    gaze = tmp_path / "gaze.csv"
    gaze.write_text("time_s,yaw_deg,pitch_deg\n0,10,0\n")
    looked = _resume_key(wav, b, None, 25, device="cpu", gaze=gaze)
    lens = _resume_key(wav, b, None, 25, device="cpu", gaze="camera")
    assert len({str(k) for k in (key, lens, looked)}) == 3
    gaze.write_text("time_s,yaw_deg,pitch_deg\n0,20,0\n")
    assert _resume_key(wav, b, None, 25, device="cpu", gaze=gaze) != looked


def test_a_fit_of_half_a_minute_never_announces_about_0_min():
    from nvp.app.fit import FitConfig, about_minutes, expected_minutes

    assert about_minutes(0.5) == "about 1 min" and about_minutes(2.5) == "about 3 min"
    assert about_minutes(0.49) == "under a minute" and about_minutes(12.2) == "about 12 min"
    assert "about 0 min" not in expected_minutes(FitConfig(steps=200), 125)[1]  # 200 steps of 0.15 s


def test_a_fit_killed_during_tracking_goes_on_from_its_last_saved_frame(
    demo_clip, tmp_path, monkeypatch, capsys
):
    """Tracking saves its landmarks segment by segment; a rerun detects only the frames after the last
    saved one (and the few before it that its detector warms up on) and tracks exactly as an uninterrupted
    run."""
    import tracking.detect
    from nvp.app import fit as app_fit
    from nvp.media import probe_video
    from nvp.tracked import TrackedSequence
    from tracking.track import saved_frames, track_video

    class Killed(BaseException):
        pass

    class Training(Exception):
        pass

    def training(*a, **k):
        raise Training

    n = probe_video(demo_clip.path).num_frames
    monkeypatch.setattr(tracking.detect, "SEGMENT_FRAMES", 10)
    monkeypatch.setattr(tracking.detect, "count_faces", lambda *a, **k: 1)
    monkeypatch.setattr(app_fit, "_train_renderer", training)
    real = tracking.detect.LandmarkDetector.detect
    seen, kill_at = [], [25]

    def detect(self, rgb, time_s):
        frame = int(round(time_s * 25))
        if kill_at and frame >= kill_at[0]:
            raise Killed
        seen.append(frame)
        return real(self, rgb, time_s)

    monkeypatch.setattr(tracking.detect.LandmarkDetector, "detect", detect)
    p, cfg = tmp_path / "p", app_fit.FitConfig(steps=1)
    with pytest.raises(Killed):
        app_fit.fit(demo_clip.path, p, cfg, progress=False)
    work = partial_dir(p)
    assert saved_frames(work / "target.mp4", work / app_fit.TRACKING_SAVES) == (20, n)
    kill_at.clear()
    seen.clear()
    capsys.readouterr()
    with pytest.raises(Training):
        app_fit.fit(demo_clip.path, p, cfg, progress=False)
    err = capsys.readouterr().err
    assert f"tracking goes on from frame 20 of {n}" in err and err.count("resuming") == 1, err
    assert sorted(seen) == list(range(20 - tracking.detect.WARMUP_FRAMES, n))  # only the rest (+ warm-up)
    assert not (work / app_fit.TRACKING_SAVES).exists()  # removed once tracked
    resumed = TrackedSequence.load(work / "tracked")
    whole = track_video(demo_clip.path, progress=False)[0]
    for name in ("landmarks", "expression", "rotation", "translation", "identity", "valid"):
        np.testing.assert_array_equal(getattr(resumed, name), getattr(whole, name), err_msg=name)


def test_saved_tracking_of_another_video_or_nvp_is_not_resumed(demo_clip, tmp_path, monkeypatch):
    import json

    import tracking.detect
    from tracking.track import saved_frames, track_video

    monkeypatch.setattr(tracking.detect, "SEGMENT_FRAMES", 10)
    video, saves = tmp_path / "talk.mp4", tmp_path / "saves"
    shutil.copyfile(demo_clip.path, video)
    track_video(video, progress=False, saves=saves)
    done, n = saved_frames(video, saves)
    assert done == n > 0
    first = saves / "segment-00000.json"
    m = json.loads(first.read_text())
    first.write_text(json.dumps({**m, "key": {**m["key"], "nvp": "0.0.9"}}))  # left by another nvp
    assert saved_frames(video, saves)[0] == 0
    with open(video, "ab") as f:
        f.write(b"\0")  # another video by content
    assert saved_frames(video, saves)[0] == 0


def test_a_fit_whose_renderer_checkpoint_was_damaged_says_so_in_one_line(
    demo_clip, tmp_path, monkeypatch, capsys
):
    """Found by scripts/tools/drill_bundle.py: the resume line promised to go on from the checkpoint, then the
    error came as a second line; now the damaged checkpoint is the only line, naming it."""
    from nvp.app import fit as app_fit

    class Training(Exception):
        pass

    def training(builder, *a, **k):
        builder.path("renderer").mkdir(parents=True, exist_ok=True)
        (builder.path("renderer") / "checkpoint.pt").write_bytes(b"PK\x03\x04" + bytes(range(256)) * 40)
        raise Training

    monkeypatch.setattr(app_fit, "_train_renderer", training)
    p = tmp_path / "p"
    with pytest.raises(Training):
        app_fit.fit(demo_clip.path, p, app_fit.FitConfig(steps=1), progress=False)
    monkeypatch.undo()
    capsys.readouterr()
    code, err = run_cli(capsys, "fit", demo_clip.path, "-o", p, "--steps", 1)
    assert_refused((code, err), "checkpoint.pt", "damaged", "delete it")
    assert "resuming" not in err, err
