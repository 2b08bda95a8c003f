"""Giving the C heap's freed memory back to the system (glibc's `malloc_trim`).

onnxruntime runs with its CPU arena off (`common.partition.runtime`), so its tensors come from
the C allocator. The first run of a session allocates tensor by tensor (its memory pattern is
traced then); glibc serves those from the heap and, after they are freed, keeps the pages
resident: with zoo:stereo at 640x480 the robot's startup runs (warm-up, profile) left ~1.1 GB of
freed heap in the process. Later runs take one planned block per run, which glibc maps and
unmaps, so a trim after startup is not undone by the frames (`docs/robot.md`, Memory).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import logging
from collections.abc import Callable

import psutil

log = logging.getLogger(__name__)
MiB = 1024 * 1024


@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    """glibc's `malloc_trim(pad)`, or None where the C library has none (musl, macOS)."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        trim = ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError):
        return None
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    fn: Callable[[int], int] = trim
    return fn


def can_trim() -> bool:
    """Whether this process's C library can give freed heap memory back (glibc)."""
    return _malloc_trim() is not None


def trim_heap() -> bool:
    """Return the freed memory of every malloc arena to the system (`malloc_trim(0)`: the free
    pages inside the heaps too, not just the top). True when some memory was released; False
    when none was, or the C library cannot (then nothing happens)."""
    trim = _malloc_trim()
    if trim is None:
        return False
    return bool(trim(0))


def release_freed_memory(who: str) -> bool:
    """`trim_heap`, and one line saying what it gave back (`who`: the daemon, in the line).
    Meant for the end of a daemon's startup, whose first session runs freed most of what they
    allocated (the robot calls it once its profile is measured)."""
    process = psutil.Process()
    resident = process.memory_info().rss
    if not trim_heap():
        return False
    log.info(
        "%s: freed startup memory returned to the system (RSS %.0f -> %.0f MiB)",
        who,
        resident / MiB,
        process.memory_info().rss / MiB,
    )
    return True
