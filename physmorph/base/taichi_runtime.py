"""One Taichi runtime per process, shared by the MPM solver and any Taichi kernels.

``ti.init`` resets every field, so calling it twice in a process would invalidate the objects
built before; every physmorph module goes through :func:`init_taichi` instead. Fields and
kernels choose their float type explicitly (f32 or f64), so one runtime serves both.
"""

from __future__ import annotations

import inspect
import os
import sys
import time
from pathlib import Path

import taichi as ti

_state: dict = {}

# Taichi holds the lock files of its offline cache only for the moments it reads or writes the
# cache's index; one left by a process killed meanwhile (a cancelled job, a test that kills a run)
# stays, and every later process then skips the cache (each kernel compiled anew) and prints two
# warnings at its start and exit. A lock this old is such a leftover.
STALE_CACHE_LOCK_S = 600.0
# Taichi's offline cache drops its least recently used quarter once its files pass a size (100 MB by
# default). The test suite's many small solvers alone fill that, so a paper-scale run after them
# compiled its solver and calibration kernels again: 5 s of its first frame and 3 s of its second
# (benchmarks/bench_morph.py --profile paper, docs/study/performance_history.md). A gigabyte holds
# every profile's kernels together.
OFFLINE_CACHE_BYTES = 1 << 30


def clear_stale_cache_locks(now: float | None = None) -> list[Path]:
    """Remove the lock files of Taichi's offline cache (TI_OFFLINE_CACHE_FILE_PATH, else Taichi's
    default folder) older than STALE_CACHE_LOCK_S; returns the ones removed."""
    folder = os.environ.get("TI_OFFLINE_CACHE_FILE_PATH") or ti.lang.impl.default_cfg().offline_cache_file_path
    now = time.time() if now is None else now
    removed = []
    for lock in Path(folder).glob("*.lock"):
        try:
            if now - lock.stat().st_mtime > STALE_CACHE_LOCK_S:
                lock.unlink()
                removed.append(lock)
        except OSError:  # removed by another process meanwhile, or not ours to remove
            pass
    return removed


def use_short_source_positions() -> bool:
    """Make Taichi's frontend record a one-line source position for each node it translates.

    While it turns a kernel's Python AST into its IR, Taichi formats an error-message header for
    every node (the source lines and a caret line, each wrapped at 80 columns), whether or not
    anything fails. On a cache hit, when no LLVM compile follows, that formatting was a third of
    a process's kernel build: 2-6 s of a 14-20 s test-profile morph (docs/performance.md). Taichi's
    own format for Python < 3.8 is kept instead: file, line, function and the source line, without
    the carets. Returns False, changing nothing, where the Taichi version lacks that method."""
    try:
        from taichi.lang.ast.ast_transformer_utils import ASTTransformerContext
    except ImportError:  # pragma: no cover - another Taichi layout
        return False
    if getattr(ASTTransformerContext.get_pos_info, "short_positions", False):
        return True
    if not callable(getattr(ASTTransformerContext, "get_pos_info", None)):  # pragma: no cover
        return False

    def get_pos_info(self, node) -> str:
        return (f'File "{self.file}", line {node.lineno + self.lineno_offset}, in {self.func.func.__name__}:\n'
                f"{self.src[node.lineno - 1]}\n")

    get_pos_info.short_positions = True
    ASTTransformerContext.get_pos_info = get_pos_info
    return True


def use_cached_function_sources() -> bool:
    """Make Taichi's frontend read each kernel's and Taichi function's source once per process.

    Taichi inlines a ``ti.func`` at every call site, and for each inlining (and each kernel
    instance) it fetches the function's source again: ``inspect.getsourcelines`` (which tokenizes
    the module's lines to find the block and looks its module up among all loaded ones) and a
    ``textwrap.fill`` of every line. A solver's build inlines ~500 functions, so that was about a
    quarter of its frontend time. The source lines, their first line number and the file are kept
    per definition (code object) here; the tree is still parsed afresh for each use (the frontend writes
    into it) and the function's globals still read at each use, as Taichi does. Returns False,
    changing nothing, where the Taichi version lacks the function this wraps."""
    try:
        from taichi.lang import kernel_impl
    except ImportError:  # pragma: no cover - another Taichi layout
        return False
    original = getattr(kernel_impl, "_get_tree_and_ctx", None)
    if original is None or getattr(original, "cached_sources", False):
        return original is not None
    needed = ("getsourcefile", "getsourcelines", "_get_global_vars", "ASTTransformerContext")
    if not all(hasattr(kernel_impl, name) for name in needed):  # pragma: no cover - another Taichi layout
        return False
    import ast
    import textwrap

    # code object -> (file, filled source lines, first line, dedented text): keyed by the code, not
    # the function, since the stress functions are closures made anew for each solver
    sources: dict = {}

    def source_of(func):
        key = getattr(func, "__code__", func)
        if key not in sources:
            file = kernel_impl.getsourcefile(func)
            src, start_lineno = kernel_impl.getsourcelines(func)
            src = [textwrap.fill(line, tabsize=4, width=9999) for line in src]
            sources[key] = (file, src, start_lineno, textwrap.dedent("\n".join(src)))
        return sources[key]

    def _get_tree_and_ctx(self, excluded_parameters=(), is_kernel=True, arg_features=None, args=None,
                          ast_builder=None, is_real_function=False):
        file, src, start_lineno, text = source_of(self.func)
        tree = ast.parse(text)
        tree.body[0].decorator_list = []
        global_vars = kernel_impl._get_global_vars(self.func)
        if is_kernel or is_real_function:  # template arguments are globals of the kernel's body
            for i in self.template_slot_locations:
                global_vars[self.arguments[i].name] = args[i]
        return tree, kernel_impl.ASTTransformerContext(
            excluded_parameters=excluded_parameters, is_kernel=is_kernel, func=self, arg_features=arg_features,
            global_vars=global_vars, argument_data=args, src=list(src), start_lineno=start_lineno, file=file,
            ast_builder=ast_builder, is_real_function=is_real_function)

    _get_tree_and_ctx.cached_sources = True
    kernel_impl._get_tree_and_ctx = _get_tree_and_ctx
    return True


def use_fast_class_test() -> bool:
    """Make Taichi tell a kernel or Taichi function defined in a class body from the frames alone.

    At each ``@ti.kernel`` and ``@ti.func`` Taichi decides whether it decorates a method by reading
    the source line of the frame around the definition (``inspect.getframeinfo``: a look-up of the
    module among every loaded one, torch's included). The library's imports (115 definitions) took
    1.18-1.39 s in a process with torch loaded, 0.96-1.28 s with this, paid by every workflow job
    and again at each solver build for the functions made then. A class body's frame is told here
    by what Python puts in every class body (``__qualname__`` among its names, in a frame that is
    not a function's): the frame below the one Taichi reads, which runs the class statement. The
    same answers for every definition of the library (tests/base). Installed when this module is
    imported: every module that defines kernels imports it before them. Returns False, changing
    nothing, where the Taichi version lacks the function this replaces."""
    try:
        from taichi.lang import kernel_impl
    except ImportError:  # pragma: no cover - another Taichi layout
        return False
    original = getattr(kernel_impl, "_inside_class", None)
    if original is None:  # pragma: no cover - another Taichi layout
        return False
    if getattr(original, "fast_class_test", False):
        return True

    def _inside_class(level_of_class_stackframe):
        try:
            # Taichi's level is the frame running the class statement (counted from its own
            # function, which this one replaces); the class body is the frame below it
            frame = sys._getframe(level_of_class_stackframe - 1)
        except ValueError:
            return False
        # a function's frame is optimised; a module's names have no __qualname__
        return not frame.f_code.co_flags & inspect.CO_OPTIMIZED and "__qualname__" in frame.f_locals

    _inside_class.fast_class_test = True
    _inside_class.taichi_original = original
    kernel_impl._inside_class = _inside_class
    return True


def resolve_device(device: str) -> str:
    """'auto' -> 'cuda' when a CUDA device is usable, else 'cpu'. 'cpu'/'cuda' pass through."""
    if device not in ("auto", "cpu", "cuda"):
        raise ValueError(f"device must be auto, cpu or cuda, got {device!r}")
    if device != "auto":
        return device
    try:
        import torch

        return "cuda" if torch.cuda.is_available() else "cpu"
    except ImportError:  # pragma: no cover - torch is a hard dependency
        return "cpu"


def init_taichi(device: str = "cpu", threads: int | None = None, debug: bool = False) -> str:
    """Initialise Taichi once; later calls must agree on the device. Returns the arch used."""
    arch = resolve_device(device)
    if _state:
        if _state["arch"] != arch:
            raise RuntimeError(
                f"Taichi already initialised on {_state['arch']}; cannot switch to {arch} in one process"
            )
        return arch
    if threads is None:
        env = os.environ.get("PHYSMORPH_THREADS")
        threads = int(env) if env else None
    kwargs = dict(arch=ti.cuda if arch == "cuda" else ti.cpu, debug=debug, log_level=ti.WARN,
                  offline_cache=True, offline_cache_max_size_of_files=OFFLINE_CACHE_BYTES, random_seed=0)
    if os.environ.get("PHYSMORPH_QUICK_COMPILE") == "1":
        # Taichi's IR optimisation passes off: kernels compile in about 60 % of the time, for
        # many small solvers of different settings (the test suite sets it; runs do not)
        kwargs["advanced_optimization"] = False
    if threads is not None and arch == "cpu":
        kwargs["cpu_max_num_threads"] = int(threads)
    if os.environ.get("PHYSMORPH_KERNEL_PROFILER") == "1":
        # each kernel's launches timed (benchmarks/bench_roofline.py); never in a run
        kwargs["kernel_profiler"] = True
    clear_stale_cache_locks()
    ti.init(**kwargs)
    use_short_source_positions()
    use_cached_function_sources()
    _state.update(arch=arch, threads=threads, debug=debug)
    return arch


def ensure_taichi() -> None:
    """The process's Taichi runtime, whichever device a run started it on (kernels with NumPy
    array arguments run on either); the CPU where nothing has started one."""
    if not _state:
        init_taichi("cpu")


def taichi_state() -> dict:
    """What the runtime was initialised with (empty before :func:`init_taichi`)."""
    return dict(_state)


# before any kernel or Taichi function of the library is defined (use_fast_class_test)
use_fast_class_test()
