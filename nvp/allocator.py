"""Keeping freed memory in the process instead of handing it back to the system after every frame.

Every rendered frame allocates and frees the same few dozen arrays of 0.1-3 MB (crops, maps at footage
resolution, the paste's region). With glibc's defaults the freed top of the heap is given back to the system
(``M_TRIM_THRESHOLD``, 128 kB at first) and the next frame's arrays fault their pages in again: an OpenCV read
of a 1080p paste's maps that takes 0.2 ms took 1.1 ms that way, and two render threads faulting pages at once
wait on each other in the kernel. :func:`keep_freed_memory` raises the trim threshold to 1 GB and serves
requests below 32 MB (glibc's largest threshold) from the heap; peak memory stays what the job needs (the
freed arrays are reused by the next frame). Measured with ``scripts/bench/dub.py`` in the closing notes and
docs/experiments/memory.md.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

M_TRIM_THRESHOLD = -1
"""glibc ``mallopt`` parameters (``malloc.h``)."""
M_MMAP_THRESHOLD = -3
TRIM_THRESHOLD = 1 << 30
"""Bytes of free memory at the top of the heap above which glibc gives it back to the system."""
MMAP_THRESHOLD = 32 << 20
"""Requests of at least this many bytes get their own mapping (glibc's maximum on 64-bit systems)."""


def keep_freed_memory() -> bool:
    """Set glibc's allocator to keep freed memory (see the module); False where the C library is not glibc
    (macOS, musl: nothing is changed) or glibc refuses a value."""
    mallopt = _glibc("mallopt", (ctypes.c_int, ctypes.c_int))
    if mallopt is None:
        return False
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))


def release_freed_memory() -> bool:
    """Give the memory glibc holds freed back to the system (``malloc_trim``), once after a step whose
    temporaries grew with the input (a long dub's audio to expressions, before it renders): kept, it would
    add to what the next step allocates anew. False where the C library is not glibc."""
    trim = _glibc("malloc_trim", (ctypes.c_size_t,))
    return trim is not None and bool(trim(0))


def _glibc(name: str, argtypes: tuple):
    """glibc's function ``name`` (returning an int), or None where the C library is not glibc's."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        func = getattr(ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6"), name)
    except (OSError, AttributeError):
        return None
    func.argtypes, func.restype = argtypes, ctypes.c_int
    return func
