"""How the morph's frames use the C library's heap: freed memory held for the next frame.

glibc serves allocations under its mmap threshold (at most 32 MB) from the heap and larger ones
by mmap, returned to the system when freed; free memory at the heap's top is returned once it
exceeds the trim threshold, and ``malloc_trim(0)`` returns every free page of the heap. Memory
returned this way has to be faulted in again by the next allocation, and on a virtual machine that
hands freed pages back to its host (free page reporting: on the 2-core development machine within
~10 s of their release) each such fault costs up to ~7 ms per MB. A paper-scale frame allocates
and frees well over a gigabyte of stage-sized NumPy and torch temporaries (11-50 MB each at the
paper's 471K particles and 8 x 960x540 pixels), so every frame paid for them again.

:func:`held_heap` (the morph run, physmorph.morph.loop.run_morph): for the duration of a run,
every allocation comes from the heap (no mmap'd blocks) and nothing is returned (no trim), so a
frame's temporaries reuse the pages the frames before them faulted in. The resident set is then
the heap's high-water mark: the largest of the stages' transients on top of what the frame holds.
Other C libraries have no such settings, and nothing is done there. What it costs and saves at
the paper's scale: docs/study/performance_history.md.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import functools

# glibc's mallopt parameters (malloc.h) and their defaults
M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4
DEFAULT_TRIM_THRESHOLD, DEFAULT_MMAP_MAX = 128 * 1024, 65536
# the largest trim threshold mallopt takes (an int): 2 GB of free memory at the heap's top
TRIM_THRESHOLD_MAX = 2**31 - 1

_held = 0  # the depth of nested held_heap contexts in this process


@functools.lru_cache(maxsize=1)
def _glibc():
    """glibc's malloc_trim and mallopt, or None (another C library: musl, macOS)."""
    name = ctypes.util.find_library("c")
    try:
        lib = ctypes.CDLL(name) if name else None
        return (lib.malloc_trim, lib.mallopt) if lib is not None else None
    except (OSError, AttributeError):
        return None


@contextlib.contextmanager
def held_heap():
    """Within the block, glibc serves every allocation from its heap and returns no freed memory
    to the system (module docstring); after it, its defaults are back and the heap's free pages are
    returned. Yields True where the C library is glibc, else False (nothing changes)."""
    global _held
    calls = _glibc()
    if calls is None:
        yield False
        return
    mallopt = calls[1]
    if not _held:
        mallopt(M_MMAP_MAX, 0)
        mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_MAX)
    _held += 1
    try:
        yield True
    finally:
        _held -= 1
        if not _held:
            mallopt(M_MMAP_MAX, DEFAULT_MMAP_MAX)
            mallopt(M_TRIM_THRESHOLD, DEFAULT_TRIM_THRESHOLD)
            calls[0](0)
