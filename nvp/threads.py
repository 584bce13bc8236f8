"""How many threads PyTorch should use now: as many as there are cores the other processes leave free.

On the 2-core machines nvp targets, PyTorch's two threads make the renderer's networks about 1.5x faster
than one when the machine is idle; when another process keeps a core busy, the two threads wait on each
other (OpenMP's busy waiting) and ``nvp dub`` falls from 21.6 to 6.5 frames/s, while one thread keeps
15.6 frames/s (512² demo person; ``OMP_WAIT_POLICY=PASSIVE`` gave 14.5 busy but 17.0 idle).
:class:`ThreadGovernor` watches the cores' busy time (``/proc/stat``) minus this process's own CPU time and
sets ``torch.set_num_threads`` to the free cores, every few seconds, so a long job adapts when the load
changes. A fixed count (``NVP_THREADS`` or ``OMP_NUM_THREADS`` in the environment, or ``threads``) turns
the governor off (renderer training and ``nvp live`` use it). ``nvp dub`` and ``nvp eval`` instead render
:func:`frame_workers` frames at once on one thread each (see :func:`renderer.loop.render_frames`).
"""

from __future__ import annotations

import os
import resource
import time
from pathlib import Path

ENV = "NVP_THREADS"
"""Environment variable that fixes PyTorch's thread count for nvp (as ``OMP_NUM_THREADS`` does)."""
INTERVAL_S = 2.0
"""Seconds between two looks at the load."""
FIRST_S = 0.5
"""Seconds from the start to the first look."""


_TORCH_DEFAULT: int | None = None
"""PyTorch's own thread count when the first governor was made (its physical cores, usually)."""


def available_cores() -> int:
    """Cores this process may run on (logical ones)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _machine_busy_s() -> float | None:
    """Seconds of CPU time all cores have spent busy since boot (``/proc/stat``), None where unknown."""
    try:
        fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()
    except OSError:
        return None
    if not fields or fields[0] != "cpu":
        return None
    ticks = [int(x) for x in fields[1:9]]  # user nice system idle iowait irq softirq steal
    busy = sum(ticks) - ticks[3] - ticks[4]
    return busy / os.sysconf("SC_CLK_TCK")


def _own_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def fixed_threads() -> int | None:
    """The thread count the user fixed in the environment (``NVP_THREADS``, else ``OMP_NUM_THREADS``)."""
    for name in (ENV, "OMP_NUM_THREADS"):
        value = os.environ.get(name, "").strip()
        if value.isdigit() and int(value) > 0:
            return int(value)
    return None


def fix_openmp_threads() -> None:
    """With ``NVP_THREADS`` set and ``OMP_NUM_THREADS`` not, set ``OMP_NUM_THREADS`` to it too; call before
    PyTorch is imported (the CLI's start). ``torch.set_num_threads`` alone left OpenMP threads that spin
    while they wait: two ``NVP_THREADS=1`` dubs of a 1 s clip side by side on 2 cores (a cluster's two
    workers) took 13.6-32.6 s each, 3.7 s with ``OMP_NUM_THREADS`` set as well (3.8 s with
    ``OMP_WAIT_POLICY=PASSIVE`` instead; AMD EPYC, 2026-11-28)."""
    fixed = os.environ.get(ENV, "").strip()
    if fixed.isdigit() and int(fixed) > 0 and not os.environ.get("OMP_NUM_THREADS", "").strip():
        os.environ["OMP_NUM_THREADS"] = fixed


def frame_workers() -> int:
    """How many frames to render at once (one PyTorch thread each, see
    :func:`renderer.loop.render_frames`): the fixed count (:func:`fixed_threads`), else the cores this
    process may use, at most PyTorch's own default thread count (hyper-threads do not speed the networks
    up)."""
    import torch

    global _TORCH_DEFAULT
    if _TORCH_DEFAULT is None:
        _TORCH_DEFAULT = torch.get_num_threads()
    return fixed_threads() or max(1, min(available_cores(), _TORCH_DEFAULT))


def threads_for(others_busy: float, cores: int) -> int:
    """Threads to use when other processes keep ``others_busy`` cores busy out of ``cores``: the free
    ones, rounded, at least 1."""
    return max(1, min(cores, round(cores - others_busy)))


class ThreadGovernor:
    """Keeps ``torch.set_num_threads`` at the number of cores other processes leave free.

    Call :meth:`update` often (every frame); it looks at the load ``first_s`` after it was made, then
    every ``interval_s``, and returns the thread count in use. ``threads``: a fixed count (no governing);
    by default the environment's (:func:`fixed_threads`), else governed, starting with every core (at most
    PyTorch's own default count).
    """

    def __init__(
        self, threads: int | None = None, interval_s: float = INTERVAL_S, first_s: float = FIRST_S
    ) -> None:
        import torch

        global _TORCH_DEFAULT
        if _TORCH_DEFAULT is None:
            _TORCH_DEFAULT = torch.get_num_threads()
        self._torch = torch
        self.fixed = threads or fixed_threads()
        # never more than PyTorch would use on its own (hyper-threads do not speed these networks up)
        self.cores = min(available_cores(), _TORCH_DEFAULT)
        self.interval_s = interval_s
        self._wait = first_s
        self._last = self._sample()
        self.threads = self.fixed or self.cores
        torch.set_num_threads(self.threads)

    def _sample(self) -> tuple[float | None, float, float]:
        return _machine_busy_s(), _own_s(), time.monotonic()

    def update(self) -> int:
        """Look at the load again when its time has come; returns the thread count in use."""
        if self.fixed or self._last[0] is None:
            return self.threads
        now = self._sample()
        elapsed = now[2] - self._last[2]
        if elapsed < self._wait:
            return self.threads
        self._wait = self.interval_s
        if elapsed > 0 and now[0] is not None:
            others = max(0.0, (now[0] - self._last[0]) - (now[1] - self._last[1])) / elapsed
            wanted = threads_for(others, self.cores)
            if wanted != self.threads:
                self._torch.set_num_threads(wanted)
                self.threads = wanted
        self._last = now
        return self.threads
