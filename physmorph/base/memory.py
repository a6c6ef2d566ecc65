"""Giving freed heap memory back to the operating system once a frame, before its commit.

glibc serves allocations under its mmap threshold from the heap, and that threshold rises to 32 MB
after the first large block is freed, so the morph loop's stage-sized NumPy and torch temporaries
(11-34 MB each at the paper's 471K particles) are carved from the heap. Freed, they stay resident
(glibc returns only the heap's top), and each stage's transient then sits on the previous stages'
leftovers: at the paper profile the frame's resident set stayed ~1 GB above what the frame holds.
``malloc_trim(0)`` releases every free page of the heap (tens of milliseconds); other C libraries
have no such call and nothing is done there.

The morph loop trims before the render (the frame's largest transient) and before the commit, and
the render once more before its rasterizer backward, not after every stage: pages given back are faulted in again by the next stage that
allocates, and on a virtual machine that hands freed memory back to its host a fault costs up to
~2 ms per MB (the 2-core development machine). At the paper profile a trim after every stage took
230-290K page faults a frame (docs/performance.md).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools


@functools.lru_cache(maxsize=1)
def _malloc_trim():
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):  # not glibc (musl, macOS): nothing to trim
        return None


def release_free_memory() -> bool:
    """Return the heap's free pages to the operating system (glibc ``malloc_trim``); True if the
    C library has the call (whether or not any page was free)."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True
