"""Tests for the demo (nvp.app.demo, demo_clip, demo_voice): the astronaut-photo talking clip."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nvp.app import demo, demo_clip, demo_voice
from nvp.errors import NoFaceError
from nvp.media import iter_frames, probe_video, read_audio

SECONDS, FPS, SIZE = 1.0, 25.0, 256


@pytest.fixture(scope="module")
def clip(tmp_path_factory: pytest.TempPathFactory) -> demo_clip.DemoClip:
    path = tmp_path_factory.mktemp("demo") / "clip.mp4"
    return demo_clip.make_demo_clip(path, seconds=SECONDS, fps=FPS, size=SIZE, seed=0)


def test_clip_file_has_the_promised_frames_duration_and_audio(clip: demo_clip.DemoClip) -> None:
    info = probe_video(clip.path)
    assert (info.width, info.height) == (SIZE, SIZE)
    assert info.num_frames == clip.num_frames == round(SECONDS * FPS)
    assert info.fps == pytest.approx(FPS)
    assert info.duration_s == pytest.approx(SECONDS, abs=0.5 / FPS)
    assert info.has_audio and info.audio_sample_rate == demo_voice.AUDIO_RATE
    audio = read_audio(clip.path, demo_voice.AUDIO_RATE)
    assert len(audio) == pytest.approx(SECONDS * demo_voice.AUDIO_RATE, abs=0.05 * demo_voice.AUDIO_RATE)
    assert np.abs(audio).max() > 0.1  # the voice is audible


def test_ground_truth_has_closed_and_open_frames(clip: demo_clip.DemoClip) -> None:
    assert clip.mouth_opening.shape == clip.head_angle.shape == (clip.num_frames,)
    assert np.all(clip.mouth_opening >= 0)
    assert np.any(clip.mouth_opening < 0.5)  # closed (the clip starts with a pause)
    assert clip.mouth_opening.max() > 5.0  # clearly open somewhere (mouth ~46 px wide at 256)
    assert np.abs(clip.head_angle).max() < 6.0


def test_audio_is_silent_while_the_mouth_is_closed(clip: demo_clip.DemoClip) -> None:
    audio = read_audio(clip.path, demo_voice.AUDIO_RATE)
    per_frame = round(demo_voice.AUDIO_RATE / FPS)
    frames = audio[: per_frame * clip.num_frames].reshape(clip.num_frames, per_frame)
    rms = np.sqrt((frames**2).mean(axis=1))
    closed = clip.mouth_opening < 1e-6
    # leave a frame of margin either side for the AAC encoder's smearing
    strict = closed & np.roll(closed, 1) & np.roll(closed, -1)
    assert strict.any() and (~closed).any()
    assert rms[strict].max() < 0.1 * rms[~closed].max()


def test_mediapipe_sees_the_animated_mouth(clip: demo_clip.DemoClip) -> None:
    from tracking.landmarks import LandmarkDetector

    gaps = []
    with LandmarkDetector() as det:
        for i, frame in enumerate(iter_frames(clip.path)):
            found = det.detect(frame, i / clip.fps)
            assert found is not None, f"no face in frame {i}"
            gaps.append(float(np.linalg.norm(found.points[13, :2] - found.points[14, :2])))
    assert len(gaps) == clip.num_frames
    r = np.corrcoef(gaps, clip.mouth_opening)[0, 1]
    assert r > 0.8, f"detected lip gap vs animated opening: r = {r:.3f}"


def test_opening_signal_is_deterministic_and_speech_like() -> None:
    a = demo_voice.speech_opening(6.0, 25.0, seed=3)
    b = demo_voice.speech_opening(6.0, 25.0, seed=3)
    c = demo_voice.speech_opening(6.0, 25.0, seed=4)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert a.shape == (150,) and a.min() >= 0 and a.max() <= 1
    closed = a < 1e-6
    assert closed[:5].all()  # starts with a pause
    assert 0.1 < closed.mean() < 0.6  # pauses, but mostly talking
    # syllables: a few local maxima per second
    peaks = np.sum((a[1:-1] > a[:-2]) & (a[1:-1] >= a[2:]) & (a[1:-1] > 0.1))
    assert 2.0 <= peaks / 6.0 <= 7.0


def test_invalid_arguments(tmp_path: Path) -> None:
    with pytest.raises(ValueError):
        demo_clip.make_demo_clip(tmp_path / "x.mp4", seconds=0)
    with pytest.raises(ValueError):
        demo_clip.make_demo_clip(tmp_path / "x.mp4", size=16)


def test_no_face_in_the_photo_raises(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import tracking.landmarks

    class Blind:
        def __enter__(self) -> Blind:
            return self

        def __exit__(self, *exc: object) -> None:
            pass

        def detect(self, rgb: np.ndarray, time_s: float) -> None:
            return None

    monkeypatch.setattr(tracking.landmarks, "LandmarkDetector", Blind)
    with pytest.raises(NoFaceError):
        demo_clip.make_demo_clip(tmp_path / "x.mp4", seconds=0.2)
    assert not (tmp_path / "x.mp4").exists()


def test_run_demo_fits_and_dubs(tmp_path: Path) -> None:
    from nvp.provenance import verify

    summary = demo.run_demo(tmp_path, progress=False, budget_minutes=0.02, seconds=1.6, text=None)
    assert "dubbed:" in summary and "synthetic-media mark: yes" in summary
    assert (tmp_path / "person" / "bundle.json").exists()
    assert verify(tmp_path / "demo_dub.mp4").marked
    assert (tmp_path / "demo_dub_stills.png").exists()
