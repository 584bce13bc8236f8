"""Tests for nvp.media on tiny synthetic media made in tmp_path."""

from __future__ import annotations

import logging
from fractions import Fraction
from pathlib import Path

import av
import numpy as np
import pytest
import soundfile as sf

from nvp import media
from nvp.errors import MediaError
from nvp.media import VideoWriter, frames_at, has_audio, iter_frames, probe_video, read_audio, rotate_frame

# ----------------------------------------------------------------------------------------------- helpers


def pattern(i: int, height: int = 48, width: int = 64) -> np.ndarray:
    """Smooth, frame-dependent RGB test pattern (compresses well, so errors stay small)."""
    y, x = np.mgrid[0:height, 0:width]
    r = 40 + 160 * x / max(width - 1, 1)
    g = 40 + 160 * y / max(height - 1, 1)
    b = np.full_like(r, 30 + 20 * i)
    return np.stack([r, g, b], axis=-1).astype(np.uint8)


def tone(freq: float, seconds: float, rate: int = 16000, amp: float = 0.5) -> np.ndarray:
    t = np.arange(round(seconds * rate)) / rate
    return (amp * np.sin(2 * np.pi * freq * t)).astype(np.float32)


def peak_frequency(x: np.ndarray, rate: int) -> float:
    spectrum = np.abs(np.fft.rfft(x * np.hanning(len(x))))
    return float(np.fft.rfftfreq(len(x), 1 / rate)[np.argmax(spectrum)])


def write_pyav(
    path: Path,
    levels_pts: list[tuple[int, int]],
    size=(32, 16),
    rotation: int | None = None,
    gop: int | None = None,
) -> None:
    """Write grey frames (level, pts in ms) with PyAV directly, for timestamp/rotation tests."""
    w, h = size
    options = {"bf": "0"}
    if gop is not None:
        options.update({"g": str(gop), "keyint_min": str(gop), "sc_threshold": "0"})
    with av.open(str(path), "w") as c:
        s = c.add_stream("libx264", rate=25, options=options)
        s.width, s.height, s.pix_fmt = w, h, "yuv420p"
        s.codec_context.time_base = Fraction(1, 1000)
        if rotation is not None:
            s.set_display_rotation(rotation)  # counter-clockwise degrees, as FFmpeg's -display_rotation
        for level, pts in levels_pts:
            img = np.full((h, w, 3), level, np.uint8)
            if rotation is not None:
                img[:6, :6] = 255  # marker in the stored top-left corner
                img[6:, :] = 0
            f = av.VideoFrame.from_ndarray(img, format="rgb24")
            f.pts, f.time_base = pts, Fraction(1, 1000)
            c.mux(s.encode(f))
        c.mux(s.encode())


def level_index(frame: np.ndarray, base: int = 10, step: int = 40) -> int:
    return int(round((float(frame.mean()) - base) / step))


@pytest.fixture
def clip(tmp_path: Path) -> Path:
    """10 frames of the test pattern at 25 fps with a 440 Hz tone, written by VideoWriter."""
    path = tmp_path / "clip.mp4"
    with VideoWriter(
        path, fps=25, width=64, height=48, audio=tone(440, 0.4), metadata={"nvp_test": "yes"}
    ) as w:
        for i in range(10):
            w.write(pattern(i))
    return path


# ----------------------------------------------------------------------------------------------- round trip


def test_round_trip_probe(clip: Path) -> None:
    info = probe_video(clip)
    assert (info.width, info.height) == (64, 48)
    assert info.fps == 25.0
    assert info.num_frames == 10
    assert info.duration_s == pytest.approx(0.4)
    assert info.rotation == 0
    assert not info.variable_frame_rate
    assert info.has_audio and info.audio_sample_rate == 16000
    assert info.codec == "h264"
    assert has_audio(clip)


def test_round_trip_frames(clip: Path) -> None:
    frames = list(iter_frames(clip))
    assert len(frames) == 10
    for i, f in enumerate(frames):
        assert f.shape == (48, 64, 3) and f.dtype == np.uint8
        assert np.abs(f.astype(int) - pattern(i)).mean() < 3.0


def test_round_trip_audio(clip: Path) -> None:
    audio = read_audio(clip, sample_rate=16000)
    assert audio.dtype == np.float32 and audio.ndim == 1
    assert len(audio) == 6400  # trimmed/padded to the video duration, encoder padding removed
    assert abs(peak_frequency(audio, 16000) - 440) < 5
    assert 0.4 < np.abs(audio[1000:5000]).max() <= 0.55


def test_metadata_read_back(clip: Path) -> None:
    with av.open(str(clip)) as c:
        assert c.metadata["nvp_test"] == "yes"


def test_start_frame_and_max_frames(clip: Path) -> None:
    assert len(list(iter_frames(clip, max_frames=3))) == 3
    part = list(iter_frames(clip, start_frame=7))
    assert len(part) == 3
    assert np.abs(part[0].astype(int) - pattern(7)).mean() < 3.0
    assert list(iter_frames(clip, start_frame=10)) == []


def test_frames_at_any_order_keeps_only_the_frames_asked_for(clip: Path, monkeypatch) -> None:
    from nvp.errors import MediaError
    from nvp.media import frames as media  # where frames_at looks iter_frames up

    every = list(iter_frames(clip))
    order = np.array([9, 0, 4, 4, 2, 9, 1])
    got = list(frames_at(clip, order, 25.0, chunk=4))
    assert len(got) == len(order)
    for i, f in zip(order, got, strict=True):
        np.testing.assert_array_equal(f, every[i])
    # a few frames spread over a long video: all between them are decoded, only those asked for are held
    import gc
    import weakref

    decoded, real = [], media.iter_frames

    def watched(*args, **kwargs):
        for frame in real(*args, **kwargs):
            decoded.append(weakref.ref(frame))
            yield frame

    monkeypatch.setattr(media, "iter_frames", watched)
    spread = frames_at(clip, np.array([0, 9]), 25.0)
    first = next(spread)
    gc.collect()
    assert len(decoded) == 10 and sum(r() is not None for r in decoded) == 2
    np.testing.assert_array_equal(first, every[0])
    np.testing.assert_array_equal(next(spread), every[9])
    with pytest.raises(MediaError, match="ended"):
        list(frames_at(clip, np.array([3, 12]), 25.0))


def test_frames_at_decodes_on_while_the_chunks_move_forward(clip: Path, monkeypatch) -> None:
    """A dub reads its footage forward (and back, ping-pong): one decoder runs on from chunk to chunk
    instead of seeking again (which decodes from the keyframe before each chunk)."""
    from nvp.media import frames as media

    every = list(iter_frames(clip))
    opened, real = [], media.iter_frames

    def counted(*args, **kwargs):
        opened.append(kwargs.get("start_frame", 0))
        return real(*args, **kwargs)

    monkeypatch.setattr(media, "iter_frames", counted)
    forward = np.arange(10)
    for i, f in zip(forward, frames_at(clip, forward, 25.0, chunk=3), strict=True):
        np.testing.assert_array_equal(f, every[i])
    assert opened == [0]
    opened.clear()
    ping_pong = np.concatenate([np.arange(10), np.arange(9, -1, -1)])
    for i, f in zip(ping_pong, frames_at(clip, ping_pong, 25.0, chunk=4), strict=True):
        np.testing.assert_array_equal(f, every[i])
    assert opened == [0, 4, 0]  # chunks 0-3, 4-7, 8-9 in one pass; a seek for each backward chunk


def test_live_footage_plays_forward_and_back_forever(clip: Path) -> None:
    from itertools import islice

    from nvp.app.live import _target_frames
    from nvp.schedule import target_frame_indices

    every = list(iter_frames(clip))
    got = list(islice(_target_frames(clip, 10, 25.0), 45))  # two and a half passes of 18 frames
    assert [i for i, _ in got] == target_frame_indices(45, 10).tolist()
    for i, frame in got:
        np.testing.assert_array_equal(frame, every[i])
    # a stream at 2/3 of the footage's rate: the nearest footage frame of each output frame's time
    slower = list(islice(_target_frames(clip, 10, 25.0, step=1.5), 60))
    assert [i for i, _ in slower] == target_frame_indices(90, 10)[
        [int(j * 1.5 + 0.5) for j in range(60)]
    ].tolist()
    for i, frame in slower:
        np.testing.assert_array_equal(frame, every[i])


def test_a_live_file_keeps_its_rate_and_its_sound_in_time(tmp_path: Path) -> None:
    """A live (fragmented) file reads at its frame rate, plays while it grows, and its sound starts with
    the picture: a click given with frame 30 plays at 1.0 s, frame 30's time."""
    click = np.zeros(32000, np.float32)
    click[16000:16400] = 0.8 * np.sin(np.arange(400) * 0.5)
    path, rng = tmp_path / "live.mp4", np.random.default_rng(0)
    w = VideoWriter(path, fps=30, width=192, height=192, audio=np.zeros(0, np.float32), live=True)
    for i in range(60):
        w.add_audio(click[i * 16000 // 30 : (i + 1) * 16000 // 30])
        w.write(
            np.full((192, 192, 3), 255, np.uint8) if i == 30 else rng.integers(0, 60, (192, 192, 3), np.uint8)
        )
        if i == 45:  # a fragment a second: the first second is on disk while the file is being written
            assert probe_video(path).num_frames >= 10
    w.close()
    info = probe_video(path)
    assert (info.fps, info.num_frames, info.variable_frame_rate) == (30, 60, False)
    with av.open(str(path)) as c:
        white = [float(f.time) for f in c.decode(video=0) if f.to_ndarray(format="rgb24").mean() > 128]
    sound = read_audio(path, 16000)
    assert white == [1.0] and abs(np.argmax(np.abs(sound) > 0.2) / 16000 - 1.0) < 0.002


def test_seek_with_short_gop_matches_full_decode(tmp_path: Path) -> None:
    path = tmp_path / "gop.mp4"
    write_pyav(path, [(10 + 12 * k, 40 * k) for k in range(20)], gop=4)
    full = [level_index(f, step=12) for f in iter_frames(path)]
    assert full == list(range(20))
    part = [level_index(f, step=12) for f in iter_frames(path, start_frame=11, max_frames=5)]
    assert part == full[11:16]


def test_resample_to_other_fps(clip: Path) -> None:
    frames = list(iter_frames(clip, fps=50))
    assert len(frames) == 20
    b = [int(round((float(f[..., 2].mean()) - 30) / 20)) for f in frames]
    assert b == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 5, 5, 6, 6, 7, 7, 8, 8, 9, 9]
    assert frames[0] is not frames[1]  # duplicates are independent arrays


# ----------------------------------------------------------------------------------------------- formats


def test_fractional_fps(tmp_path: Path) -> None:
    path = tmp_path / "ntsc.mp4"
    with VideoWriter(path, fps=29.97, width=32, height=32) as w:
        for i in range(10):
            w.write(pattern(i, 32, 32))
    info = probe_video(path)
    assert info.fps == pytest.approx(29.97, abs=1e-9)
    assert info.num_frames == 10
    assert info.duration_s == pytest.approx(10 / 29.97, abs=1e-6)
    assert not info.has_audio and info.audio_sample_rate is None
    assert len(list(iter_frames(path))) == 10


def test_odd_size_is_padded_by_edge_replication(tmp_path: Path) -> None:
    path = tmp_path / "odd.mp4"
    frames = [pattern(i, 21, 33) for i in range(5)]
    with VideoWriter(path, fps=25, width=33, height=21) as w:
        for f in frames:
            w.write(f)
    info = probe_video(path)
    assert (info.width, info.height) == (34, 22)
    out = list(iter_frames(path))
    assert len(out) == 5 and out[0].shape == (22, 34, 3)
    # lossy 4:2:0 at this tiny size: 2.8-3.1 grey levels depending on encoder threading
    assert np.abs(out[2][:21, :33].astype(int) - frames[2]).mean() < 3.5
    assert np.abs(out[2][:21, 33].astype(int) - frames[2][:, 32]).mean() < 4.0  # replicated last column
    assert np.abs(out[2][21, :33].astype(int) - frames[2][20]).mean() < 4.0  # replicated last row


def test_variable_frame_rate_is_put_on_grid(tmp_path: Path) -> None:
    path = tmp_path / "vfr.mp4"
    # frame k has grey level 10 + 40k and is shown from these times (ms); the last lasts 40 ms
    write_pyav(path, [(10 + 40 * k, t) for k, t in enumerate([0, 40, 120, 160, 240, 280])])
    info = probe_video(path)
    assert info.variable_frame_rate
    assert info.duration_s == pytest.approx(0.32)
    # grid 0,40,...,280 ms: 80 ms and 200 ms fall midway, where the earlier frame is still showing
    assert [level_index(f) for f in iter_frames(path, fps=25)] == [0, 1, 1, 2, 3, 3, 4, 5]
    # at the mean rate (6 frames / 0.32 s) every frame appears once
    assert info.fps == pytest.approx(18.75)
    assert [level_index(f) for f in iter_frames(path)] == [0, 1, 2, 3, 4, 5]


@pytest.mark.parametrize(
    ("ccw", "rotation", "corner"),
    [(90, 270, "bottom-left"), (-90, 90, "top-right"), (180, 180, "bottom-right")],
)
def test_display_matrix_rotation(tmp_path: Path, ccw: int, rotation: int, corner: str) -> None:
    path = tmp_path / "rot.mp4"
    write_pyav(path, [(0, 0), (0, 40)], size=(40, 20), rotation=ccw)
    info = probe_video(path)
    assert info.rotation == rotation
    expected_shape = (20, 40, 3) if rotation == 180 else (40, 20, 3)
    assert (info.height, info.width, 3) == expected_shape
    frame = next(iter_frames(path))
    assert frame.shape == expected_shape
    h, w = frame.shape[:2]
    ys, xs = np.nonzero(frame[..., 0] > 128)
    top = ys.max() < 8
    left = xs.max() < 8
    assert (ys.min() >= h - 8 or top) and (xs.min() >= w - 8 or left)
    assert corner == f"{'top' if top else 'bottom'}-{'left' if left else 'right'}"


def test_rotate_frame_helper() -> None:
    img = np.arange(6).reshape(2, 3)
    assert rotate_frame(img, 0) is img
    assert rotate_frame(img, 90).tolist() == [[3, 0], [4, 1], [5, 2]]  # clockwise
    assert rotate_frame(img, 270).tolist() == [[2, 5], [1, 4], [0, 3]]
    assert rotate_frame(img, 180).tolist() == [[5, 4, 3], [2, 1, 0]]
    with pytest.raises(ValueError):
        rotate_frame(img, 45)


# ----------------------------------------------------------------------------------------------- audio


def test_read_stereo_44k_wav(tmp_path: Path) -> None:
    path = tmp_path / "stereo.wav"
    left = tone(1000, 1.0, rate=44100, amp=0.5)
    sf.write(path, np.stack([left, left], axis=1), 44100, subtype="PCM_16")
    audio = read_audio(path)
    assert audio.dtype == np.float32 and audio.ndim == 1
    assert abs(len(audio) - 16000) <= 1
    assert abs(peak_frequency(audio, 16000) - 1000) < 3
    assert np.abs(audio[2000:14000]).max() == pytest.approx(0.5, abs=0.02)  # channels averaged


def test_read_24bit_wav_at_other_rate(tmp_path: Path) -> None:
    path = tmp_path / "mono24.wav"
    sf.write(path, tone(300, 0.5, rate=22050, amp=0.9), 22050, subtype="PCM_24")
    audio = read_audio(path, sample_rate=8000)
    assert abs(len(audio) - 4000) <= 1
    assert abs(peak_frequency(audio, 8000) - 300) < 4
    assert np.abs(audio).max() <= 1.0


def test_writer_pads_short_audio_and_accepts_stereo(tmp_path: Path) -> None:
    path = tmp_path / "short_audio.mp4"
    stereo = np.stack([tone(500, 0.2), tone(500, 0.2)], axis=1)
    with VideoWriter(path, fps=25, width=16, height=16, audio=stereo) as w:
        for i in range(10):
            w.write(pattern(i, 16, 16))
    audio = read_audio(path)
    assert len(audio) == 6400
    assert np.abs(audio[:3000]).max() > 0.3 and np.abs(audio[4000:]).max() < 0.05


def noise_wav(path: Path, rate: int, channels: int, seconds: float, seed: int = 0) -> Path:
    """16-bit wav of quiet noise, each channel its own."""
    data = 0.3 * np.random.default_rng(seed).standard_normal((round(rate * seconds), channels))
    sf.write(path, data.astype(np.float32), rate, subtype="PCM_16")
    return path


def blocks_of(blocks: media.AudioBlocks) -> tuple[np.ndarray, int]:
    """All of an AudioBlocks' samples, and how many blocks they came in."""
    parts = list(blocks)
    return np.concatenate(parts), len(parts)


@pytest.mark.parametrize(
    ("rate", "channels"), [(48000, 2), (44100, 2), (22050, 1), (22000, 1), (8000, 1), (16000, 10)]
)
def test_audio_blocks_are_read_audio_in_pieces(tmp_path: Path, rate: int, channels: int) -> None:
    wav = noise_wav(tmp_path / "a.wav", rate, channels, 1.3)
    whole = read_audio(wav, None, mono=False)
    blocks = media.AudioBlocks(wav, None, mono=False)
    streamed, count = blocks_of(blocks)
    assert count > 1 and streamed.shape == whole.shape and np.array_equal(streamed, whole)
    assert (blocks.rate, blocks.source_rate, blocks.source_samples) == (rate, rate, len(whole))
    assert blocks.channels == channels
    mono = media.AudioBlocks(wav, 16000)
    assert np.array_equal(blocks_of(mono)[0], read_audio(wav, 16000))
    assert mono.source_samples == len(whole) and mono.channels == 1


def test_audio_blocks_drop_the_aac_padding_as_read_audio_does(clip: Path) -> None:
    blocks = media.AudioBlocks(clip, None)
    streamed, _ = blocks_of(blocks)
    assert len(streamed) == blocks.source_samples == 6400  # 0.4 s of AAC, decoded to 7 x 1024 samples
    assert np.array_equal(streamed, read_audio(clip, None))
    assert np.array_equal(blocks_of(media.AudioBlocks(clip, 8000))[0], read_audio(clip, 8000))


def test_audio_blocks_read_a_stream_of_unknown_length(tmp_path: Path, monkeypatch) -> None:
    wav = noise_wav(tmp_path / "a.wav", 44100, 2, 3.0)
    assert media.AudioBlocks(wav, 16000).stated_seconds == pytest.approx(3.0)
    monkeypatch.setattr(media.audio, "_stated_seconds", lambda stream: None)
    blocks = media.AudioBlocks(wav, None, mono=False)
    assert blocks.stated_seconds is None
    assert np.array_equal(blocks_of(blocks)[0], read_audio(wav, None, mono=False))
    assert np.array_equal(blocks_of(media.AudioBlocks(wav, 16000))[0], read_audio(wav, 16000))


def test_audio_blocks_refuse_samples_that_are_not_numbers(tmp_path: Path) -> None:
    audio = tone(300, 1.0, 22050)
    audio[11025] = np.nan
    sf.write(tmp_path / "nan.wav", audio, 22050, subtype="FLOAT")
    with pytest.raises(MediaError, match=r"nan.wav.*not numbers .*the first at 0.50 s"):
        list(media.AudioBlocks(tmp_path / "nan.wav", 16000))
    with pytest.raises(MediaError, match="no audio stream"):
        media.AudioBlocks(video_without_audio(tmp_path / "silent.mp4"))


def test_audio_blocks_of_all_channels_need_the_stated_layout(tmp_path: Path, monkeypatch) -> None:
    from types import SimpleNamespace

    wav = noise_wav(tmp_path / "a.wav", 22050, 2, 0.2)
    unstated = SimpleNamespace(layout=SimpleNamespace(name="", nb_channels=0), sample_rate=22050)
    stream = SimpleNamespace(codec_context=unstated, duration=None)  # no length stated either
    monkeypatch.setattr(media.audio, "_audio_stream", lambda *a: stream)
    with pytest.raises(MediaError, match="a.wav.*channel layout is not stated"):
        media.AudioBlocks(wav, None, mono=False)
    assert media.AudioBlocks(wav, 16000).channels == 1  # mono: each frame's own layout is mixed


def video_without_audio(path: Path) -> Path:
    with VideoWriter(path, 25, 16, 16) as w:
        w.write(pattern(0, 16, 16))
    return path


@pytest.mark.parametrize(
    ("rate", "channels", "stored"),
    [
        (48000, 2, 48000),
        (44100, 2, 44100),
        (22050, 1, 22050),
        (22000, 1, 22050),
        (8000, 1, 8000),
        (100000, 2, 96000),
        (16000, 10, 16000),
    ],
)
@pytest.mark.parametrize("frames", [12, 25, 40])  # a video shorter than the audio, as long, longer
def test_a_streamed_audio_file_writes_the_track_the_array_writes(
    tmp_path: Path, rate: int, channels: int, stored: int, frames: int
) -> None:
    wav = noise_wav(tmp_path / "a.wav", rate, channels, 1.0)
    outs = {"array": tmp_path / "array.mp4", "file": tmp_path / "file.mp4"}
    given = {"array": {"audio": read_audio(wav, None, mono=False), "audio_rate": rate}}
    for how, out in outs.items():
        with VideoWriter(out, 25, 16, 16, **given.get(how, {"audio_file": wav})) as w:
            for i in range(frames):
                w.write(pattern(i, 16, 16))
    array, streamed = (read_audio(outs[how], None, mono=False) for how in ("array", "file"))
    assert probe_video(outs["file"]).audio_sample_rate == stored
    assert streamed.shape == array.shape and np.array_equal(streamed, array)  # the same AAC track
    assert streamed.shape[1:] == (() if channels in (1, 10) else (channels,))
    assert len(streamed) == frames * stored // 25  # trimmed or padded to the video
    if frames == 40:  # 0.6 s of silence after the audio's second
        assert (
            np.abs(streamed[int(1.1 * stored) :]).max() < 1e-3 < np.abs(streamed[: int(0.9 * stored)]).max()
        )


def test_a_streamed_audio_file_that_fails_leaves_no_output(tmp_path: Path) -> None:
    audio = tone(300, 2.0, 22050)
    audio[33075] = np.inf  # at 1.5 s: the writer reaches it after 30 frames
    sf.write(tmp_path / "inf.wav", audio, 22050, subtype="FLOAT")
    out = tmp_path / "o.mp4"
    with pytest.raises(MediaError, match="the first at 1.50 s"):
        with VideoWriter(out, 25, 16, 16, audio_file=tmp_path / "inf.wav") as w:
            for i in range(50):
                w.write(pattern(i, 16, 16))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["inf.wav"]  # no output, no temporary file
    with pytest.raises(MediaError, match="does not exist"):
        VideoWriter(out, 25, 16, 16, audio_file=tmp_path / "missing.wav")
    with pytest.raises(ValueError, match="not both"):
        VideoWriter(out, 25, 16, 16, audio=audio, audio_file=tmp_path / "inf.wav")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["inf.wav"]


# ----------------------------------------------------------------------------------------------- writer


def test_atomic_writer_leaves_nothing_on_exception(tmp_path: Path) -> None:
    path = tmp_path / "out.mp4"
    with pytest.raises(RuntimeError, match="boom"):
        with VideoWriter(path, fps=25, width=16, height=16, audio=tone(440, 0.2)) as w:
            w.write(pattern(0, 16, 16))
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_atomic_writer_keeps_existing_file_on_exception(tmp_path: Path) -> None:
    path = tmp_path / "out.mp4"
    path.write_bytes(b"previous")
    with pytest.raises(ValueError, match=r"expected \(16, 16, 3\), found \(16, 17, 3\)"):
        with VideoWriter(path, fps=25, width=16, height=16) as w:
            w.write(pattern(0, 16, 16))
            w.write(np.zeros((16, 17, 3), np.uint8))
    assert path.read_bytes() == b"previous"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.mp4"]


def test_writer_rejects_wrong_dtype(tmp_path: Path) -> None:
    with VideoWriter(tmp_path / "x.mp4", fps=25, width=8, height=8) as w:
        with pytest.raises(ValueError, match="uint8"):
            w.write(np.zeros((8, 8, 3), np.float32))
        w.write(np.zeros((8, 8, 3), np.uint8))
    assert (tmp_path / "x.mp4").exists()


def test_writer_without_frames_writes_nothing(tmp_path: Path) -> None:
    with pytest.raises(MediaError, match="no frames"):
        with VideoWriter(tmp_path / "empty.mp4", fps=25, width=8, height=8):
            pass
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------------------------- errors


def test_missing_file(tmp_path: Path) -> None:
    missing = tmp_path / "nope.mp4"
    for fn in (probe_video, iter_frames, read_audio, has_audio):
        with pytest.raises(MediaError, match="does not exist"):
            fn(missing)


def test_text_file_renamed_mp4(tmp_path: Path) -> None:
    path = tmp_path / "fake.mp4"
    path.write_text("this is not a video\n" * 20)
    with pytest.raises(MediaError, match="fake.mp4"):
        probe_video(path)
    with pytest.raises(MediaError):
        read_audio(path)


def test_audio_only_file_is_not_a_video(tmp_path: Path) -> None:
    path = tmp_path / "a.wav"
    sf.write(path, tone(440, 0.1), 16000)
    with pytest.raises(MediaError, match=r"no video stream \(found streams: audio\)"):
        probe_video(path)
    with pytest.raises(MediaError, match="no video stream"):
        iter_frames(path)
    assert has_audio(path)


def test_video_without_audio(tmp_path: Path) -> None:
    path = tmp_path / "silent.mp4"
    with VideoWriter(path, fps=25, width=8, height=8) as w:
        w.write(np.zeros((8, 8, 3), np.uint8))
    assert not has_audio(path)
    with pytest.raises(MediaError, match=r"no audio stream \(found streams: video\)"):
        read_audio(path)


def test_decode_error_names_frame_index(clip: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    real_decode = media.frames._decode

    def failing_decode(container, stream):
        for n, frame in enumerate(real_decode(container, stream)):
            if n == 4:
                raise av.error.InvalidDataError(1094995529, "Invalid data found when processing input")
            yield frame

    monkeypatch.setattr(media.frames, "_decode", failing_decode)
    frames = iter_frames(clip)
    with pytest.raises(MediaError, match="at output frame 3 of 10"):
        for _ in frames:
            pass


def test_a_file_cut_short_is_read_with_a_warning(tmp_path, caplog):
    path = tmp_path / "full.mp4"
    rng = np.random.default_rng(0)
    with media.VideoWriter(path, 25, 64, 64) as w:  # faststart: the index sits at the start of the file
        for _ in range(100):
            w.write(rng.integers(0, 255, (64, 64, 3), dtype=np.uint8))
    cut = tmp_path / "cut.mp4"
    data = path.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.4)])
    with caplog.at_level(logging.WARNING, logger="nvp.media"):
        frames = list(media.iter_frames(cut))
    assert 0 < len(frames) < 100
    assert any("cut short" in r.getMessage() and "announces 100" in r.getMessage() for r in caplog.records)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="nvp.media"):
        media.probe_video(path)
    assert not caplog.records  # an intact file is read without a word


def test_disk_full_while_writing_a_video_names_the_file(tmp_path, monkeypatch):
    import errno

    from nvp.artifact import DiskFullError

    out = tmp_path / "out.mp4"
    w = media.VideoWriter(out, 25, 32, 32)

    class FullDisk:  # the real container, whose writes fail as on a full disk
        def __init__(self, container):
            self.container = container

        def mux(self, *a, **k):
            raise OSError(errno.ENOSPC, "No space left on device")

        def __getattr__(self, name):
            return getattr(self.container, name)

    monkeypatch.setattr(w, "_container", FullDisk(w._container))
    with pytest.raises(DiskFullError, match=f"disk full while writing {out}"):
        w.write(np.zeros((32, 32, 3), np.uint8))
    assert not out.exists() and not list(tmp_path.glob(".*tmp*"))


def test_writer_joins_parts_without_encoding_them_again(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for _ in range(23)]
    parts = []
    for i, (a, b) in enumerate([(0, 10), (10, 20), (20, 23)]):
        parts.append(tmp_path / f"part{i}.mp4")
        with VideoWriter(parts[-1], 25, 64, 48) as vw:
            for f in frames[a:b]:
                vw.write(f)
    out = tmp_path / "joined.mp4"
    audio = tone(440, 1.0)
    with VideoWriter(
        out, 25, 64, 48, audio=audio, audio_rate=16000, metadata={"k": "v"}, template=parts[0]
    ) as vw:
        with pytest.raises(ValueError, match="append"):
            vw.write(frames[0])
        for p in parts:
            vw.append(p)
    info = probe_video(out)
    assert info.num_frames == 23 and not info.variable_frame_rate and info.audio_sample_rate == 16000
    joined, separate = list(iter_frames(out)), [f for p in parts for f in iter_frames(p)]
    assert all(np.array_equal(a, b) for a, b in zip(joined, separate, strict=True))  # copied, not re-encoded
    with av.open(str(out)) as c:
        assert c.metadata["k"] == "v"
        pts = [f.pts for f in c.decode(video=0)]
        assert pts[0] == 0 and len(set(np.diff(pts))) == 1  # one frame after the other, evenly
    assert len(read_audio(out, 16000)) == pytest.approx(23 / 25 * 16000, abs=1024)  # trimmed to the video
    with VideoWriter(tmp_path / "x.mp4", 25, 64, 48, template=parts[0]) as vw:
        (tmp_path / "empty.mp4").write_bytes(b"")
        with pytest.raises(MediaError, match="empty.mp4"):
            vw.append(tmp_path / "empty.mp4")
        vw.append(parts[2])
