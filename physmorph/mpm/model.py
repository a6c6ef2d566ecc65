"""The solver's static model (warp.sim's split: the model does not change within a run): the
config and its compile-time constants, the grid, the particles' constants within a frame (Fp^-1,
mass, rest volume, the step's weight), the target's grid mass, the stress model, and the
geometry every step shares: the quadratic B-spline stencil (per particle and per node), the
boundary condition, the rotation's quaternion and the isochoric smoothing's volume factor
(equations in physmorph/mpm/solver.py's docstring).
"""

import numpy as np
import taichi as ti

from physmorph.base.grid import BOUNDARY_CELLS, Grid
from physmorph.base.linalg3 import inverse3
from physmorph.base.taichi_runtime import init_taichi
from physmorph.settings.mpm import MPMConfig, MPMStateError
from physmorph.settings.solver_memory import PACKED_STRESS_MIN_PARTICLES

from .lanes import ScatterLanes
from .state import ParticleState
from .stress import make_stress_funcs


def checked_array(g, shape: tuple, name: str) -> np.ndarray:
    """``g`` as float64 of ``shape``, finite; else MPMStateError naming it."""
    g = np.asarray(g, dtype=np.float64)
    if g.shape != shape:
        raise MPMStateError(f"{name} must have shape {shape}, got {g.shape}")
    if not np.isfinite(g).all():
        raise MPMStateError(f"{name} is not finite (NaN/Inf)")
    return g


@ti.data_oriented
class MPMModel:
    """What one run's steps read and never write: built once per (config, particle count)."""

    def __init__(self, cfg: MPMConfig, n_particles: int):
        if int(n_particles) < 1:
            raise MPMStateError(f"n_particles must be >= 1, got {n_particles}")
        self.arch = init_taichi(cfg.device, cfg.threads)  # 'cpu' or 'cuda'
        self.cfg = cfg
        self.n = int(n_particles)
        self.grid = Grid(cfg.grid_res, cfg.domain_lo, cfg.domain_hi)
        self.dtype = ti.f64 if cfg.precision == "float64" else ti.f32
        self.np_dtype = np.float64 if cfg.precision == "float64" else np.float32
        self.stress = make_stress_funcs(self.dtype, cfg.mu, cfg.lam)
        # compile-time constants of the kernels
        self.dx = cfg.dx
        self.inv_dx = 1.0 / cfg.dx
        self.lo = cfg.domain_lo
        self.res = cfg.grid_res
        self.bound = BOUNDARY_CELLS
        # positions are clamped so the 3x3x3 stencil never leaves the grid: x_g in [1, res - 2]
        self.x_min = cfg.domain_lo + 1.0 * cfg.dx
        self.x_max = cfg.domain_lo + (cfg.grid_res - 2.0) * cfg.dx
        # the particle loops that add into the grid, split over the CPU threads (physmorph.mpm.lanes)
        self.lanes = ScatterLanes(self.n, on_cpu=self.arch == "cpu")
        # the CPU at scale (from PACKED_STRESS_MIN_PARTICLES on): P2G's stress on packs and the node
        # loops unrolled over the stencil (physmorph.mpm.transfers' docstring), compile-time constants
        self.at_scale = self.lanes.private and self.n >= PACKED_STRESS_MIN_PARTICLES
        f, N, R = self.dtype, self.n, cfg.grid_res
        self.Fp_inv = ti.types.matrix(3, 3, f).field(shape=N)
        self.mass = ti.field(f, shape=N)
        self.vol = ti.field(f, shape=N)
        self.step_weight = ti.field(f, shape=N)  # w_p of the normalised step (step_per_volume), else 1
        self.target_m = ti.field(f, shape=(R, R, R))
        self.Fp = None  # the loaded Fp, float64 (state_at hands it back)
        self.weighted_step = False

    def load_constants(self, st: ParticleState) -> None:
        """The frame's particle constants (Fp^-1, m, V0, the step's weights) from a validated state."""
        if st.n != self.n:
            raise MPMStateError(f"state has {st.n} particles, solver was built for {self.n}")
        if st.x.min() < self.x_min or st.x.max() > self.x_max:  # the particle is found only when one is outside
            p = int(np.argmax(((st.x < self.x_min) | (st.x > self.x_max)).any(axis=1)))
            raise MPMStateError(
                f"x of particle {p} = {st.x[p].tolist()} is outside the usable domain "
                f"[{self.x_min}, {self.x_max}] (the B-spline stencil would leave the grid)")
        dt_ = self.np_dtype
        self.Fp_inv.from_numpy(inverse3(st.Fp).astype(dt_, copy=False))
        self.mass.from_numpy(st.mass.astype(dt_, copy=False))
        self.vol.from_numpy(st.volume.astype(dt_, copy=False))
        weight = st.volume.max() / st.volume if self.cfg.step_per_volume else np.ones(self.n)
        self.step_weight.from_numpy(weight.astype(dt_))
        self.weighted_step = bool(self.cfg.step_per_volume and (weight != 1.0).any())
        self.Fp = st.Fp.copy()

    @ti.func
    def stencil(self, xp):
        """Quadratic B-spline: base node, fractional offset fx, weights w[axis][k], dw/dx."""
        xg = (xp - self.dtype(self.lo)) * self.dtype(self.inv_dx)
        base = ti.floor(xg - 0.5, ti.i32)
        fx = xg - ti.cast(base, self.dtype)
        # rows: stencil offset 0..2, columns: axis (dynamic loops over the 27 nodes keep the
        # kernels small to compile)
        w = ti.Matrix.rows([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2])
        dw = ti.Matrix.rows([(fx - 1.5) * self.dtype(self.inv_dx), -2.0 * (fx - 1.0) * self.dtype(self.inv_dx),
                             (fx - 0.5) * self.dtype(self.inv_dx)])
        return base, fx, w, dw

    @ti.func
    def node_grad(self, w: ti.template(), dw: ti.template(), i, j, k):
        """grad_x w_Ip of node (i, j, k) (only the reverse kernels need it). w and dw are taken by
        reference (ti.template()): passed by value they were copied for every node."""
        return ti.Vector([dw[i, 0] * w[j, 1] * w[k, 2], w[i, 0] * dw[j, 1] * w[k, 2], w[i, 0] * w[j, 1] * dw[k, 2]])

    @ti.func
    def boundary(self, I, v):
        """Zero the outward velocity component on the BOUNDARY_CELLS layer of every face."""
        out = v
        for a in ti.static(range(3)):
            if I[a] < self.bound and v[a] < 0:
                out[a] = 0.0
            if I[a] >= self.res - self.bound and v[a] > 0:
                out[a] = 0.0
        return out

    @ti.func
    def quaternion_of(self, R):
        """The unit quaternion (w, x, y, z) of the rotation R (Shepperd's branches: the largest of
        4w^2, 4x^2, 4y^2, 4z^2 is taken from the diagonal, so no division by a small number)."""
        tr = R[0, 0] + R[1, 1] + R[2, 2]
        q = ti.Vector.zero(self.dtype, 4)
        if tr > 0.0:
            r = 2.0 * ti.sqrt(1.0 + tr)
            q = ti.Vector([0.25 * r, (R[2, 1] - R[1, 2]) / r, (R[0, 2] - R[2, 0]) / r, (R[1, 0] - R[0, 1]) / r])
        elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
            r = 2.0 * ti.sqrt(ti.max(1.0 + R[0, 0] - R[1, 1] - R[2, 2], 0.0))
            q = ti.Vector([(R[2, 1] - R[1, 2]) / r, 0.25 * r, (R[0, 1] + R[1, 0]) / r, (R[0, 2] + R[2, 0]) / r])
        elif R[1, 1] > R[2, 2]:
            r = 2.0 * ti.sqrt(ti.max(1.0 + R[1, 1] - R[0, 0] - R[2, 2], 0.0))
            q = ti.Vector([(R[0, 2] - R[2, 0]) / r, (R[0, 1] + R[1, 0]) / r, 0.25 * r, (R[1, 2] + R[2, 1]) / r])
        else:
            r = 2.0 * ti.sqrt(ti.max(1.0 + R[2, 2] - R[0, 0] - R[1, 1], 0.0))
            q = ti.Vector([(R[1, 0] - R[0, 1]) / r, (R[0, 2] + R[2, 0]) / r, (R[1, 2] + R[2, 1]) / r, 0.25 * r])
        return q

    @ti.func
    def rotation_of(self, q):
        """The rotation of the quaternion q (w, x, y, z), normalised first."""
        u = q / q.norm()
        w, x, y, z = u[0], u[1], u[2], u[3]
        return ti.Matrix([[1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)],
                          [2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w)],
                          [2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)]], self.dtype)

    @ti.func
    def volume_target(self, Fn):
        """det F' under isochoric smoothing: max(det F_new, J_min), J_min = min_volume_ratio."""
        J = Fn.determinant()
        if ti.static(self.cfg.min_volume_ratio > 0):
            J = ti.max(J, self.dtype(self.cfg.min_volume_ratio))
        return J

    @ti.func
    def volume_scale(self, Fn, Fs):
        """r = (max(det F_new, J_min) / det F_s)^(1/3) (smoothing_mode "isochoric"); 1 where the
        ratio is not positive (an inverted F, which the blend cannot rescale)."""
        q = self.volume_target(Fn) / Fs.determinant()
        r = ti.cast(1.0, self.dtype)
        if q > 0:
            r = ti.pow(q, self.dtype(1.0 / 3.0))
        return r
