"""The scatter lanes (physmorph.mpm.lanes): each CPU thread adds into its own copy of the grid
with plain adds. A lane written by two threads at once would lose adds; these tests would see it."""

import numpy as np
import pytest
import taichi as ti

from physmorph.base.taichi_runtime import ensure_taichi
from physmorph.mpm.lanes import LANE_BLOCK, ScatterLanes, cpu_threads

RES = 8


@ti.data_oriented
class CellCounter:
    """Adds each particle's value into its cell (and the next cell along x), through ScatterLanes,
    as P2G does: the particle loop split into lanes, the lanes collected in a grid pass."""

    def __init__(self, n: int, on_cpu: bool):
        self.lanes = ScatterLanes(n, on_cpu)
        self.cell = ti.Vector.field(3, ti.i32, shape=n)
        self.value = ti.field(ti.f64, shape=n)
        self.grid = ti.field(ti.f64, shape=(RES, RES, RES))
        self.grid_lanes = self.lanes.grid_field(ti.f64, RES)

    @ti.kernel
    def scatter(self):
        for I in ti.grouped(self.grid):
            self.grid[I] = 0.0
        if ti.static(self.lanes.private):
            ti.loop_config(block_dim=LANE_BLOCK)
            for c in range(self.lanes.blocks):
                for p in range(self.lanes.first(c), self.lanes.first(c + 1)):
                    self._add(p, c // LANE_BLOCK)
        else:
            for p in range(self.lanes.n):
                self._add(p, 0)
        for I in ti.grouped(self.grid):
            self.grid[I] = self.lanes.collect(self.grid_lanes, self.grid, I)

    @ti.func
    def _add(self, p, lane):
        I = self.cell[p]
        for k in range(2):
            self.lanes.add(self.grid_lanes, self.grid, lane, ti.Vector([(I[0] + k) % RES, I[1], I[2]]), self.value[p])


def scattered(n: int, on_cpu: bool, seed: int = 0):
    """(the counter's grid, NumPy's): integer values, so every order of adds gives the same sum
    exactly and a lost add shows."""
    rng = np.random.default_rng(seed)
    # most particles in a few cells: the adds of different particles meet there all the time
    cells = np.where(rng.random((n, 1)) < 0.8, rng.integers(0, 2, (n, 3)), rng.integers(0, RES, (n, 3)))
    values = rng.integers(1, 1000, n).astype(np.float64)
    counter = CellCounter(n, on_cpu)
    counter.cell.from_numpy(cells.astype(np.int32))
    counter.value.from_numpy(values)
    expected = np.zeros((RES, RES, RES))
    for k in range(2):
        np.add.at(expected, ((cells[:, 0] + k) % RES, cells[:, 1], cells[:, 2]), values)
    counter.scatter()
    return counter, expected


def test_the_chunks_cover_every_particle_once_in_order():
    ensure_taichi()
    n = 100_003
    lanes = ScatterLanes(n, on_cpu=True)
    assert lanes.count == cpu_threads() and lanes.blocks == LANE_BLOCK * lanes.count
    firsts = [(c * n) // lanes.blocks for c in range(lanes.blocks + 1)]
    assert firsts[0] == 0 and firsts[-1] == n and all(a <= b for a, b in zip(firsts, firsts[1:]))


@pytest.mark.parametrize("on_cpu", [True, False], ids=["lanes", "atomic"])
def test_the_lanes_add_what_numpy_adds_exactly(on_cpu):
    ensure_taichi()
    counter, expected = scattered(300_000, on_cpu)
    if on_cpu:
        assert counter.lanes.count == cpu_threads()
    np.testing.assert_array_equal(counter.grid.to_numpy(), expected)
    if on_cpu:  # the lanes are left zero for the next particle loop
        assert not counter.grid_lanes.to_numpy().any()
        counter.scatter()  # and a second pass adds the same again, not twice
        np.testing.assert_array_equal(counter.grid.to_numpy(), expected)


def test_the_solver_with_atomic_adds_computes_what_its_lanes_compute(monkeypatch, state):
    """The GPU's path (one lane, atomic adds), built on the CPU, against the lanes' solver: the
    same forward, and the same gradients from a backward and from a paired backward. Slow (~11 s):
    the atomic solver is a second build of every kernel (the lanes' solver is the module's shared one)."""
    from mpm_cases import cfg64, make, random_control
    from physmorph.mpm import model as model_module

    cfg = cfg64()
    lanes_solver = make(cfg, state, reuse=True)
    monkeypatch.setattr(model_module, "ScatterLanes", lambda n, on_cpu: ScatterLanes(n, on_cpu=False))
    atomic_solver = make(cfg, state)
    assert lanes_solver.model.lanes.private and not atomic_solver.model.lanes.private
    control = random_control(cfg, state.n)
    gx = np.random.default_rng(5).normal(size=(state.n, 3))
    results = []
    for s in (lanes_solver, atomic_solver):
        s.set_control(control)
        loss = s.forward()
        end = s.state_at(cfg.substeps)
        s.backward(None, gx)
        grad = s.control_gradient().copy()
        x0_bar = s.initial_state_gradients()["x"]
        n_mass, n_inj = s.backward_pair(None, gx)
        results.append((loss, end.x, end.F, grad, x0_bar, n_mass, n_inj, s.control_gradient().copy()))
    for a, b in zip(*results):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)
