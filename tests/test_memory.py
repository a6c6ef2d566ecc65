"""Freed heap memory goes back to the system before a frame's render and its commit (physmorph.memory)."""

import os
import platform

import numpy as np
import pytest

from physmorph.memory import release_free_memory


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc's malloc_trim")
def test_freed_heap_blocks_leave_the_resident_set():
    """200 MB of 100 KB arrays (under glibc's mmap threshold, so on the heap) freed below a block
    still in use stay resident until released; released, at least half of them leave."""
    blocks = [np.ones(12_800) for _ in range(2_000)]  # 100 KB each
    keep = blocks[-1]  # the heap's top stays in use: glibc cannot shrink the heap by itself
    before = _rss_mb()
    del blocks
    freed = _rss_mb()
    assert release_free_memory()
    after = _rss_mb()
    assert freed - after > 100, (before, freed, after)
    assert keep.sum() == 12_800
