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


def test_other_systems_are_left_alone(monkeypatch):
    monkeypatch.setattr(sys, "platform", "darwin")
    assert allocator.keep_freed_memory() is False


def test_the_cli_sets_it_before_any_command(monkeypatch):
    from nvp.app import cli

    calls = []
    monkeypatch.setattr(allocator, "keep_freed_memory", lambda: calls.append(1) or True)
    assert cli.main(["track", "/nonexistent/video.mp4", "-o", "/nonexistent/out"]) == 2
    assert calls == [1]
