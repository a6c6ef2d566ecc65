"""Freed heap memory is held for the next frame through a morph run (physmorph.base.memory), and
the morph's memory estimate asks the solver what it stores (physmorph.settings.solver_memory)."""

import os
import platform

import numpy as np
import pytest

from physmorph.base.memory import held_heap


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc's mallopt")
def test_a_held_heap_keeps_freed_blocks_for_the_next_and_gives_them_back_after():
    """Inside held_heap a freed 200 MB array (above glibc's largest mmap threshold, so mmap'd
    otherwise) stays resident, the next one of that size reuses its pages (the resident set does
    not grow by it); after the block the defaults are back:
    the pages are returned, and a freed large array leaves the resident set at once."""
    n = 25_000_000  # 200 MB of float64
    with held_heap() as held:
        assert held
        start = _rss_mb()
        block = np.ones(n)
        del block
        kept = _rss_mb()
        assert kept - start > 150, (start, kept)
        again = np.ones(n)
        assert _rss_mb() - kept < 50
        del again
    after = _rss_mb()
    assert kept - after > 150, (kept, after)
    block = np.ones(n)
    before_free = _rss_mb()
    del block
    assert before_free - _rss_mb() > 150


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_the_solver_stores_what_the_memory_module_says(precision):
    from physmorph.settings.mpm import MPMConfig
    from physmorph.mpm.solver import MPMSolver
    from physmorph.settings.solver_memory import bytes_per_particle_substep

    cfg = MPMConfig(grid_res=16, precision=precision, device="cpu")
    assert MPMSolver(cfg, 8).bytes_per_particle_substep() == bytes_per_particle_substep(cfg)


def test_the_morph_estimate_asks_the_solvers_storage(monkeypatch):
    """physmorph.settings.memory_model.morph_memory takes its bytes per particle-substep from
    physmorph.settings.solver_memory: what that says more, the estimate holds more, for every
    particle and substep."""
    from physmorph.settings import memory_model
    from physmorph.settings import workflow as config
    from physmorph.settings.solver_memory import bytes_per_particle_substep

    s = config.load_settings("config/config.yaml")
    n, extra = 10_000, 1000
    args = (s.shape("iso"), s.sampling, s.target, s.mpm, s.domain, "")
    before = memory_model.morph_memory(*args, n_particles=n).mb
    monkeypatch.setattr(memory_model, "bytes_per_particle_substep", lambda cfg: bytes_per_particle_substep(cfg) + extra)
    after = memory_model.morph_memory(*args, n_particles=n).mb
    assert after - before == pytest.approx(n * s.mpm.substeps * extra / 2**20)


def test_the_morph_estimate_holds_each_threads_lanes():
    """Each CPU thread's lanes hold a copy of the grid (physmorph.mpm.lanes): the estimate grows by
    that copy per thread, in the solver's precision, and not on a GPU (no lanes there); the lanes
    the solver allocates are the floats the memory module counts."""
    import dataclasses

    from physmorph.mpm.solver import MPMSolver
    from physmorph.settings import memory_model
    from physmorph.settings import workflow as config
    from physmorph.settings.mpm import MPMConfig
    from physmorph.settings.solver_memory import LANE_FLOATS_PER_NODE

    s = config.load_settings("config/config.yaml")
    args = (s.shape("iso"), s.sampling, s.target, s.mpm, s.domain, "")
    one, eight = (memory_model.morph_memory(*args, n_particles=10_000, threads=t).mb for t in (1, 8))
    assert eight - one == pytest.approx(7 * s.sampling.grid_res ** 3 * LANE_FLOATS_PER_NODE * 4 / 2**20)
    gpu = (dataclasses.replace(s.mpm, device="cuda"), s.domain, "")
    assert memory_model.morph_memory(*args[:3], *gpu, n_particles=10_000, threads=8).mb < one
    solver = MPMSolver(MPMConfig(grid_res=16, device="cpu"), 8)
    lanes = solver.model.lanes
    fields = (solver.trajectory.grid_mvm_lanes, solver.adjoint.grid_v_adj_lanes)
    assert sum(f.n for f in fields) == LANE_FLOATS_PER_NODE and {f.shape for f in fields} == {(lanes.count, 16, 16, 16)}
