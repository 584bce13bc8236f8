"""The one render loop: footage frames in, their renders out, frames in parallel (:func:`render_frames`)."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import ExitStack
from functools import partial

import numpy as np

from renderer.render import FrameRenderer
from renderer.workers import RenderWorkers

MOUTH_LAG = 3
"""Output frames a stream renders ahead before it fixes a frame's mouth-bank entry
(:class:`renderer.mouths.EntryChooser`), each held in memory until then. Over 250 frames of audio-driven
dubs (edtalk__pose_source2, dfrf__cnn2) lag 0 / 1 / 3 / 6 / 12 chose 84-86 / 92-93 / 96-99 / 97-100 / 100 %
of the whole clip's best path's entries (path cost +0.8 / +0.2 / 0.0 / 0.0 / 0 %)."""

Geometry = Callable[[int, int, np.ndarray], np.ndarray]
"""``(j, index, tracked_cam) → (V, 3)`` camera-frame vertices to render for output frame ``j`` over footage
frame ``index`` whose tracked vertices are ``tracked_cam``."""


def render_frames(
    fr: FrameRenderer,
    frames: Iterable[np.ndarray],
    indices: Sequence[int],
    variants: Mapping[str, Geometry | None],
    progress: bool = True,
    desc: str = "render",
    workers: int | None = None,
    sources: Callable[[int], tuple[np.ndarray, int, np.ndarray]] | None = None,
    start_entries: Mapping[str, int | None] | None = None,
    decided: list[dict[str, int | None]] | None = None,
    finish: Callable[[int, int, np.ndarray], np.ndarray] | None = None,
) -> Iterator[tuple[np.ndarray, dict[str, np.ndarray]]]:
    """The one render loop: footage ``frames`` (``(H, W, 3)`` uint8, one per entry of ``indices``, the
    footage frame each one is) in; for each, in order, the footage frame and its renders
    ``{name: (H, W, 3) uint8}`` out, with a progress bar that is closed however the loop ends (an error,
    or the consumer stopping).

    A variant ``None`` re-renders the frame from its own tracking (re-creation); a :data:`Geometry` renders
    ``geometry(j, index, tracked_cam)`` and the replaced region also covers the tracked face (a dub).
    ``sources(j)``: the ``source`` of frame ``j``'s fine detail (default: the footage frame itself), e.g. an
    evaluation that must not move the real frame's own detail onto its re-creation. With a mouth bank,
    each variant's open mouths get their bank entries from an :class:`renderer.mouths.EntryChooser` over
    :meth:`FrameRenderer.entry_costs` (:data:`MOUTH_LAG` frames ahead), so the teeth do not flicker.
    ``start_entries``: each variant's entry of the frame before the first (a resumed job then chooses as
    an uninterrupted one would); ``decided``, when given, receives every frame's entries, in order, before
    the frame is yielded. ``finish(j, index, render)``: a last step of each render, done by the workers too
    (e.g. the eyes turned, :mod:`renderer.eyes`).

    On the CPU, ``workers`` frames are rendered at once, each by its own thread and renderer
    (:meth:`FrameRenderer.twin`) on one PyTorch thread, while the caller consumes (encodes) the previous
    ones: first the networks (:meth:`FrameRenderer.prepare`), then, once the entry is chosen, the paste
    (:meth:`FrameRenderer.composite`). Default: one per core PyTorch would use (``NVP_THREADS`` /
    ``OMP_NUM_THREADS`` fix it). Per-frame work is small and partly single-threaded (rasterizing,
    pasting), so frames in parallel use two cores far better than two threads inside each frame (measured
    on a 2-core EPYC, 512² dub: one frame on two threads 56.7 ms, two frames on one thread each 30.5 ms per
    frame), and a single-threaded worker has no OpenMP barriers that stall when another process takes a
    core. On a GPU, one frame at a time."""
    from tqdm import tqdm

    from nvp.threads import frame_workers
    from renderer.mouths import EntryChooser

    n = 1 if str(fr.device) != "cpu" else (workers or frame_workers())
    bar = tqdm(total=len(indices), desc=desc, unit="frame", disable=not progress)
    choosers = {name: EntryChooser(MOUTH_LAG) for name in variants} if fr.mouths is not None else None
    for name, chooser in (choosers or {}).items():
        chooser.current = (start_entries or {}).get(name)

    def prepare(renderer: FrameRenderer, j: int, k: int, frame: np.ndarray) -> dict[str, tuple]:
        tracked = renderer.tracked(k)
        source = None if sources is None else sources(j)
        faces = {
            name: renderer.prepare(frame, k, tracked, source=source)
            if geo is None
            else renderer.prepare(frame, k, geo(j, k, tracked), tracked, source=source)
            for name, geo in variants.items()
        }
        costs = {name: renderer.entry_costs(face) if choosers else None for name, face in faces.items()}
        return {name: (face, costs[name]) for name, face in faces.items()}

    with ExitStack() as stack:
        stack.callback(bar.close)
        pool = stack.enter_context(RenderWorkers(fr, n))

        def composite(faces: dict[str, tuple], entries: dict[str, int | None], j: int) -> Callable:
            def paste(r: FrameRenderer) -> dict[str, np.ndarray]:
                made = {name: r.composite(face, entries[name]) for name, (face, _) in faces.items()}
                if finish is None:
                    return made
                return {name: finish(j, faces[name][0].index, image) for name, image in made.items()}

            return paste

        pasted = 0  # output frames handed to the paste so far

        started: deque = deque()  # (frame, networks' future), in order
        waiting: deque = deque()  # (frame, prepared faces) whose bank entries are not fixed yet
        pasting: deque = deque()  # (frame, composite's future)

        def choose(item: tuple[np.ndarray, dict[str, tuple]] | None) -> None:
            """Hands the frames whose bank entries ``item`` (the next frame and its prepared faces) fixes
            to the paste; all frames still waiting when ``item`` is None (the end)."""
            nonlocal pasted
            if item is not None:
                waiting.append(item)
            if choosers is None:
                fixed = {name: [None] * len(waiting) for name in variants}
            elif item is None:
                fixed = {name: c.flush() for name, c in choosers.items()}
            else:
                fixed = {name: choosers[name].push(item[1][name][1]) for name in variants}
            for entries in zip(*fixed.values(), strict=True):
                frame, prepared = waiting.popleft()
                chosen = dict(zip(variants, entries, strict=True))
                if decided is not None:
                    decided.append(chosen)
                pasting.append((frame, pool.submit(composite(prepared, chosen, pasted))))
                pasted += 1

        def done(limit: int) -> Iterator[tuple[np.ndarray, dict[str, np.ndarray]]]:
            while len(pasting) > limit:
                frame, future = pasting.popleft()
                yield frame, future.result()
                bar.update(1)

        for j, (k, frame) in enumerate(zip(indices, frames, strict=False)):
            started.append((frame, pool.submit(partial(prepare, j=j, k=int(k), frame=frame))))
            while len(started) > n - 1:
                first, future = started.popleft()
                choose((first, future.result()))
                yield from done(n - 1)
        while started:
            first, future = started.popleft()
            choose((first, future.result()))
        choose(None)
        yield from done(0)
