"""The solver's state (warp.sim's split): what the substeps write. Per substep t = 0..T the
particle state s_t = (x, v, C, F); for the adjoint the forward's rotation of Fe (a unit
quaternion) with its smallest pair sum and the P2G grid of every substep; and the grid the
substep being run works on (momentum, mass, velocity).
"""

import numpy as np
import taichi as ti

from physmorph.base import taichi_runtime  # noqa: F401  (Taichi's fast class test, before the kernels below)
from physmorph.settings.mpm import MPMDivergenceError

from .model import MPMModel
from .state import ParticleState

# |F| or |v| entries above this are treated as a divergence (Inf follows soon after).
BLOWUP = 1e8


@ti.data_oriented
class Trajectory:
    """The stored rollout of one frame, index [t, p] (t = 0..T), and the working grid."""

    def __init__(self, model: MPMModel):
        self.model = model
        self.n, self.dtype, self.np_dtype = model.n, model.dtype, model.np_dtype
        f, T, N, R = model.dtype, model.cfg.substeps, model.n, model.cfg.grid_res
        vec, mat = ti.types.vector(3, f), ti.types.matrix(3, 3, f)
        self.x = vec.field(shape=(T + 1, N))
        self.v = vec.field(shape=(T + 1, N))
        self.C = mat.field(shape=(T + 1, N))
        self.F = mat.field(shape=(T + 1, N))
        self.grid_mv = vec.field(shape=(R, R, R))
        self.grid_m = ti.field(f, shape=(R, R, R))
        self.grid_v = vec.field(shape=(R, R, R))
        # P2G adds into a copy of (grid_mv, grid_m) per CPU thread, packed as one 4-vector a node,
        # summed by Transfers.grid_update
        self.lanes = model.lanes
        self.grid_mvm_lanes = self.lanes.grid_field(f, R, 4)
        # the forward's rotation of Fe and smallest pair sum per substep, and its P2G grid: the
        # backward restores them instead of running P2G (and its SVD) again, which was 55 % of a
        # backward (kernel profiler, 471K particles). The rotation is kept as a unit quaternion
        # (20 B per particle per substep in float32 with the pair sum, against 40 B as a matrix:
        # 0.19 GB less at 471K particles x 20 substeps); the forward's warm start reads the exact
        # rotation one substep earlier (R_prev), so only the backward sees the quaternion's rounding
        self.R_q = ti.types.vector(4, f).field(shape=(T, N))
        self.R_prev = mat.field(shape=N)
        self.gap_t = ti.field(f, shape=(T, N))
        self.grid_m_t = ti.field(f, shape=(T, R, R, R))
        self.grid_mv_t = vec.field(shape=(T, R, R, R))

    def load(self, st: ParticleState) -> None:
        """s_0 = (x, v, F, C) of a validated state, in the solver's precision."""
        d = self.np_dtype
        self._load_initial(st.x.astype(d), st.v.astype(d), st.F.astype(d), st.C.astype(d))

    @ti.kernel
    def _load_initial(self, x: ti.types.ndarray(), v: ti.types.ndarray(), F: ti.types.ndarray(),
                      C: ti.types.ndarray()):
        for p in range(self.n):
            for a in ti.static(range(3)):
                self.x[0, p][a] = x[p, a]
                self.v[0, p][a] = v[p, a]
                for b in ti.static(range(3)):
                    self.F[0, p][a, b] = F[p, a, b]
                    self.C[0, p][a, b] = C[p, a, b]

    @ti.kernel
    def _export(self, t: ti.i32, x: ti.types.ndarray(), v: ti.types.ndarray(), F: ti.types.ndarray(),
                C: ti.types.ndarray()):
        for p in range(self.n):
            for a in ti.static(range(3)):
                x[p, a] = self.x[t, p][a]
                v[p, a] = self.v[t, p][a]
                for b in ti.static(range(3)):
                    F[p, a, b] = self.F[t, p][a, b]
                    C[p, a, b] = self.C[t, p][a, b]

    def export_raw(self, t: int):
        """The stored (x, v, F, C) of substep t in the solver's precision."""
        n, d = self.n, self.np_dtype
        x, v = np.empty((n, 3), d), np.empty((n, 3), d)
        F, C = np.empty((n, 3, 3), d), np.empty((n, 3, 3), d)
        self._export(t, x, v, F, C)
        return x, v, F, C

    def state_at(self, t: int) -> ParticleState:
        """The stored particle state at substep t (0..T), float64, with the model's constants."""
        T = self.model.cfg.substeps
        if not 0 <= t <= T:
            raise IndexError(f"substep t must be in [0, {T}], got {t}")
        x, v, F, C = self.export_raw(t)
        return ParticleState(x=x.astype(np.float64), v=v.astype(np.float64), F=F.astype(np.float64),
                             C=C.astype(np.float64), Fp=self.model.Fp.copy(),
                             mass=self.model.mass.to_numpy().astype(np.float64),
                             volume=self.model.vol.to_numpy().astype(np.float64))

    def check_finite(self) -> None:
        """Cheap check of the final state; on failure find the first bad substep and particle and
        raise MPMDivergenceError naming them."""
        T = self.model.cfg.substeps

        def bad_rows(t):
            x, v, F, _ = self.export_raw(t)
            for name, a in (("x", x), ("v", v), ("F", F)):
                # max and min pass NaN on, which fails both tests; the row is found only when one fails
                if a.max(initial=-np.inf) <= BLOWUP and a.min(initial=np.inf) >= -BLOWUP:
                    continue
                bad = ~(np.abs(a.reshape(self.n, -1)) <= BLOWUP).all(axis=1)
                return name, int(np.argmax(bad))
            return None

        if bad_rows(T) is None:
            return
        for t in range(1, T + 1):
            hit = bad_rows(t)
            if hit is not None:
                name, p = hit
                raise MPMDivergenceError(
                    f"{name} became non-finite (NaN/Inf or |{name}| > {BLOWUP:g}) at substep "
                    f"{t - 1} (particle {p})", quantity=name, substep=t - 1, particle=p)
