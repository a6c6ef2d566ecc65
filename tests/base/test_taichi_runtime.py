"""The process's Taichi runtime (physmorph.base.taichi_runtime): a lock of Taichi's offline cache left
by a killed process is cleared before the runtime starts, a lock in use is not; Taichi's test of a
class body, replaced, answers as Taichi's own for every definition of the library."""

import os
import re
import time
from pathlib import Path

import taichi as ti
from taichi.lang import kernel_impl

import physmorph
from physmorph.base.taichi_runtime import STALE_CACHE_LOCK_S, clear_stale_cache_locks, use_fast_class_test


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


def _definitions_decided_by_both(monkeypatch, run) -> list:
    """(Taichi's answer, the fast test's answer) for each kernel and Taichi function ``run`` defines."""
    fast = kernel_impl._inside_class
    answers = []

    def both(level_of_class_stackframe):
        # one frame more than either function counts from (this one): Taichi's own reads the frame
        # one further, the fast one counts from a frame further down as well
        theirs = fast.taichi_original(level_of_class_stackframe + 1)
        answers.append((theirs, fast(level_of_class_stackframe + 1)))
        return theirs

    monkeypatch.setattr(kernel_impl, "_inside_class", both)
    run()
    return answers


def test_the_fast_class_test_is_installed_and_answers_as_taichi_for_every_library_definition(monkeypatch):
    """Every library file with a kernel or a Taichi function run again in a namespace of its own
    (its classes and kernels defined anew, nothing compiled): at each definition the replaced test
    and Taichi's agree, methods and plain functions among them."""
    import physmorph.mpm.lanes  # noqa: F401  (a module with kernels: it installs the test first)

    assert getattr(kernel_impl._inside_class, "fast_class_test", False) and use_fast_class_test()
    root = Path(physmorph.__file__).parent
    files = [f for f in sorted(root.rglob("*.py")) if re.search(r"^\s*@ti\.(kernel|func)", f.read_text(), re.M)]
    assert len(files) >= 15

    def run():
        for f in files:
            package = ".".join(f.relative_to(root.parent).with_suffix("").parts[:-1])
            exec(compile(f.read_text(), str(f), "exec"), {"__name__": f"{package}._probe", "__package__": package})

    answers = _definitions_decided_by_both(monkeypatch, run)
    assert len(answers) >= 100 and all(theirs == ours for theirs, ours in answers), answers
    assert {True, False} == {ours for _, ours in answers}


def test_the_fast_class_test_tells_a_method_from_a_function_and_a_nested_class():
    """Kernels and Taichi functions in a class body, in a class nested in a function and in a
    function: methods in the first two only (Taichi binds them to the instance)."""

    def definitions():
        @ti.data_oriented
        class Outer:
            @ti.kernel
            def method_kernel(self):
                pass

            @ti.func
            def method_func(self):
                pass

        @ti.kernel
        def local_kernel():
            pass

        return Outer.method_kernel, local_kernel

    method, local = definitions()
    assert method._is_classkernel and not local._is_classkernel



def test_every_module_with_kernels_installs_the_fast_class_test_before_them():
    """Each library module that defines a kernel or a Taichi function imports taichi_runtime (which
    installs the fast test) before its first definition, whatever was imported before it."""
    root = Path(physmorph.__file__).parent
    checked = 0
    for f in sorted(root.rglob("*.py")):
        text = f.read_text()
        first = re.search(r"^\s*@ti\.(kernel|func|data_oriented)", text, re.M)
        if first is None or f.name == "taichi_runtime.py":
            continue
        head = text[:first.start()]
        assert re.search(r"^(from physmorph\.base\.taichi_runtime import|import physmorph\.base\.taichi_runtime|"
                         r"from physmorph\.base import taichi_runtime)", head, re.M), f
        checked += 1
    assert checked >= 20
