"""Tests for nvp.allocator: glibc keeps freed memory; elsewhere nothing changes."""

from __future__ import annotations

import platform
import sys

import numpy as np
import pytest

from nvp import allocator


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's allocator only")
def test_glibc_keeps_freed_memory_and_arrays_still_work():
    assert allocator.keep_freed_memory() is True
    for _ in range(3):  # arrays above the old thresholds are allocated, filled and freed as before
        a = np.ones((1024, 1024, 3), np.float32)
        assert float(a.sum()) == 3 * 1024 * 1024
        del a


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's allocator only")
def test_freed_memory_kept_by_glibc_goes_back_to_the_system():
    def rss_mb() -> float:
        status = open("/proc/self/status").read()
        return int(next(line.split()[1] for line in status.splitlines() if line.startswith("VmRSS:"))) / 1024

    allocator.keep_freed_memory()
    blocks = [np.ones(1 << 18, np.float32) for _ in range(200)]  # 200 MB in 1 MB arrays, from the heap
    del blocks[:-1]  # the last one keeps the heap's top: only a trim of its middle gives the rest back
    before = rss_mb()
    assert allocator.release_freed_memory() is True
    assert rss_mb() < before - 100


def test_other_systems_are_left_alone(monkeypatch):
    monkeypatch.setattr(sys, "platform", "darwin")
    assert allocator.keep_freed_memory() is False
    assert allocator.release_freed_memory() is False


def test_the_cli_sets_it_before_any_command(monkeypatch):
    from nvp.app import cli

    calls = []
    monkeypatch.setattr(allocator, "keep_freed_memory", lambda: calls.append(1) or True)
    assert cli.main(["track", "/nonexistent/video.mp4", "-o", "/nonexistent/out"]) == 2
    assert calls == [1]
