"""The worker pool of the render loop: renderers of one person, each on its own thread."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import ExitStack
from typing import TypeVar

import torch

from renderer.render import FrameRenderer

T = TypeVar("T")


class RenderWorkers:
    """``workers`` renderers of one person (``fr`` and twins, :meth:`FrameRenderer.twin`), each on its own
    thread with one PyTorch thread (see :func:`render_frames`), or ``fr`` alone in the calling thread when
    ``workers`` is 1 (a profiler sees it; a GPU renders one frame at a time anyway). Use as a context
    manager: leaving it stops the threads (what has not started is cancelled) and closes the twins."""

    def __init__(self, fr: FrameRenderer, workers: int) -> None:
        self._stack = ExitStack()
        self._idle = [fr] + [self._stack.enter_context(fr.twin()) for _ in range(workers - 1)]
        self._pool = None
        if workers > 1:
            self._pool = ThreadPoolExecutor(workers, initializer=torch.set_num_threads, initargs=(1,))
            self._stack.enter_context(self._pool)
            self._stack.callback(self._pool.shutdown, cancel_futures=True)  # first: nothing new starts

    def __enter__(self) -> RenderWorkers:
        return self

    def __exit__(self, *exc) -> None:
        self._stack.close()

    def submit(self, job: Callable[[FrameRenderer], T]) -> Future[T]:
        """``job(renderer)`` on a free renderer; its future."""

        def run() -> T:
            renderer = self._idle.pop()  # list.pop/append are atomic; at most `workers` jobs run at once
            try:
                return job(renderer)
            finally:
                self._idle.append(renderer)

        if self._pool is not None:
            return self._pool.submit(run)
        done: Future = Future()
        done.set_result(run())
        return done
