"""End to end on the tiny demo clip: fit → info → dub → verify, resuming, and clear errors."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import soundfile as sf
from test_cli import assert_one_line_error, nvp

from nvp.bundle import BundleBuilder
from nvp.face_model import default_face_model
from nvp.media import probe_video, read_audio


def speechlike(seconds: float, sr: int = 22050, seed: int = 0) -> np.ndarray:
    """Synthetic voiced speech (the demo's voice), which the voice-activity detector takes for speech."""
    from nvp.app.demo_voice import speech_script, synth_voice

    rng = np.random.default_rng(seed)
    return synth_voice(speech_script(seconds, rng), seconds, rng, sr)


@pytest.fixture(scope="module")
def bundle(demo_clip, tmp_path_factory):
    out = tmp_path_factory.mktemp("fit") / "person"
    proc = nvp("fit", demo_clip.path, "-o", out, "--steps", 2)
    assert proc.returncode == 0, proc.stderr
    assert "person bundle" in proc.stdout
    return out


def test_fit_writes_a_complete_bundle(bundle):
    m = json.loads((bundle / "bundle.json").read_text())
    assert m["format"] == "nvp.person_bundle" and m["version"] == 1
    assert set(m["stages"]) == {"target", "track", "style", "renderer", "register", "mouths"}
    # the tracking is registered to the renderer (renderer.register); the tracker's own output is gone
    tracked = json.loads((bundle / "tracked" / "tracked.json").read_text())
    assert tracked["info"]["registration"] == {
        k: m["stages"]["register"][k] for k in tracked["info"]["registration"]
    }
    assert not (bundle / "tracked_unregistered").exists()
    assert (bundle / "renderer" / "renderer.json").exists() and (bundle / "style.json").exists()
    # the demo talker opens its mouth: its open-mouth frames make a mouth bank next to the renderer
    assert m["stages"]["mouths"]["entries"] > 0 and (bundle / "renderer" / "mouths.json").exists()
    assert not (bundle / "renderer" / "checkpoint.pt").exists()
    assert not bundle.with_name("person.partial").exists()
    proc = nvp("info", bundle)
    assert "mouth-opening model: calibrated" in proc.stdout and "mouths: " in proc.stdout
    assert "eyes: iris" in proc.stdout and "too small to turn" in proc.stdout  # 256²: irises under 6 px
    assert proc.returncode == 0 and "renderer preset: cpu" in proc.stdout, proc.stderr


@pytest.mark.parametrize(("seconds", "channels"), [(0.8, 1), (1.7, 2), (0.8, 6)])
def test_dub_lasts_as_long_as_the_audio_and_is_marked(bundle, demo_clip, tmp_path, seconds, channels):
    audio = speechlike(seconds)
    if channels > 1:
        audio = np.stack([audio * (1 - 0.1 * c) for c in range(channels)], 1)
    wav = tmp_path / "speech.wav"
    sf.write(wav, audio, 22050)
    out = tmp_path / "dub.mp4"
    proc = nvp("dub", wav, "--person", bundle, "-o", out)
    assert proc.returncode == 0, proc.stderr
    info = probe_video(out)
    fps = 25.0
    assert abs(info.num_frames - seconds * fps) <= 1  # longer than the 1.2 s target: ping-pong
    assert (info.width, info.height) == (256, 256) and info.audio_sample_rate == 22050
    back = read_audio(out, None, mono=False)
    assert back.ndim == (1 if channels == 1 else 2) and (channels == 1 or back.shape[1] == channels)
    proc = nvp("verify", out)
    assert proc.returncode == 0 and "SYNTHETIC" in proc.stdout
    assert nvp("verify", demo_clip.path).returncode == 0  # the demo target is synthetic too


def test_dub_turns_only_the_eyes_where_asked_and_a_bad_gaze_file_is_one_error(bundle, tmp_path, monkeypatch):
    import renderer.eyes
    from nvp.app.dub import dub
    from nvp.media import iter_frames
    from nvp.tracked import TrackedSequence

    wav = tmp_path / "speech.wav"
    sf.write(wav, speechlike(0.8), 22050)
    aside = tmp_path / "aside.json"
    aside.write_text(json.dumps([{"time_s": 0, "yaw_deg": 25, "pitch_deg": 0}]))
    made = {}
    for name, gaze in {"today": [], "footage": ["--gaze", "footage"], "small": ["--gaze", aside]}.items():
        proc = nvp("dub", wav, "--person", bundle, "-o", tmp_path / f"{name}.mp4", *gaze)
        assert proc.returncode == 0, proc.stderr
        made[name] = np.stack(list(iter_frames(tmp_path / f"{name}.mp4"))).astype(int)
    np.testing.assert_array_equal(made["footage"], made["today"])  # the default is today's dub
    # the demo's eyes (256² footage) are too small to turn: the dub says so and leaves them
    assert "eyes are small" in proc.stderr
    # turned anyway, 25 degrees to the side move the irises; away from the eyes only the encoder's noise
    monkeypatch.setattr(renderer.eyes, "MIN_IRIS_PX", 0.0)
    dub(wav, bundle, tmp_path / "aside.mp4", progress=False, gaze=aside)
    made["aside"] = np.stack(list(iter_frames(tmp_path / "aside.mp4"))).astype(int)
    seq = TrackedSequence.load(bundle / "tracked")
    model = default_face_model()
    eyes = np.zeros(made["today"].shape[1:3], bool)
    for g in ("left_eye", "right_eye"):
        pts = seq.landmarks[:, model.landmark_groups[g]].reshape(-1, 2)
        (x0, y0), (x1, y1) = np.floor(pts.min(0)).astype(int) - 8, np.ceil(pts.max(0)).astype(int) + 8
        eyes[max(y0, 0) : y1, max(x0, 0) : x1] = True
    change = np.abs(made["aside"] - made["today"]).max(-1)
    assert change[:, eyes].max() > 40, change[:, eyes].max()
    assert np.percentile(change[:, ~eyes], 99) < 8 and change[:, ~eyes].mean() < 1
    proc = nvp("verify", tmp_path / "aside.mp4", "--json")
    assert "aside.json" in proc.stdout, proc.stdout  # the output says where its eyes were turned to look
    for text, says in [("time_s,yaw_deg\n0,5\n", "pitch_deg"), ("time_s,yaw_deg,pitch_deg\n0,90,0\n", "45")]:
        aside.with_suffix(".csv").write_text(text)
        proc = nvp(
            "dub", wav, "--person", bundle, "-o", tmp_path / "x.mp4", "--gaze", aside.with_suffix(".csv")
        )
        assert_one_line_error(proc, says)
        assert not (tmp_path / "x.mp4").exists()


def test_a_camera_video_is_not_marked(tmp_path):
    import av

    path = tmp_path / "camera.mp4"
    with av.open(str(path), "w") as c:
        s = c.add_stream("libx264", rate=25)
        s.width, s.height, s.pix_fmt = 64, 64, "yuv420p"
        for _ in range(5):
            c.mux(s.encode(av.VideoFrame.from_ndarray(np.zeros((64, 64, 3), np.uint8), format="rgb24")))
        c.mux(s.encode(None))
    proc = nvp("verify", path, "--json")
    assert proc.returncode == 1 and json.loads(proc.stdout)["synthetic"] is False


def test_dub_errors_are_one_line(bundle, tmp_path):
    silent = tmp_path / "silent.wav"
    sf.write(silent, np.zeros(16000, np.float32), 16000)
    proc = nvp("dub", silent, "--person", bundle, "-o", tmp_path / "x.mp4")
    assert_one_line_error(proc, "no speech")
    assert not (tmp_path / "x.mp4").exists()
    proc = nvp("dub", silent, "--person", tmp_path / "nobody", "-o", tmp_path / "x.mp4")
    assert_one_line_error(proc, "not a person bundle")
    (tmp_path / "notes.wav").write_text("not audio")
    proc = nvp("dub", tmp_path / "notes.wav", "--person", bundle, "-o", tmp_path / "x.mp4")
    assert_one_line_error(proc, "notes.wav")
    assert not (tmp_path / "x.mp4").exists()


def test_fit_resumes_after_an_interruption(demo_clip, tmp_path, monkeypatch):
    import tracking.track
    from nvp.app import fit as pipeline

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "_train_renderer", interrupted)
    cfg = pipeline.FitConfig(steps=2)
    with pytest.raises(KeyboardInterrupt):
        pipeline.fit(demo_clip.path, tmp_path / "p", cfg, progress=False)
    assert not (tmp_path / "p").exists()
    progress = json.loads((tmp_path / "p.partial" / "progress.json").read_text())
    assert set(progress["stages"]) == {"target", "track", "style"}
    monkeypatch.undo()

    def no_tracking(*a, **k):
        raise AssertionError("tracking should not run again")

    monkeypatch.setattr(tracking.track, "track_video", no_tracking)
    bundle = pipeline.fit(demo_clip.path, tmp_path / "p", cfg, progress=False)
    assert bundle.root == tmp_path / "p" and (tmp_path / "p" / "bundle.json").exists()
    with pytest.raises(Exception, match="other settings"):
        BundleBuilder(tmp_path / "q", {"preset": "cpu"})
        BundleBuilder(tmp_path / "q", {"preset": "quality"})


def test_a_fit_trains_footage_in_several_lights_longer_and_says_so(demo_clip, tmp_path, monkeypatch, caplog):
    import renderer.train
    import renderer.train_data
    from nvp.app import fit as pipeline

    budgets = []

    def training(cache, tcfg, *a, **k):  # note the time the fit gives the renderer, then stop
        budgets.append(tcfg.budget_s)
        raise KeyboardInterrupt

    monkeypatch.setattr(renderer.train, "train_renderer", training)
    for share in (0.0, 0.3):
        monkeypatch.setattr(renderer.train_data, "varied_light", lambda cache, share=share: share)
        with pytest.raises(KeyboardInterrupt):
            pipeline.fit(demo_clip.path, tmp_path / "p", pipeline.FitConfig(), progress=False)
    assert budgets == [5 * 60, 15 * 60]  # one take: 5 minutes; a third in another light: 15
    said = [r.getMessage() for r in caplog.records if "another light" in r.getMessage()]
    assert len(said) == 1 and "30 % of the footage" in said[0] and "15 minutes instead of 5" in said[0]


def test_an_interrupted_registration_starts_again_from_the_trackers_output(demo_clip, tmp_path, monkeypatch):
    import renderer.register
    from nvp.app import fit as pipeline
    from nvp.tracked import TrackedSequence

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(renderer.register, "registration_offsets", interrupted)
    cfg = pipeline.FitConfig(steps=2)
    with pytest.raises(KeyboardInterrupt):
        pipeline.fit(demo_clip.path, tmp_path / "p", cfg, progress=False)
    work = tmp_path / "p.partial"
    tracker = TrackedSequence.load(work / "tracked")
    np.testing.assert_array_equal(
        TrackedSequence.load(work / "tracked_unregistered").translation, tracker.translation
    )

    def constant(renderer_dir, video, seq, indices, *a, **k):
        return np.tile([0.5, -0.25], (len(indices), 1))

    monkeypatch.setattr(renderer.register, "registration_offsets", constant)
    original = BundleBuilder.mark_done

    def dies_after_saving(self, stage, **facts):  # registered tracking written, the stage not yet marked
        if stage == "register":
            raise KeyboardInterrupt
        original(self, stage, **facts)

    monkeypatch.setattr(BundleBuilder, "mark_done", dies_after_saving)
    with pytest.raises(KeyboardInterrupt):
        pipeline.fit(demo_clip.path, tmp_path / "p", cfg, progress=False)
    monkeypatch.setattr(BundleBuilder, "mark_done", original)
    bundle = pipeline.fit(demo_clip.path, tmp_path / "p", cfg, progress=False)
    # moved once from the tracker's output, not twice
    out = TrackedSequence.load(bundle.path("tracked"))
    model = default_face_model()
    frames = np.arange(out.num_frames)[tracker.valid]
    moved = out.pixels(out.camera_vertices(model, frames)) - tracker.pixels(
        tracker.camera_vertices(model, frames)
    )
    np.testing.assert_allclose(moved.mean(1), np.tile([0.5, -0.25], (len(frames), 1)), atol=0.01)
    assert not (tmp_path / "p" / "tracked_unregistered").exists()


def test_fit_needs_audio(tmp_path):
    from nvp.media import VideoWriter

    path = tmp_path / "mute.mp4"
    with VideoWriter(path, 25, 64, 64) as w:
        for _ in range(5):
            w.write(np.zeros((64, 64, 3), np.uint8))
    proc = nvp("fit", path, "-o", tmp_path / "p")
    assert_one_line_error(proc, "no audio")
    assert not (tmp_path / "p").exists() and not (tmp_path / "p.partial").exists()


def test_say_speaks_text_offline_and_marks_how(bundle, tmp_path):
    pytest.importorskip("piper", reason="the optional tts extra is not installed")
    from nvp.provenance import verify

    out, wav = tmp_path / "say.mp4", tmp_path / "s.wav"
    proc = nvp("say", "Hi there.", "--person", bundle, "-o", out, "--wav", wav)
    assert proc.returncode == 0, proc.stderr
    speech = read_audio(wav, None)
    assert abs(probe_video(out).num_frames - len(speech) / 22050 * 25) <= 1
    assert verify(out).tags["nvp_speech"] == "text to speech (piper, voice joe_us)"
    listed = nvp("say", "--list-voices")
    assert listed.returncode == 0 and listed.stdout.startswith("joe_us\t")
    assert_one_line_error(nvp("say", "Hi.", "--person", bundle, "-o", out, "--voice", "nobody"), "joe_us")
    assert_one_line_error(nvp("say", "   ", "--person", bundle, "-o", out), "empty")
    assert_one_line_error(nvp("say", "Hi.", "-o", out), "--person")


def test_say_with_a_voice_file_and_the_espeak_fallback(tmp_path, monkeypatch):
    from nvp import tts
    from nvp.errors import NvpError

    pytest.importorskip("piper", reason="the optional tts extra is not installed")
    _, model, config = tts.voice_files(None)
    mine = tmp_path / "my-voice.onnx"
    mine.symlink_to(model)
    (tmp_path / "my-voice.onnx.json").symlink_to(config)
    speech = tts.synthesize("Yes.", voice=str(mine), length_scale=1.5)
    assert (speech.engine, speech.voice, speech.rate) == ("piper", "my-voice", 22050)
    assert 0.2 < speech.seconds < 3 and np.abs(speech.audio).max() > 0.05
    with pytest.raises(NvpError, match="onnx.json"):
        (tmp_path / "my-voice.onnx.json").unlink()
        tts.synthesize("Yes.", voice=str(mine))
    # without piper: espeak-ng when it is installed, else one clear message naming both
    monkeypatch.setattr(tts, "have_piper", lambda: False)
    if tts.espeak_program():
        speech = tts.synthesize("Hello there.")
        assert speech.engine == "espeak-ng" and speech.seconds > 0.3
    monkeypatch.setattr(tts, "espeak_program", lambda: None)
    with pytest.raises(NvpError, match="nvp\\[tts\\].*espeak-ng"):
        tts.synthesize("Hello there.")
    with pytest.raises(NvpError, match="piper is not installed"):
        tts.synthesize("Hello there.", engine="piper")


def test_dub_in_another_persons_style(bundle, tmp_path):
    from nvp.person import PersonStyle
    from nvp.provenance import verify

    own = PersonStyle.load(bundle / "style.json")
    wide = PersonStyle(
        own.person_map.__class__(3 * own.person_map.matrix, own.person_map.bias + 0.5),
        own.rest_expression + 0.5,
        own.feature_kind,
        own.audio2exp_sha256,
        {"video": "other.mp4"},
        None,
    )
    other = tmp_path / "other_style"
    wide.save(other)
    wav = tmp_path / "speech.wav"
    sf.write(wav, speechlike(0.8), 22050)
    out = tmp_path / "styled.mp4"
    proc = nvp("dub", wav, "--person", bundle, "-o", out, "--style", other.with_suffix(".json"))
    assert proc.returncode == 0, proc.stderr
    assert verify(out).tags["nvp_style"] == "other.mp4"
    assert_one_line_error(
        nvp("dub", wav, "--person", bundle, "-o", out, "--style", tmp_path / "no"), "not found"
    )


def test_eval_needs_audio_and_enough_frames(tmp_path, demo_clip):
    from nvp.media import VideoWriter

    path = tmp_path / "mute.mp4"
    with VideoWriter(path, 25, 64, 64) as w:
        for _ in range(5):
            w.write(np.zeros((64, 64, 3), np.uint8))
    assert_one_line_error(nvp("eval", path, "-o", tmp_path / "e"), "no audio")
    proc = nvp("eval", demo_clip.path, "-o", tmp_path / "e2", "--steps", 1)
    assert_one_line_error(proc, "held-out part is only")
    # several videos: each failure is one line, the others still run, and the exit code says so
    proc = nvp("eval", path, demo_clip.path, "-o", tmp_path / "e3", "--steps", 1)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "no audio" in proc.stderr and "held-out part is only" in proc.stderr
    assert not (tmp_path / "e3" / "results.md").exists()


def test_dub_checks_its_output_before_any_work(bundle, tmp_path, monkeypatch):
    from nvp import artifact
    from nvp.app.cli import main

    audio = tmp_path / "speech.wav"
    sf.write(audio, speechlike(0.8), 22050)
    before = audio.read_bytes()
    assert_one_line_error(nvp("dub", audio, "--person", bundle, "-o", audio), "also an input")
    assert audio.read_bytes() == before
    folder = tmp_path / "already_a_folder"
    folder.mkdir()
    assert_one_line_error(nvp("dub", audio, "--person", bundle, "-o", folder), "is a folder")
    # a folder where no file can be made: one line, nothing rendered
    monkeypatch.setattr("nvp.app.dub.PersonBundle.load", lambda *a, **k: pytest.fail("work before the check"))
    if os.path.isdir("/proc/self"):  # permissions say yes, yet no file can be made there
        assert main(["-q", "dub", str(audio), "--person", str(bundle), "-o", "/proc/nvp_dub.mp4"]) == 2
    # a read-only folder (simulated: root may write anywhere)
    monkeypatch.setattr(artifact.os, "access", lambda *a: False)
    assert main(["-q", "dub", str(audio), "--person", str(bundle), "-o", str(tmp_path / "ro" / "x.mp4")]) == 2


def test_predict_into_a_folder_leaves_no_temporary_file(bundle, tmp_path):
    audio = tmp_path / "speech.wav"
    sf.write(audio, speechlike(0.8), 22050)
    out = tmp_path / "out"
    out.mkdir()
    proc = nvp("predict", audio, "--style", bundle / "style.json", "-o", out)
    assert_one_line_error(proc, "is a folder")
    assert not list(tmp_path.rglob(".*tmp*"))


def test_a_killed_dub_leaves_no_temporary_file_behind(bundle, tmp_path):
    import contextlib
    import os
    import signal
    import subprocess
    import sys
    import time

    audio = tmp_path / "speech.wav"
    sf.write(audio, speechlike(6.0), 22050)
    out = tmp_path / "dub.mp4"
    cmd = [
        sys.executable,
        "-m",
        "nvp.app.cli",
        "-q",
        "dub",
        str(audio),
        "--person",
        str(bundle),
        "-o",
        str(out),
    ]
    p = subprocess.Popen(cmd)
    deadline = time.time() + 60
    writing = tmp_path / ".dub.mp4.nvp-parts"  # the video is written in parts there first
    while not list(writing.glob(".part-*.tmp.mp4")) and time.time() < deadline and p.poll() is None:
        time.sleep(0.05)
    with contextlib.suppress(ProcessLookupError):
        os.kill(p.pid, signal.SIGKILL)
    p.wait()
    assert p.returncode == -signal.SIGKILL, "the dub ended before it could be killed"
    assert list(writing.glob(".part-*.tmp.mp4"))
    proc = nvp("dub", audio, "--person", bundle, "-o", out)
    assert proc.returncode == 0, proc.stderr
    assert out.exists() and not list(tmp_path.glob(".dub*tmp*")) and not list(tmp_path.glob(".dub*parts"))


def test_an_interrupted_dub_resumes_at_its_first_unfinished_part(bundle, tmp_path, monkeypatch, caplog):
    from nvp.app import dub as dubbing
    from nvp.errors import NvpError
    from nvp.media import VideoWriter, iter_frames

    monkeypatch.setenv("NVP_THREADS", "1")  # the same arithmetic in every run
    monkeypatch.setattr(dubbing, "PART_FRAMES", 10)
    audio, other = tmp_path / "speech.wav", tmp_path / "other.wav"
    sf.write(audio, speechlike(1.7), 22050)  # 43 frames: parts of 10, 10, 10, 10 and 3
    sf.write(other, speechlike(1.7, seed=1), 22050)
    whole = dubbing.dub(audio, bundle, tmp_path / "whole.mp4", progress=False)
    assert whole.rendered == whole.frames == 43
    out, parts = tmp_path / "dub.mp4", tmp_path / ".dub.mp4.nvp-parts"
    write = VideoWriter.write

    def interrupt(after: int):
        calls = []

        def writing(self, frame):
            calls.append(1)
            if len(calls) > after:
                raise KeyboardInterrupt
            write(self, frame)

        monkeypatch.setattr(VideoWriter, "write", writing)

    interrupt(25)
    with pytest.raises(KeyboardInterrupt):
        dubbing.dub(audio, bundle, out, progress=False)
    assert not out.exists() and not list(tmp_path.glob(".dub*tmp*"))
    assert sorted(p.name for p in parts.iterdir()) == [
        "key.json",
        "part-00000.json",
        "part-00000.mp4",
        "part-00001.json",
        "part-00001.mp4",
    ]  # the third part's temporary file is gone
    interrupt(10)  # resumed and interrupted again: one more part
    with pytest.raises(KeyboardInterrupt):
        dubbing.dub(audio, bundle, out, progress=False)
    assert len(list(parts.glob("part-*.mp4"))) == 3
    monkeypatch.setattr(VideoWriter, "write", write)
    r = dubbing.dub(audio, bundle, out, progress=False)
    assert (r.frames, r.rendered) == (43, 13) and not parts.exists()
    # the same frames as the dub that ran through (the mouth-bank choice goes on where it stopped)
    assert all(np.array_equal(a, b) for a, b in zip(iter_frames(out), iter_frames(whole.output), strict=True))
    assert np.array_equal(read_audio(out, 22050), read_audio(whole.output, 22050))
    # parts of other audio are not resumed
    interrupt(25)
    with pytest.raises(KeyboardInterrupt):
        dubbing.dub(audio, bundle, out, progress=False)
    monkeypatch.setattr(VideoWriter, "write", write)
    r = dubbing.dub(other, bundle, out, progress=False)
    assert r.rendered == r.frames and "interrupted dub of other input" in caplog.text

    # a dub that fails before its first part leaves no folder behind
    def no_renderer(*args, **kwargs):
        raise OSError("no OpenGL context")

    monkeypatch.setattr("renderer.render.FrameRenderer.__init__", no_renderer)
    with pytest.raises(OSError, match="OpenGL"):
        dubbing.dub(audio, bundle, out, progress=False)
    assert not parts.exists()
    monkeypatch.undo()
    # one holding only the temporary key of a dub killed as it began is nvp's own
    parts.mkdir()
    (parts / ".key.json.123.tmp.json").write_text("{")
    assert dubbing.dub(audio, bundle, out, progress=False).rendered == 43 and not parts.exists()
    # a folder of that name that nvp did not make is left alone
    parts.mkdir()
    (parts / "notes.txt").write_text("mine")
    with pytest.raises(NvpError, match="not made by nvp dub"):
        dubbing.dub(audio, bundle, out, progress=False)
    assert (parts / "notes.txt").exists()


def test_an_error_under_a_progress_bar_gets_a_line_of_its_own(capsys):
    from tqdm import tqdm

    from nvp.app.cli import _fail

    bar = tqdm(total=10, desc="dub")
    bar.update(3)
    assert _fail("dub", "error: boom", 2) == 2
    err = capsys.readouterr().err
    assert "\nnvp dub: error: boom\n" in err  # the bar's line was ended first
    assert bar.disable or bar.n == 3


def test_predict_exports_a_gltf_animation_that_reads_back_and_renders(bundle, tmp_path):
    import pygltflib

    from nvp.gltf import CM_TO_GLTF, read_glb
    from renderer.gl import GLRasterizer

    wav = tmp_path / "speech.wav"
    sf.write(wav, speechlike(1.2), 22050)
    glb, npz = tmp_path / "anim.glb", tmp_path / "p.npz"
    proc = nvp("predict", wav, "--style", bundle, "--fps", 30, "--export", glb, "-o", npz)
    assert proc.returncode == 0, proc.stderr
    with np.load(npz) as z:
        expected, expression = z["vertices"], z["expression"]
    # a maintained glTF reader sees one mesh with 64 morph targets and a weights animation at 30 fps
    g = pygltflib.GLTF2().load(str(glb))
    assert g.asset.version == "2.0" and len(g.meshes[0].primitives[0].targets) == 64
    channel = g.animations[0].channels[0]
    assert channel.target.path == "weights" and g.animations[0].samplers[0].interpolation == "LINEAR"
    times = g.accessors[g.animations[0].samplers[0].input]
    assert times.count == len(expected) == 36 and times.max[0] == pytest.approx(35 / 30)
    anim = read_glb(glb)
    assert anim.fps == pytest.approx(30, rel=1e-4) and "first audio sample" in anim.info["timing"]
    np.testing.assert_allclose(anim.weights, expression, atol=1e-6)
    for j in (
        0,
        17,
        35,
    ):  # the loaded animation's vertices are predict's mesh, in metres, y up, z to the viewer
        np.testing.assert_allclose(anim.vertices(j), expected[j] * CM_TO_GLTF, atol=1e-6)
    # the front faces are counter-clockwise seen from +Z, as glTF wants
    v, f = anim.base, anim.triangles
    normal_z = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])[:, 2]
    assert (normal_z > 0).mean() > 0.9
    # rendered with nvp's rasterizer (back in the camera frame, 40 cm away), it covers the same pixels
    with GLRasterizer(96, 96) as gl:
        for j in (0, 35):
            cam = [anim.vertices(j) / CM_TO_GLTF, expected[j]]
            masks = [
                gl.rasterize(c + [0, 0, 40], f, np.zeros((len(c), 2)), 150.0, [48, 48]).mask for c in cam
            ]
            assert masks[0].sum() > 1000 and bool((masks[0] == masks[1]).all())
    # the eyes: two nodes under the face, behind the eye openings, looking ahead ("camera", the default)
    assert [n.name for n in g.nodes] == ["face", "eye_left", "eye_right"] and g.nodes[0].children == [1, 2]
    assert anim.eyes[0, 0] > 0 > anim.eyes[1, 0] and np.all(anim.eyes[:, 2] < anim.base[:, 2].max())
    np.testing.assert_allclose(anim.gaze, 0, atol=1e-6)
    # ... or where a gaze file says, interpolated between its samples
    gaze = tmp_path / "gaze.csv"
    gaze.write_text("time_s,yaw_deg,pitch_deg\n0.0,0,0\n1.0,20,-10\n")
    proc = nvp("predict", wav, "--style", bundle, "--fps", 30, "--export", glb, "--gaze", gaze)
    assert proc.returncode == 0, proc.stderr
    looked = np.degrees(read_glb(glb).gaze)
    np.testing.assert_allclose(looked[[0, 15, 30, 35]], [[0, 0], [10, -5], [20, -10], [20, -10]], atol=1e-3)
    gaze.write_text("time_s,yaw_deg\n0,0\n")
    assert_one_line_error(
        nvp("predict", wav, "--style", bundle, "--export", glb, "--gaze", gaze), "pitch_deg"
    )
    assert_one_line_error(nvp("predict", wav, "--style", bundle, "--export", tmp_path / "a.gltf"), ".glb")
    assert_one_line_error(nvp("predict", wav, "--style", bundle), "--export")


def test_a_person_fitted_before_the_opening_model_still_dubs_and_says_so(bundle, monkeypatch, caplog):
    import dataclasses
    import logging

    from nvp.app import dub as dub_module
    from nvp.bundle import PersonBundle
    from nvp.person import PersonStyle

    load = PersonStyle.load

    def older(path):
        style = load(path)
        info = {k: v for k, v in style.info.items() if k != "opening"}
        return dataclasses.replace(style, opening=None, info=info)

    monkeypatch.setattr(PersonStyle, "load", older)
    with caplog.at_level(logging.WARNING):
        person = dub_module.load_person(PersonBundle.load(bundle))
    assert person.style.opening is None and "mouth-opening model" in caplog.text
    caplog.clear()
    monkeypatch.setattr(PersonStyle, "load", load)
    with caplog.at_level(logging.WARNING):
        assert dub_module.load_person(PersonBundle.load(bundle)).style.opening is not None
    assert "mouth-opening" not in caplog.text


@pytest.mark.parametrize("opening_model", [0, 1])
def test_expression_stream_is_causal_and_follows_whole_file_prediction(bundle, opening_model):
    """Both shipped opening models: Whisper's features from the stream's shorter opening context, and the
    earlier phonetic model's from the recogniser's pass (a person fitted before keeps streaming)."""
    import dataclasses

    from nvp.audio2exp import default_audio2exp
    from nvp.face_model import default_face_model
    from nvp.opening import SHIPPED_PATHS, OpeningModel
    from nvp.person import PersonStyle, predict_expressions
    from nvp.stream import ExpressionStream
    from nvp.windows import num_video_frames

    style = PersonStyle.load(bundle / "style.json")
    assert style.opening is not None  # nvp fit calibrated the opening model: the stream uses it too
    sha = OpeningModel.load(SHIPPED_PATHS[opening_model]).sha256
    style = dataclasses.replace(style, opening=dataclasses.replace(style.opening, model_sha256=sha))
    net, _ = default_audio2exp(style.feature_kind)
    audio = speechlike(6.0, 16000, seed=3)
    whole = predict_expressions(audio, 16000, 25.0, style, net)
    stream = ExpressionStream(style, net, 25.0, lookahead_s=0.4)
    parts = []
    for i in range(0, len(audio), 3200):
        parts.append(stream.push(audio[i : i + 3200]))
        # a frame comes out only once its audio and the look-ahead are in
        assert stream.done == num_video_frames(max(0.0, stream.received / 16000 - 0.4), 25.0)
    parts.append(stream.finish())
    live = np.concatenate(parts)
    assert live.shape == whole.shape == (num_video_frames(6.0, 25.0), whole.shape[1])
    model = default_face_model()
    ident = np.zeros(model.num_id, np.float32)
    g_live, g_whole = model.inner_lip_gap(ident, live), model.inner_lip_gap(ident, whole)
    assert np.corrcoef(g_live, g_whole)[0, 1] > 0.8


def test_long_audio_in_blocks_holds_one_block_and_follows_whole_file_prediction(bundle):
    """``nvp dub``'s expressions of long audio (nvp.long_audio): audio within one block is predicted
    exactly as a whole; longer audio block by block, holding at most a block and its context, close to
    whole-file prediction; its speech counted as nvp.vad.speech_activity counts it."""
    from nvp.audio2exp import default_audio2exp
    from nvp.long_audio import BlockedExpressions
    from nvp.person import PersonStyle, predict_expressions
    from nvp.vad import speech_activity

    style = PersonStyle.load(bundle / "style.json")
    net, _ = default_audio2exp(style.feature_kind)
    rng = np.random.default_rng(5)
    audio = np.concatenate([np.zeros(16000, np.float32), speechlike(7.0, 16000, seed=4)])
    whole = predict_expressions(audio, 16000, 25.0, style, net, num_frames=201)

    def blocked(block_s: float, context_s: float) -> tuple[np.ndarray, BlockedExpressions, int]:
        stream, held = BlockedExpressions(style, net, 25.0, block_s=block_s, context_s=context_s), 0
        at = 0
        while at < len(audio):
            piece = int(rng.integers(100, 4000))
            stream.push(audio[at : at + piece])
            held, at = max(held, stream.held), at + piece
        return stream.finish(201), stream, held

    one, stream, _ = blocked(8.0, 1.0)  # 8 s of audio: one block, the whole file's prediction exactly
    assert np.array_equal(one, whole) and stream.has_speech() == speech_activity(audio, 16000) is True
    parts, stream, held = blocked(2.0, 1.0)  # four blocks
    assert parts.shape == whole.shape and stream.has_speech()
    assert held <= (2.0 + 2 * 1.0) * 16000 + 4000  # a block, its context on both sides, one piece
    model = default_face_model()
    ident = np.zeros(model.num_id, np.float32)
    gap_parts, gap_whole = model.inner_lip_gap(ident, parts), model.inner_lip_gap(ident, whole)
    assert np.corrcoef(gap_parts, gap_whole)[0, 1] > 0.9
    silent = BlockedExpressions(style, net, 25.0, block_s=2.0, context_s=1.0)
    silent.push(np.zeros(6 * 16000, np.float32))
    assert silent.finish().shape == (150, whole.shape[1]) and not silent.has_speech()


def test_live_dubs_a_stream_in_real_time_and_to_a_pipe(bundle, tmp_path):
    import subprocess
    import sys

    from nvp.app.live import BLOCK_S, live
    from nvp.provenance import verify

    wav = tmp_path / "speech.wav"
    sf.write(wav, speechlike(5.0), 22050)
    out = tmp_path / "live.mp4"
    r = live(wav, bundle, out, realtime=True)
    assert r.frames == 125 and probe_video(out).num_frames == 125  # 5 s at 25 fps
    assert 0 <= len(read_audio(out, 16000)) / 16000 - 5.0 < 0.1  # + the last AAC frame, untrimmed
    assert r.seconds >= 5.0 - BLOCK_S  # played at the pace of the audio
    # no frame is shown before its audio and the look-ahead have arrived (the last ones: at the end)
    assert r.latency_s[:-15].min() >= r.lookahead_s - BLOCK_S
    assert verify(out).tags["nvp_kind"] == "live"
    # raw PCM in on stdin, raw RGB frames out on stdout, with eye contact
    pcm = (np.clip(speechlike(2.0, 16000), -1, 1) * 32767).astype("<i2").tobytes()
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "nvp.app.cli",
            "-q",
            "live",
            "-",
            "--person",
            bundle,
            "--raw",
            "--gaze",
            "camera",
        ],
        input=pcm,
        capture_output=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr.decode()
    assert len(proc.stdout) == 50 * 256 * 256 * 3 and b"frames dropped" in proc.stderr
    assert_one_line_error(nvp("live", tmp_path / "none.wav", "--person", bundle, "-o", out), "no such")
    assert_one_line_error(nvp("live", wav, "--person", bundle), "--raw")
    (tmp_path / "gaze.csv").write_text("time_s,yaw_deg,pitch_deg\n0,60,0\n")
    proc = nvp("live", wav, "--person", bundle, "-o", tmp_path / "x.mp4", "--gaze", tmp_path / "gaze.csv")
    assert_one_line_error(proc, "45")
    (tmp_path / "gaze.csv").write_text("time_s,yaw_deg,pitch_deg\n0,10,0\n4,-10,5\n")
    r = live(wav, bundle, tmp_path / "looked.mp4", realtime=False, gaze=tmp_path / "gaze.csv")
    assert r.frames == 125 and verify(tmp_path / "looked.mp4").tags.get("nvp_gaze") == "gaze.csv"
    assert r.dropped == 0  # as fast as it can: the file "arrived" at once, but no frame is late for a clock
    # a slower stream: every other footage frame and expression, the same length
    half = tmp_path / "half.mp4"
    r = live(wav, bundle, half, realtime=False, fps=12.5)
    assert r.fps == 12.5 and r.frames == 63 and probe_video(half).num_frames == 63  # frames 0, 2, …, 124
    assert abs(probe_video(half).duration_s - probe_video(out).duration_s) < 0.1  # as long as at 25 fps
    assert_one_line_error(nvp("live", wav, "--person", bundle, "-o", half, "--fps", "50"), "--fps")


def test_batch_dub_of_ten_files_goes_on_past_a_failing_one(bundle, tmp_path):
    names = []
    for i in range(10):
        wav = tmp_path / f"line{i:02d}.wav"
        noise = (0.3 * np.random.default_rng(i).standard_normal(16000)).astype(np.float32)
        sf.write(wav, noise if i == 4 else speechlike(1.0, seed=i), 22050 if i != 4 else 16000)
        names.append(wav.name)
    (tmp_path / "lines.txt").write_text("# the episode's lines\n" + "\n".join(names[3:]) + "\n")
    out = tmp_path / "dubbed"
    proc = nvp(
        "dub",
        *[tmp_path / n for n in names[:3]],
        "--list",
        tmp_path / "lines.txt",
        "--person",
        bundle,
        "-o",
        out,
    )
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.count("error") == 1 and "line04.wav" in proc.stderr and "no speech" in proc.stderr
    made = sorted(p.name for p in out.glob("*.mp4"))
    assert made == [f"line{i:02d}.mp4" for i in range(10) if i != 4]
    assert "9 of 10 dubbed" in proc.stdout
    assert_one_line_error(
        nvp("dub", *[tmp_path / n for n in names[:2]], "--person", bundle, "-o", tmp_path / "x.mp4"), "folder"
    )


def test_a_fit_without_flags_ends_on_its_own_and_says_how_long_it_takes():
    from nvp.app.fit import FitConfig, expected_minutes, renderer_minutes, renderer_steps
    from renderer.preset import get_preset

    assert renderer_minutes(FitConfig()) == 5  # the cpu preset's default time on a CPU ...
    assert renderer_minutes(FitConfig(), varied=True) == 15  # ... footage in several lights: longer ...
    assert renderer_steps(FitConfig()) == get_preset("cpu").steps  # ... or its steps, whichever ends first
    assert renderer_minutes(FitConfig(preset="quality")) == 45
    assert renderer_minutes(FitConfig(budget_minutes=7)) == 7
    assert renderer_minutes(FitConfig(budget_minutes=7), varied=True) == 7  # the user's time decides
    assert renderer_steps(FitConfig(budget_minutes=7)) is None  # the time alone decides
    assert renderer_minutes(FitConfig(steps=100)) is None  # steps given: steps decide
    assert renderer_steps(FitConfig(steps=100, budget_minutes=7)) == 100  # both: whichever ends first
    assert renderer_minutes(FitConfig(device="cuda")) is None  # a GPU runs the preset's steps
    total, parts = expected_minutes(FitConfig(), 3000)  # 2 minutes of 25 fps footage
    assert 7 < total < 11  # the minutes end before 8,000 steps
    assert "renderer training 5 min, 15 if the footage shows the face in several lights" in parts
    per_step = get_preset("cpu").step_seconds
    total, parts = expected_minutes(FitConfig(steps=3600), 3000)
    assert f"renderer training about {3600 * per_step / 60:.0f} min (3,600 steps)" in parts
    assert 1 + 3600 * per_step / 60 < total < 5 + 3600 * per_step / 60
    parts = expected_minutes(FitConfig(steps=3600, budget_minutes=15), 3000)[1]
    assert "(3,600 steps, at most 15 min)" in parts
    assert "renderer training 7 min" in expected_minutes(FitConfig(steps=3600, budget_minutes=7), 3000)[1]
    assert "for 500 steps" in expected_minutes(FitConfig(steps=500, device="cuda"), 3000)[1]
    assert "tracking under a minute" in expected_minutes(FitConfig(), 500)[1]
    short = expected_minutes(FitConfig(steps=20), 250)[1]  # a trial fit: no "about 0 min"
    assert short == "tracking under a minute, renderer training under a minute (20 steps)"
