"""The reverse sweep's state: the adjoints of the particle state at the substep being reversed and
of the grid, a second set of each for two seeds in one sweep (MPMSolver.backward_pair, allocated
on first use: 96 B a particle in float32), and the per-thread lanes the reverse of G2P adds
into (physmorph.mpm.lanes). The reverse of P2G computes A, Fe and its polar factors where it
needs them, from the forward's records (no SVD, nothing stored).
"""

import taichi as ti

from physmorph.base import taichi_runtime  # noqa: F401  (Taichi's fast class test, before the kernels below)
from .model import MPMModel


@ti.data_oriented
class Adjoint:
    """x_bar, v_bar, C_bar, F_bar of one substep's particle state and the grid's adjoints."""

    def __init__(self, model: MPMModel):
        self.model = model
        f, N, R = model.dtype, model.n, model.cfg.grid_res
        vec, mat = ti.types.vector(3, f), ti.types.matrix(3, 3, f)
        self.x_adj = vec.field(shape=N)
        self.v_adj = vec.field(shape=N)
        self.C_adj = mat.field(shape=N)
        self.F_adj = mat.field(shape=N)
        self.grid_v_adj = vec.field(shape=(R, R, R))
        # the reverse of G2P adds into a copy of grid_v_adj per CPU thread (physmorph.mpm.lanes)
        self.grid_v_adj_lanes = model.lanes.grid_field(f, R, 3)
        self.grid_mv_adj = vec.field(shape=(R, R, R))
        self.grid_m_adj = ti.field(f, shape=(R, R, R))
        self.x_adj2 = self.v_adj2 = self.C_adj2 = self.F_adj2 = None
        self.grid_v_adj2 = self.grid_mv_adj2 = self.grid_m_adj2 = self.grid_v_adj2_lanes = None

    def ensure_pair(self) -> None:
        """Allocate the second adjoint set (backward_pair) on first use."""
        if self.x_adj2 is None:
            f, N, R = self.model.dtype, self.model.n, self.model.cfg.grid_res
            vec, mat = ti.types.vector(3, f), ti.types.matrix(3, 3, f)
            self.x_adj2, self.v_adj2 = vec.field(shape=N), vec.field(shape=N)
            self.C_adj2, self.F_adj2 = mat.field(shape=N), mat.field(shape=N)
            self.grid_v_adj2, self.grid_mv_adj2 = vec.field(shape=(R, R, R)), vec.field(shape=(R, R, R))
            self.grid_m_adj2 = ti.field(f, shape=(R, R, R))
            self.grid_v_adj2_lanes = self.model.lanes.grid_field(f, R, 3)

    def seed(self, gx, gF, pair: bool) -> None:  # gx: [N, 3], gF: [N, 3, 3] in the solver's precision
        """The end state's adjoints: x_bar_T = gx, F_bar_T = gF, v_bar and C_bar zero (with pair,
        the second set all zero)."""
        self.x_adj.from_numpy(gx)
        self.F_adj.from_numpy(gF)
        self.v_adj.fill(0.0)
        self.C_adj.fill(0.0)
        if pair:
            for f in (self.x_adj2, self.v_adj2, self.C_adj2, self.F_adj2):
                f.fill(0.0)
