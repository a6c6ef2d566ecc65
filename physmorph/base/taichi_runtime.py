"""One Taichi runtime per process, shared by the MPM solver and any Taichi kernels.

``ti.init`` resets every field, so calling it twice in a process would invalidate the objects
built before; every physmorph module goes through :func:`init_taichi` instead. Fields and
kernels choose their float type explicitly (f32 or f64), so one runtime serves both.
"""

from __future__ import annotations

import os

import taichi as ti

_state: dict = {}


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
                  offline_cache=True, random_seed=0)
    if os.environ.get("PHYSMORPH_QUICK_COMPILE") == "1":
        # Taichi's IR optimisation passes off: kernels compile in about 60 % of the time, for
        # many small solvers of different settings (the test suite sets it; runs do not)
        kwargs["advanced_optimization"] = False
    if threads is not None and arch == "cpu":
        kwargs["cpu_max_num_threads"] = int(threads)
    if os.environ.get("PHYSMORPH_KERNEL_PROFILER") == "1":
        # each kernel's launches timed (benchmarks/bench_roofline.py); never in a run
        kwargs["kernel_profiler"] = True
    ti.init(**kwargs)
    use_short_source_positions()
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
