"""Training on several processes with torch's own engine: ``torchrun`` starts them, this module joins them.

    torchrun --standalone --nproc_per_node 2 -m nvp.app.cli train-audio2exp corpus/ -o out/

Under ``torchrun`` (``WORLD_SIZE`` > 1 in the environment) :func:`process_group` joins the process group
(gloo on CPU, nccl on CUDA); without it, it is a one-process group and nothing changes. Each process
computes its share of every batch and DistributedDataParallel averages the gradients. Losses that are not
means of per-item terms (an RMS) are made from sums over all processes (:meth:`Group.total`), so N
processes compute the one-process loss and gradient, up to float rounding.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import TYPE_CHECKING

from nvp.errors import NvpError

if TYPE_CHECKING:
    import torch


@dataclass(frozen=True)
class Group:
    """This process's place among the training processes."""

    rank: int
    world: int

    @property
    def main(self) -> bool:
        """The process that validates, saves and reports."""
        return self.rank == 0

    def share(self, n: int) -> slice:
        """This process's part of a batch of ``n`` items (``n`` must divide evenly)."""
        if n % self.world:
            raise NvpError(f"a batch of {n} cannot be split evenly over {self.world} processes")
        k = n // self.world
        return slice(self.rank * k, (self.rank + 1) * k)

    def barrier(self) -> None:
        if self.world > 1:
            import torch.distributed as dist

            dist.barrier()

    def add_up(self, t: torch.Tensor, patience: float = 10.0) -> None:
        """Sum ``t`` over the processes in place, and return only once gloo has let go of it.

        gloo's worker thread drops its reference to a finished operation a moment after the caller's wait
        ends, and a later barrier keeps the operations still in progress alive. When Python has already
        dropped the tensor, that last reference frees its Python object from the worker thread, which must
        take the GIL; at interpreter exit this kills the process (``terminate called without an active
        exception``, SIGABRT: caught in a core dump of the torchrun test on a busy core, about 1 run in 30).
        Waiting here until Python holds the only reference (``patience`` seconds at most) leaves nothing for
        the worker to free later."""
        if self.world == 1:
            return
        import time

        import torch.distributed as dist

        dist.all_reduce(t)
        if dist.get_backend() != "gloo":
            return
        deadline = time.monotonic() + patience
        while t._use_count() > 1 and time.monotonic() < deadline:
            time.sleep(1e-4)

    def mean(self, value: float) -> float:
        """The mean of ``value`` over the processes."""
        if self.world == 1:
            return value
        import torch

        t = torch.tensor([value], dtype=torch.float64)
        self.add_up(t)
        return float(t.item()) / self.world

    def total(self, local: torch.Tensor) -> torch.Tensor:
        """``local`` summed over the processes, with the gradient of this process's own part only (the
        other processes' parts are constants here; each process differentiates its own)."""
        if self.world == 1:
            return local

        others = local.detach().clone()
        self.add_up(others)
        return local + (others - local.detach())


def process_group(device: str = "cpu") -> Group:
    """Join ``torchrun``'s process group (once; later calls return the same group)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return Group(0, 1)
    import torch.distributed as dist

    if not dist.is_initialized():
        import atexit

        dist.init_process_group("nccl" if device.startswith("cuda") else "gloo")
        atexit.register(_leave)
    return Group(dist.get_rank(), dist.get_world_size())


def _leave() -> None:
    """Leave the process group cleanly at exit (gloo aborts a process that exits while still in it)."""
    import torch.distributed as dist

    if dist.is_initialized():
        dist.barrier()
        dist.destroy_process_group()
