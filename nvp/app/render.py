"""``nvp render``: a tracked video re-rendered with its trained renderer (no audio involved)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nvp.artifact import check_output_file
from nvp.face_model import default_face_model
from nvp.media import VideoWriter, audio_rate, has_audio, iter_frames, read_audio
from nvp.provenance import synthetic_mark
from nvp.tracked import TrackedSequence


def rerender(
    track_dir: Path,
    renderer_dir: Path,
    video: Path,
    output: Path,
    start_frame: int = 0,
    frames: int | None = None,
    device: str = "cpu",
    progress: bool = True,
) -> int:
    """Frames ``start_frame`` … of ``video`` (tracked in ``track_dir``; ``frames`` of them, default: to the
    end) re-rendered from their own tracking by the renderer of ``renderer_dir`` into the mp4 ``output``,
    with the video's audio from the same moment on. Returns the number of frames."""
    from renderer.loop import render_frames
    from renderer.render import FrameRenderer

    check_output_file(output, inputs=(video,))
    seq = TrackedSequence.load(track_dir)
    start = start_frame
    n = seq.num_frames - start if frames is None else min(frames, seq.num_frames - start)
    audio, rate = None, 48000
    if has_audio(video):
        rate = audio_rate(video)
        audio = read_audio(video, None, mono=False)[int(start / seq.fps * rate) :]
    tags = synthetic_mark("render", renderer=str(renderer_dir))
    with (
        FrameRenderer(renderer_dir, default_face_model(), seq, device) as fr,
        VideoWriter(output, seq.fps, seq.width, seq.height, audio, rate, metadata=tags) as vw,
    ):
        footage = iter_frames(video, seq.fps, start, n)
        for _, made in render_frames(fr, footage, np.arange(start, start + n), {"render": None}, progress):
            vw.write(made["render"])
    return n
