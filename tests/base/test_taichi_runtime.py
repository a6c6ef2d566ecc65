"""The process's Taichi runtime (physmorph.base.taichi_runtime): a lock of Taichi's offline cache left
by a killed process is cleared before the runtime starts, a lock in use is not."""

import os
import time

from physmorph.base.taichi_runtime import STALE_CACHE_LOCK_S, clear_stale_cache_locks


def test_a_stale_lock_of_the_kernel_cache_is_removed_and_a_fresh_one_kept(tmp_path, monkeypatch):
    monkeypatch.setenv("TI_OFFLINE_CACHE_FILE_PATH", str(tmp_path))
    stale, fresh, index = tmp_path / "ticache.lock", tmp_path / "metadata.lock", tmp_path / "ticache.tcb"
    for path in (stale, fresh, index):
        path.write_bytes(b"")
    past = time.time() - STALE_CACHE_LOCK_S - 60
    os.utime(stale, (past, past))
    os.utime(index, (past, past))
    assert clear_stale_cache_locks() == [stale]
    assert not stale.exists() and fresh.exists() and index.exists()  # the cache itself untouched
    assert clear_stale_cache_locks(now=time.time() + STALE_CACHE_LOCK_S + 60) == [fresh]


def test_no_cache_folder_is_no_error(tmp_path, monkeypatch):
    monkeypatch.setenv("TI_OFFLINE_CACHE_FILE_PATH", str(tmp_path / "none"))
    assert clear_stale_cache_locks() == []
