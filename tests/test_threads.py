"""PyTorch's thread count follows the cores other processes leave free (nvp.threads)."""

from __future__ import annotations

import pytest
import torch

from nvp import threads
from nvp.threads import ThreadGovernor, threads_for


def test_threads_for_the_free_cores():
    assert threads_for(0.0, 2) == 2
    assert threads_for(0.3, 2) == 2
    assert threads_for(1.0, 2) == 1
    assert threads_for(2.0, 2) == 1  # never none
    assert threads_for(1.6, 8) == 6


@pytest.fixture
def clock(monkeypatch):
    """A fake machine: ``state`` holds the cores' busy seconds, this process's CPU seconds and the time."""
    state = {"busy": 100.0, "own": 10.0, "now": 1000.0}
    monkeypatch.setattr(threads, "_machine_busy_s", lambda: state["busy"])
    monkeypatch.setattr(threads, "_own_s", lambda: state["own"])
    monkeypatch.setattr(threads.time, "monotonic", lambda: state["now"])
    monkeypatch.setattr(threads, "available_cores", lambda: 2)
    monkeypatch.setattr(threads, "_TORCH_DEFAULT", 2)
    monkeypatch.delenv("NVP_THREADS", raising=False)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    before = torch.get_num_threads()
    yield state
    torch.set_num_threads(before)


def _run(state, seconds, own_cores, other_cores):
    state["now"] += seconds
    state["own"] += seconds * own_cores
    state["busy"] += seconds * (own_cores + other_cores)


def test_the_governor_gives_up_a_core_while_another_process_uses_it(clock):
    g = ThreadGovernor(interval_s=2.0, first_s=0.5)
    assert g.threads == 2 == torch.get_num_threads()  # every core to start with
    _run(clock, 0.3, 2.0, 0.0)
    assert g.update() == 2  # too early to look
    _run(clock, 0.3, 2.0, 0.0)
    assert g.update() == 2  # idle machine
    _run(clock, 1.0, 1.0, 1.0)
    assert g.update() == 2  # too early to look again
    _run(clock, 1.5, 1.0, 1.0)  # another process keeps a core busy
    assert g.update() == 1 == torch.get_num_threads()
    _run(clock, 2.5, 1.0, 1.0)
    assert g.update() == 1
    _run(clock, 2.5, 1.0, 0.05)  # it stopped
    assert g.update() == 2 == torch.get_num_threads()


def test_a_fixed_count_is_kept(clock, monkeypatch):
    monkeypatch.setenv("NVP_THREADS", "1")
    g = ThreadGovernor()
    assert g.fixed == 1 and torch.get_num_threads() == 1
    _run(clock, 5.0, 1.0, 0.0)
    assert g.update() == 1
    assert ThreadGovernor(threads=2).threads == 2


def test_never_more_threads_than_pytorch_would_use(clock, monkeypatch):
    monkeypatch.setattr(threads, "available_cores", lambda: 8)  # 8 logical cores, PyTorch's default 2
    g = ThreadGovernor()
    assert g.cores == 2 and g.threads == 2


def test_a_fixed_count_fixes_openmp_too_unless_the_user_did(monkeypatch):
    monkeypatch.setenv("NVP_THREADS", "1")
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    threads.fix_openmp_threads()
    assert threads.os.environ["OMP_NUM_THREADS"] == "1"
    monkeypatch.setenv("OMP_NUM_THREADS", "3")  # the user's own choice stays
    threads.fix_openmp_threads()
    assert threads.os.environ["OMP_NUM_THREADS"] == "3"
    monkeypatch.delenv("NVP_THREADS")
    monkeypatch.delenv("OMP_NUM_THREADS")
    threads.fix_openmp_threads()  # nothing fixed: OpenMP keeps its default
    assert "OMP_NUM_THREADS" not in threads.os.environ
