"""``nvp live``: dub audio as it arrives and emit each frame as soon as it is made.

Audio comes from a file played in real time (or as fast as possible with ``realtime=False``, every frame
rendered) or from raw PCM on stdin (signed 16-bit little-endian mono, e.g. a microphone: ``arecord -f S16_LE
-r 16000 -c 1 -t raw | nvp live - --person P ...``). A reader thread stamps each block with its arrival
time; the main loop turns the audio into expressions with :class:`nvp.stream.ExpressionStream` (a frame
is predicted once its audio and :data:`nvp.stream.LOOKAHEAD_S` more have arrived), renders the frame into
the person's footage (played forward and backward as in ``nvp dub``) and writes it at once: to a
fragmented MP4 that grows a fragment per second (with the audio), and/or as raw RGB frames to stdout for a
player or a virtual camera.

Latency of a frame: from the arrival of the audio sample at the frame's time to the frame being written.
When rendering falls behind by more than ``max_lag_s``, frames are not rendered but repeat the last one
(counted as dropped), so the picture stays in sync with the sound on a machine that cannot keep up.
"""

from __future__ import annotations

import bisect
import itertools
import math
import queue
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import BinaryIO

import numpy as np

from nvp.errors import NvpError

BLOCK_S = 0.2
"""Audio per reading step (the stream's granularity)."""
MAX_LAG_S = 1.0
"""A frame whose audio arrived longer ago than this is not rendered (the last frame repeats)."""


@dataclass(frozen=True)
class LiveResult:
    """What a live session did."""

    frames: int
    dropped: int
    """Frames that repeated the previous one because rendering was behind."""
    latency_s: np.ndarray
    """``(frames,)`` seconds from the arrival of each frame's audio to the frame being written."""
    lookahead_s: float
    audio_seconds: float
    seconds: float
    fps: float


class _Reader(threading.Thread):
    """Puts ``(samples at 16 kHz, arrival time)`` blocks on a queue, then ``None``; errors are handed to the
    consumer as an exception object."""

    def __init__(self, blocks: Iterator[np.ndarray], realtime_rate: float | None) -> None:
        super().__init__(daemon=True)
        self.blocks, self.realtime_rate = blocks, realtime_rate
        self.queue: queue.Queue = queue.Queue()
        self.start_time = time.perf_counter()

    def run(self) -> None:
        sent = 0
        try:
            for block in self.blocks:
                sent += len(block)
                if self.realtime_rate:  # a file played in real time: the block is there when it has played
                    wait = self.start_time + sent / self.realtime_rate - time.perf_counter()
                    if wait > 0:
                        time.sleep(wait)
                self.queue.put((block, time.perf_counter()))
        except Exception as e:  # reported by the consumer as one clear message
            self.queue.put(e)
        self.queue.put(None)


def file_blocks(path: Path, block_s: float = BLOCK_S) -> Iterator[np.ndarray]:
    """A file's audio (mono, 16 kHz) in blocks of ``block_s`` seconds."""
    from nvp.media import read_audio

    audio = read_audio(path, 16000)
    n = int(round(block_s * 16000))
    for i in range(0, len(audio), n):
        yield audio[i : i + n]


def pcm_blocks(stream: BinaryIO, rate: int, block_s: float = BLOCK_S) -> Iterator[np.ndarray]:
    """Raw signed 16-bit little-endian mono PCM at ``rate`` Hz from ``stream`` (e.g. stdin), as float
    blocks at 16 kHz (resampled block by block when ``rate`` is not 16000)."""
    from fractions import Fraction

    from scipy.signal import resample_poly

    n = int(round(block_s * rate)) * 2
    ratio = Fraction(16000, rate)
    while True:
        data = stream.read(n)
        if not data:
            return
        if len(data) % 2:
            data = data[:-1]
        x = np.frombuffer(data, "<i2").astype(np.float32) / 32768.0
        if rate != 16000:
            x = resample_poly(x, ratio.numerator, ratio.denominator).astype(np.float32)
        yield x


def _target_frames(
    path: Path, num_target: int, fps: float, step: float = 1.0
) -> Iterator[tuple[int, np.ndarray]]:
    """The footage's frames in ``nvp dub``'s forward-backward order, forever: ``(index, frame)`` of each
    output frame, ``step`` footage frames after the one before (a stream at the footage's rate over
    ``step``, :func:`nvp.schedule.stream_positions`), read at least one forward-and-back pass (48 output
    frames at least) at a time (one decoder runs through the forward half, see :func:`nvp.media.frames_at`;
    the frames held are its chunk's at most)."""
    from nvp.media import frames_at
    from nvp.schedule import ping_pong, stream_positions

    period = max(1, 2 * (num_target - 1))
    chunk = period * -(-48 // period)  # a very short footage: several passes per read
    for first in itertools.count(0, chunk):
        order = ping_pong(stream_positions(first, chunk, step), num_target)
        yield from zip(order.tolist(), frames_at(path, order, fps), strict=True)


def live(
    source: str | Path,
    bundle_dir: str | Path,
    output: str | Path | None = None,
    raw_out: BinaryIO | None = None,
    device: str = "cpu",
    realtime: bool = True,
    rate: int = 16000,
    style: str | Path | None = None,
    max_lag_s: float = MAX_LAG_S,
    lookahead_s: float | None = None,
    status=None,
    gaze: str | Path = "footage",
    fps: float | None = None,
) -> LiveResult:
    """Dub the person of ``bundle_dir`` live from ``source`` (an audio/video file, or ``"-"``: raw PCM on
    stdin at ``rate`` Hz). Frames go to ``output`` (fragmented MP4 with the audio) and/or ``raw_out``
    (RGB24, ``width × height × 3`` bytes per frame). ``status(text)`` is called about once a second.
    ``gaze``: where the eyes look, as :func:`nvp.app.dub.dub` takes it (a gaze file's times count from the
    stream's start). ``fps``: frames per second of the stream, at most the person's (the default): a lower
    rate renders fewer frames (each the footage frame and the expressions nearest its time, so head and
    mouth move at their real speed), for a machine that cannot render every frame in time."""
    from nvp.app.dub import check_gaze, dubbed_vertices, gaze_mark, load_person
    from nvp.artifact import check_output_file
    from nvp.bundle import PersonBundle
    from nvp.gaze import gaze_at, gaze_file, read_gaze_file
    from nvp.media import VideoWriter
    from nvp.provenance import synthetic_mark
    from nvp.schedule import stream_positions
    from nvp.stream import LOOKAHEAD_S, ExpressionStream
    from nvp.threads import ThreadGovernor, frame_workers
    from renderer.eyes import turn_eyes
    from renderer.mouths import EntryChooser
    from renderer.render import FrameRenderer
    from renderer.workers import RenderWorkers

    if output is None and raw_out is None:
        raise NvpError("give an output: -o live.mp4 and/or --raw (frames on stdout)")
    if output is not None:
        check_output_file(output, inputs=() if source == "-" else (source,))
    if source == "-":
        blocks, pace = pcm_blocks(sys.stdin.buffer, rate), None
    else:
        if not Path(source).is_file():
            raise NvpError(f"{source}: no such audio file")
        blocks, pace = file_blocks(Path(source)), (16000.0 if realtime else None)
        if not realtime:  # no clock to keep up with (the whole file "arrives" at once): every frame is made
            max_lag_s = math.inf
    bundle = PersonBundle.load(bundle_dir)
    person = load_person(bundle, style)
    seq, model = person.tracked, person.model
    out_fps = seq.fps if fps is None else float(fps)
    if not 1.0 <= out_fps <= seq.fps * (1 + 1e-6):
        raise NvpError(f"--fps {out_fps:g}: choose a rate from 1 to the person's {seq.fps:g} frames/s")
    step = seq.fps / out_fps
    if str(gaze) != "footage":
        check_gaze(seq)
    gaze_rows = None if gaze_file(gaze) is None else read_gaze_file(gaze_file(gaze))
    lookahead = LOOKAHEAD_S if lookahead_s is None else lookahead_s
    stream = ExpressionStream(person.style, person.net, seq.fps, lookahead)
    weights = model.mouth_weights()
    footage = _target_frames(bundle.path("target"), seq.num_frames, seq.fps, step)
    mark = {**person.mark, **gaze_mark(gaze)}
    tags = synthetic_mark("live", bundle=bundle.manifest.get("id", bundle.root.name), **mark)
    totals: list[int] = []  # samples received in all after each block
    times: list[float] = []  # when each block arrived
    latency: list[float] = []
    dropped = 0
    last: np.ndarray | None = None
    t0 = time.perf_counter()
    next_status = t0 + 1.0

    def time_of(j: int) -> float:
        """Output frame ``j``'s time in the stream: the footage frame's it shows."""
        return float(stream_positions(j, 1, step)[0]) / seq.fps

    def arrival(j: int) -> float:
        """When the audio sample at output frame ``j``'s time arrived."""
        i = bisect.bisect_left(totals, int(time_of(j) * 16000) + 1)
        return times[min(i, len(times) - 1)]

    taken = made = 0  # output frames taken from the stream; the stream's frames (the footage's rate)

    def outputs(expressions: np.ndarray) -> np.ndarray:
        """The output frames' expressions among the stream's newly made ``expressions``."""
        nonlocal taken, made
        first, made = made, made + len(expressions)
        at = stream_positions(taken, len(expressions) + 1, step)
        at = at[at < made]
        taken += len(at)
        return expressions[at - first]

    with (
        FrameRenderer(bundle.path("renderer"), model, seq, device) as fr,
        VideoWriter(
            output, out_fps, seq.width, seq.height, np.zeros(0, np.float32), 16000, metadata=tags, live=True
        )
        if output is not None
        else _NoWriter() as vw,
        # the frames of a block are rendered side by side, one PyTorch thread each, as nvp dub does; closed
        # first, so the render threads stop before the renderer and the writer close
        RenderWorkers(fr, frame_workers() if str(device) == "cpu" else 1) as pool,
    ):
        governor = ThreadGovernor() if str(device) == "cpu" else None
        teeth = EntryChooser()  # the person's own teeth without flicker; the future is unknown

        def networks(renderer: FrameRenderer, k: int, frame: np.ndarray, e: np.ndarray) -> tuple:
            tracked = renderer.tracked(k)
            face = renderer.prepare(frame, k, dubbed_vertices(model, seq, k, e, weights, tracked), tracked)
            return face, renderer.entry_costs(face) if renderer.mouths is not None else None

        def paste(renderer: FrameRenderer, j: int, face, mouth: int | None) -> np.ndarray:
            image = renderer.composite(face, mouth)
            if str(gaze) == "footage":
                return image
            look = None if gaze_rows is None else gaze_at(gaze_rows, np.array([time_of(j)]))[0]
            return turn_eyes(model, seq, image, face.index, look)

        def emit(expressions: np.ndarray) -> None:
            """Renders and writes the frames of one block of audio (all of them before the next block is
            read): their networks side by side, the bank entries in order, then the pastes side by side."""
            nonlocal dropped, last
            started = []  # (output frame, its networks' future, or None: repeat the last frame)
            for e in expressions:
                if governor is not None:
                    governor.update()
                j = len(latency) + len(started)
                k, frame = next(footage)
                late = time.perf_counter() - arrival(j)
                if (last is not None or started) and late > max_lag_s:
                    dropped += 1
                    started.append((j, None))
                else:
                    started.append((j, pool.submit(partial(networks, k=k, frame=frame, e=e))))
            pasting = []
            for j, future in started:
                if future is not None:
                    face, costs = future.result()
                    entry = teeth.push(costs)[0] if costs is not None else None
                    future = pool.submit(partial(paste, j=j, face=face, mouth=entry))
                pasting.append((j, future))
            for j, future in pasting:
                if future is not None:
                    last = future.result()
                write(j, last)

        def write(j: int, frame: np.ndarray) -> None:
            nonlocal next_status
            vw.write(frame)
            if raw_out is not None:
                raw_out.write(frame.tobytes())
                raw_out.flush()
            latency.append(time.perf_counter() - arrival(j))
            now = time.perf_counter()
            if status is not None and now >= next_status:
                next_status = now + 1.0
                status(
                    f"{j + 1} frames, {stream.received / 16000:.1f} s of audio, latency "
                    f"{latency[-1]:.2f} s, {dropped} dropped"
                )

        reader = _Reader(blocks, pace)  # its clock starts now: the first block "arrives" BLOCK_S later
        reader.start()
        while True:
            item = reader.queue.get()
            if item is None:
                break
            if isinstance(item, Exception):
                raise NvpError(f"reading the audio failed: {item}") from item
            block, when = item
            if len(block) == 0:
                continue
            totals.append(stream.received + len(block))
            times.append(when)
            if output is not None:
                vw.add_audio(block)
            emit(outputs(stream.push(block)))
        if not totals:
            raise NvpError(f"{source}: no audio arrived")
        emit(outputs(stream.finish()))
    return LiveResult(
        frames=len(latency),
        dropped=dropped,
        latency_s=np.asarray(latency),
        lookahead_s=lookahead,
        audio_seconds=stream.received / 16000,
        seconds=time.perf_counter() - t0,
        fps=out_fps,
    )


class _NoWriter:
    """Stands in for the MP4 writer when frames only go to stdout."""

    def __enter__(self) -> _NoWriter:
        return self

    def __exit__(self, *exc) -> None:
        return None

    def write(self, frame: np.ndarray) -> None:
        return None
