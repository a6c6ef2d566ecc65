"""The solver's Taichi fields: what MPMSolver stores, allocated once per (config, particle count),
the groups only some settings use allocated on their first use.

Per substep t = 0..T the particle state (x, v, C, F), and for the adjoint the forward's rotation
of Fe (a unit quaternion) with its smallest pair sum and the P2G grid; per particle the constants
(Fp^-1, m, V0) and the control dFc per slot with its gradient; the grid's momentum, mass,
velocity and their adjoints; the target's grid mass and the loss's levels.
"""

import numpy as np
import taichi as ti

from physmorph.base.grid import blur_weights


class SolverFields:
    """Allocation of MPMSolver's fields (a mixin: the kernels are Transfers', PhysicsLoss', ...)."""

    def _allocate_fields(self) -> None:
        cfg, f = self.cfg, self.dtype
        T, N, R, Tc = cfg.substeps, self.n, cfg.grid_res, cfg.n_control_slots
        vec, mat = ti.types.vector(3, f), ti.types.matrix(3, 3, f)
        # stored per-substep particle state, index [t, p], t = 0..T
        self.x = vec.field(shape=(T + 1, N))
        self.v = vec.field(shape=(T + 1, N))
        self.C = mat.field(shape=(T + 1, N))
        self.F = mat.field(shape=(T + 1, N))
        self.Fp_inv = mat.field(shape=N)
        self.mass = ti.field(f, shape=N)
        self.vol = ti.field(f, shape=N)
        self.step_weight = ti.field(f, shape=N)  # w_p of the normalised step (step_per_volume), else 1
        # control field and its gradient, index [slot, p]
        self.ctrl = mat.field(shape=(Tc, N))
        self.ctrl_grad = mat.field(shape=(Tc, N))
        # the line search's starting control: the trial steps are taken from it in place, so a
        # trial costs no NumPy copy of the [Tc, N, 3, 3] control (0.34 GB each at 471K x 20 slots).
        # Before the line search it holds the injection calibration's mass gradient
        # (calibration_gradients), which the first iteration's gradient is combined from.
        self.ctrl_base = mat.field(shape=(Tc, N))
        # Adam's moments are allocated at Adam's first use (_ensure_adam): the default optimiser
        # (normalised GD) has none, which at 471K particles x 20 slots saves 0.7 GB and their checkpoint
        self.adam_m = None
        self.adam_v = None
        # adjoints of the particle state at the substep being reversed
        self.x_adj = vec.field(shape=N)
        self.v_adj = vec.field(shape=N)
        self.C_adj = mat.field(shape=N)
        self.F_adj = mat.field(shape=N)
        # a second set of particle and grid adjoints for backward_pair (two seeds in one reverse
        # sweep), allocated on its first use (_ensure_pair): 96 B a particle in float32
        self.x_adj2 = self.v_adj2 = self.C_adj2 = self.F_adj2 = None
        self.grid_v_adj2 = self.grid_mv_adj2 = self.grid_m_adj2 = None
        self.step_volume_share = ti.field(ti.f64, shape=())  # MPMConfig.step_volume_share, set per step
        self._allocate_grid_fields(vec, R)
        # position anchors of the loss (set_position_anchors: the morph loop's stray pull),
        # allocated on first use: a_p and the weight w_p of w_p |x_T,p - a_p|^2
        self.anchor = self.anchor_w = None
        self.loss_acc = ti.field(ti.f64, shape=())
        self.norm_acc = ti.field(ti.f64, shape=())
        self._allocate_substep_scratch(vec, mat, T, N, R)

    def _allocate_grid_fields(self, vec, R: int) -> None:
        """The grid, its adjoints, the target, and the mass loss's blurred level."""
        f, cfg = self.dtype, self.cfg
        self.grid_mv = vec.field(shape=(R, R, R))
        self.grid_m = ti.field(f, shape=(R, R, R))
        self.grid_v = vec.field(shape=(R, R, R))
        self.grid_v_adj = vec.field(shape=(R, R, R))
        self.grid_mv_adj = vec.field(shape=(R, R, R))
        self.grid_m_adj = ti.field(f, shape=(R, R, R))
        self.target_m = ti.field(f, shape=(R, R, R))
        # the blurred level of the mass loss (mass_loss_blur > 0): the blurred grid mass, the blurred
        # target, the level's adjoint and two scratch grids for the separable passes
        self._blur_radius = int(np.ceil(3.0 * cfg.mass_loss_blur)) if cfg.mass_loss_blur > 0 else 0
        self.blur_grids = [ti.field(f, shape=(R, R, R)) for _ in range(5)] if cfg.mass_loss_blur > 0 else []
        if cfg.mass_loss_blur > 0:
            self.blur_w = ti.field(f, shape=2 * self._blur_radius + 1)
            self.blur_w.from_numpy(blur_weights(cfg.mass_loss_blur).astype(self.np_dtype))

    def _allocate_substep_scratch(self, vec, mat, T: int, N: int, R: int) -> None:
        """What the adjoint of a substep reads: the per-particle scratch and the forward's records."""
        f = self.dtype
        # per-particle scratch of the substep being reversed: affine A, Fe and its SVD, so
        # the backward computes each SVD once (O(N) memory, not stored per substep)
        self.A_s = mat.field(shape=N)
        self.Fe_s = mat.field(shape=N)
        self.R_s = mat.field(shape=N)
        self.S_s = mat.field(shape=N)
        self.gap_s = ti.field(f, shape=N)
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

    def _ensure_adam(self) -> None:
        """Allocate Adam's moments (zero) on first use."""
        if self.adam_m is None:
            mat = ti.types.matrix(3, 3, self.dtype)
            shape = (self.cfg.n_control_slots, self.n)
            self.adam_m = mat.field(shape=shape)
            self.adam_v = mat.field(shape=shape)
            self.adam_m.fill(0.0)
            self.adam_v.fill(0.0)

    def _ensure_anchors(self) -> None:
        """Allocate the stray pull's anchors and weights on first use."""
        if self.anchor is None:
            self.anchor = ti.types.vector(3, self.dtype).field(shape=self.n)
            self.anchor_w = ti.field(self.dtype, shape=self.n)

    def _ensure_pair(self) -> None:
        """Allocate the second adjoint set (backward_pair) on first use."""
        if self.x_adj2 is None:
            f, N, R = self.dtype, self.n, self.cfg.grid_res
            vec, mat = ti.types.vector(3, f), ti.types.matrix(3, 3, f)
            self.x_adj2, self.v_adj2 = vec.field(shape=N), vec.field(shape=N)
            self.C_adj2, self.F_adj2 = mat.field(shape=N), mat.field(shape=N)
            self.grid_v_adj2, self.grid_mv_adj2 = vec.field(shape=(R, R, R)), vec.field(shape=(R, R, R))
            self.grid_m_adj2 = ti.field(f, shape=(R, R, R))
