"""Worker pools of the render loop and the frame cache: one resource (a renderer, a rasterizer) per thread."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import ExitStack
from typing import TYPE_CHECKING, Generic, TypeVar

import torch

if TYPE_CHECKING:
    from renderer.render import FrameRenderer

T = TypeVar("T")
R = TypeVar("R")


class Workers(Generic[R]):
    """``resources`` (objects one thread may use at a time: an OpenGL context is one), each job on a free
    one, in as many threads as there are resources, each thread with one PyTorch thread; with a single
    resource the jobs run in the calling thread (a profiler sees them). Use as a context manager: leaving
    it stops the threads (what has not started is cancelled), then closes ``owned`` (the resources' own
    closing, when the pool is to do it)."""

    def __init__(self, resources: Sequence[R], owned: ExitStack | None = None) -> None:
        self._stack = ExitStack()
        if owned is not None:  # what closes the resources: last, once the threads have stopped
            self._stack.enter_context(owned)
        self._idle = list(resources)
        self.size = len(self._idle)
        """How many jobs run at once."""
        self._pool = None
        if len(self._idle) > 1:
            self._pool = ThreadPoolExecutor(len(self._idle), initializer=torch.set_num_threads, initargs=(1,))
            self._stack.enter_context(self._pool)
            self._stack.callback(self._pool.shutdown, cancel_futures=True)  # first: nothing new starts

    def __enter__(self) -> Workers[R]:
        return self

    def __exit__(self, *exc) -> None:
        self._stack.close()

    def submit(self, job: Callable[[R], T]) -> Future[T]:
        """``job(resource)`` on a free resource; its future."""

        def run() -> T:
            resource = self._idle.pop()  # list.pop/append are atomic; at most len(resources) jobs at once
            try:
                return job(resource)
            finally:
                self._idle.append(resource)

        if self._pool is not None:
            return self._pool.submit(run)
        done: Future = Future()
        done.set_result(run())
        return done

    def in_order(self, jobs: Iterable[Callable[[R], T] | None]) -> Iterator[T | None]:
        """Each of ``jobs``'s results in order (None for a None job), the next ones running meanwhile: at
        most one job per resource is taken from ``jobs`` ahead of the result being handed out."""
        pending: deque[Future | None] = deque()
        for job in jobs:
            pending.append(None if job is None else self.submit(job))
            while pending and (len(pending) >= self.size or pending[0] is None):
                future = pending.popleft()
                yield None if future is None else future.result()
        for future in pending:
            yield None if future is None else future.result()


class RenderWorkers(Workers["FrameRenderer"]):
    """``workers`` renderers of one person (``fr`` and twins, :meth:`FrameRenderer.twin`) as :class:`Workers`
    (see :func:`renderer.loop.render_frames`; a GPU renders one frame at a time anyway); leaving it also
    closes the twins."""

    def __init__(self, fr: FrameRenderer, workers: int) -> None:
        twins = ExitStack()
        super().__init__([fr] + [twins.enter_context(fr.twin()) for _ in range(workers - 1)], twins)
