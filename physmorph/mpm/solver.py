"""Differentiable MLS-MPM solver with hand-written reverse kernels (paper section 4, "Physics
rollout").

One substep t (state s_t = (x, v, C, F), control dFc_t, constants Fp, m, V0):

    Fe = (F + dFc_t) Fp^-1,   tau = P(Fe) Fe^T   (Kirchhoff stress, fixed corotated)
    A  = -dt V0 (4/dx^2) tau + m C                                    (MLS-MPM affine)
    P2G:  mv_I = sum_p w_Ip [m (1 - dt d) v + A (x_I - x_p)],  m_I = sum_p w_Ip m
    grid: v_I = mv_I / m_I, outward component zeroed on the BOUNDARY_CELLS layer of each face
    G2P:  v' = sum_I w_Ip v_I,  C' = 4/dx^2 sum_I w_Ip v_I (x_I - x_p)^T,  x' = x + dt v'
          F_new = (I + dt C') F,   F' = (1 - s) F_new + s F
    (with smoothing_mode "isochoric", not in the paper: F' <- (det F_new / det F')^(1/3) F', the
    volume ratio follows the motion and only the shape is smoothed)
    (with control_in_F: F_new = (I + dt C') (F + dFc_t), the authors' code)
    (with volume_stiffness K > 0, not in the paper: A += dt V0 (4/dx^2) p I, a packing pressure
    p = K ln(rho / (c rho0)) where the P2G density at the frame's start, rho = sum_I w_Ip m_I / dx^3,
    exceeds c rho0; held over the frame's substeps)

P = 2 mu (Fe - R) + lam (J - 1) cof(Fe), with cof(Fe) = J Fe^-T written with cross products
so it stays finite for singular Fe. The control dFc enters the stress only (it acts like an
actuation); F itself is advected by the grid velocity. The end-layer mass loss compares the
grid mass of x_T (same quadratic B-spline as physmorph.grid.splat_mass) with the target.

Backward: the adjoint of each substep is written by hand (reverse of G2P, grid update, P2G);
the per-substep particle state (x, v, C, F), the rotation of Fe with its smallest pair sum, and
the P2G grid are stored in the forward; the backward restores A and Fe from them (no second SVD). The stress model and its
hand-written differential, the rotation derivative included, are in physmorph.mpm.stress.
"""


import numpy as np
import taichi as ti

from ..grid import BOUNDARY_CELLS, Grid, blur_weights
from ..taichi_runtime import init_taichi
from .config import STEP_VOLUME_MODES, MPMConfig, MPMConfigError, MPMDivergenceError, MPMStateError
from .state import ParticleState
from .stress import evaluate_stress, make_stress_funcs  # noqa: F401 (evaluate_stress re-exported)

# |F| or |v| entries above this are treated as a divergence (Inf follows soon after).
_BLOWUP = 1e8
# the injection calibration's backward_pair from this many particle-substeps on (n x substeps;
# below, its kernels' compilation costs more than it saves in a run: docs/performance.md)
PAIR_MIN_PARTICLE_STEPS = 1_000_000


@ti.data_oriented
class MPMSolver:
    """Differentiable MPM over one frame of T substeps, with the control field dFc and its optimisers (normalised GD, Adam).

    Built once per (config, particle count); ``load_state`` each frame. See the module docstring
    for the equations and physmorph/mpm/__init__.py for the design decisions.
    """

    def __init__(self, cfg: MPMConfig, n_particles: int):
        if int(n_particles) < 1:
            raise MPMStateError(f"n_particles must be >= 1, got {n_particles}")
        init_taichi(cfg.device, cfg.threads)
        self.cfg = cfg
        self.n = int(n_particles)
        self.grid = Grid(cfg.grid_res, cfg.domain_lo, cfg.domain_hi)
        self.dtype = ti.f64 if cfg.precision == "float64" else ti.f32
        self.np_dtype = np.float64 if cfg.precision == "float64" else np.float32
        T, N, R, f = cfg.substeps, self.n, cfg.grid_res, self.dtype
        Tc = cfg.n_control_slots
        vec, mat = ti.types.vector(3, f), ti.types.matrix(3, 3, f)
        # stored per-substep particle state, index [t, p], t = 0..T
        self.x = vec.field(shape=(T + 1, N))
        self.v = vec.field(shape=(T + 1, N))
        self.C = mat.field(shape=(T + 1, N))
        self.F = mat.field(shape=(T + 1, N))
        self.Fp_inv = mat.field(shape=N)
        self.mass = ti.field(f, shape=N)
        self.vol = ti.field(f, shape=N)
        self.press = ti.field(f, shape=N)  # the frame's packing pressure (volume_stiffness)
        self.step_weight = ti.field(f, shape=N)  # w_p of the normalised step (step_per_volume), else 1
        # control field and Adam moments, index [slot, p]
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
        # the body-volume projection's coefficient per control slot (step_volume = "body")
        self.step_volume_acc = ti.Vector.field(2, ti.f64, shape=cfg.n_control_slots)
        self.step_volume_coef = ti.field(ti.f64, shape=cfg.n_control_slots)
        self.step_volume_share = ti.field(ti.f64, shape=())  # MPMConfig.step_volume_share, set per step
        # the step smoothing's grid and direction (step_smoothing = "grid"), allocated on first use
        self.step_grid = self.step_grid_w = self.step_dir = None
        # grid
        self.grid_mv = vec.field(shape=(R, R, R))
        self.grid_m = ti.field(f, shape=(R, R, R))
        self.grid_v = vec.field(shape=(R, R, R))
        self.grid_v_adj = vec.field(shape=(R, R, R))
        self.grid_mv_adj = vec.field(shape=(R, R, R))
        self.grid_m_adj = ti.field(f, shape=(R, R, R))
        self.target_m = ti.field(f, shape=(R, R, R))
        # the coarser levels of the mass-loss pyramid (mass_loss_levels > 1): block sums of the grid
        # mass, of the target and their loss adjoints, level l = 1 .. levels - 1
        self.pyramid = [tuple(ti.field(f, shape=(R >> lv,) * 3) for _ in range(3))
                        for lv in range(1, cfg.mass_loss_levels)]
        # the blurred level of the mass loss (mass_loss_blur > 0): the blurred grid mass, the blurred
        # target, the level's adjoint and two scratch grids for the separable passes
        self._blur_radius = int(np.ceil(3.0 * cfg.mass_loss_blur)) if cfg.mass_loss_blur > 0 else 0
        self.blur_grids = [ti.field(f, shape=(R, R, R)) for _ in range(5)] if cfg.mass_loss_blur > 0 else []
        if cfg.mass_loss_blur > 0:
            self.blur_w = ti.field(f, shape=2 * self._blur_radius + 1)
            self.blur_w.from_numpy(blur_weights(cfg.mass_loss_blur).astype(self.np_dtype))
        # position anchors of the loss (set_position_anchors: the morph loop's stray pull),
        # allocated on first use: a_p and the weight w_p of w_p |x_T,p - a_p|^2
        self.anchor = self.anchor_w = None
        self.loss_acc = ti.field(ti.f64, shape=())
        self.norm_acc = ti.field(ti.f64, shape=())
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
        self._stress_model = make_stress_funcs(f, cfg.mu, cfg.lam, cfg.volume_law)
        # compile-time constants of the kernels
        self._dx = cfg.dx
        self._inv_dx = 1.0 / cfg.dx
        self._lo = cfg.domain_lo
        self._res = R
        self._bound = BOUNDARY_CELLS
        # positions are clamped so the 3x3x3 stencil never leaves the grid: x_g in [1, res - 2]
        self._x_min = cfg.domain_lo + 1.0 * cfg.dx
        self._x_max = cfg.domain_lo + (R - 2.0) * cfg.dx
        self._clip_on = cfg.control_clip > 0
        self._pressure_on = cfg.volume_stiffness > 0
        self.reset()

    def reset(self) -> None:
        """Back to a freshly built solver: no state or target loaded, dFc and the Adam moments
        zero. Every other field is written before it is read (load_state, set_target_grid_mass,
        forward, backward), so a reset solver computes what a new one would."""
        self._has_target = False
        self._loaded = False
        self._forward_done = False
        self._forward_current = False  # the stored trajectory is that of the current dFc/state
        self._rollout_id = 0  # counts forwards: the calibration's gradients belong to one
        self._calibrated_for = -1
        self._combined_for = -1
        self._grad_norm = float("nan")
        self._Fp = None
        self._last_loss: float | None = None
        self._last_mass_loss: float | None = None  # the last forward's loss without the anchors' term
        self._adam_step = 0
        self._kept = None  # keep_control's fields, allocated on first use
        self._kept_adam_step = (0, False)
        self._log_eps = 0.0
        self._overfill_weight = float(self.cfg.overfill_weight)
        self._anchored = False
        self.reset_control()

    def configure(self, cfg: MPMConfig) -> None:
        """Take cfg's driver settings (DRIVER_FIELDS: learning rate, optimiser, line search, ...)
        without compiling again; every other field must equal the built solver's."""
        if cfg.kernel_settings() != self.cfg.kernel_settings():
            changed = [k for (k, a), (_, b) in zip(cfg.kernel_settings(), self.cfg.kernel_settings()) if a != b]
            raise MPMConfigError(f"configure can only change driver settings; {', '.join(changed)} "
                                 "would need a new solver (its kernels bake them in)")
        self.cfg = cfg

    # ------------------------------------------------------------------ kernels
    # Each forward kernel is followed by its reverse. The 27-node quadratic B-spline stencil is
    # _stencil (per particle) and _node (per node); every transfer loops over ti.ndrange(3, 3, 3).
    @ti.func
    def _stencil(self, xp):
        """Quadratic B-spline: base node, fractional offset fx, weights w[axis][k], dw/dx."""
        xg = (xp - self.dtype(self._lo)) * self.dtype(self._inv_dx)
        base = ti.floor(xg - 0.5, ti.i32)
        fx = xg - ti.cast(base, self.dtype)
        # rows: stencil offset 0..2, columns: axis (dynamic loops over the 27 nodes keep the
        # kernels small to compile)
        w = ti.Matrix.rows([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2])
        dw = ti.Matrix.rows([(fx - 1.5) * self.dtype(self._inv_dx), -2.0 * (fx - 1.0) * self.dtype(self._inv_dx),
                             (fx - 0.5) * self.dtype(self._inv_dx)])
        return base, fx, w, dw

    @ti.func
    def _node(self, fx: ti.template(), w: ti.template(), i, j, k):
        """Node (i, j, k) of the stencil: offset from base, x_I - x_p and weight w_Ip.
        fx and w are taken by reference (ti.template()): passed by value they were copied for
        every node, which made P2G's backward ~50 % and G2P ~25 % slower (kernel profiler)."""
        off = ti.Vector([i, j, k])
        dpos = (ti.cast(off, self.dtype) - fx) * self.dtype(self._dx)
        return off, dpos, w[i, 0] * w[j, 1] * w[k, 2]

    @ti.func
    def _node_grad(self, w: ti.template(), dw: ti.template(), i, j, k):
        """grad_x w_Ip of node (i, j, k) (only the reverse kernels need it)."""
        return ti.Vector([dw[i, 0] * w[j, 1] * w[k, 2], w[i, 0] * dw[j, 1] * w[k, 2], w[i, 0] * w[j, 1] * dw[k, 2]])

    @ti.kernel
    def _clear_grid(self):
        for I in ti.grouped(self.grid_m):
            self.grid_mv[I] = ti.Vector.zero(self.dtype, 3)
            self.grid_m[I] = 0.0

    @ti.kernel
    def _clear_grid_adj(self, pair: ti.template()):
        for I in ti.grouped(self.grid_m):
            self.grid_v_adj[I] = ti.Vector.zero(self.dtype, 3)
            if ti.static(pair):
                self.grid_v_adj2[I] = ti.Vector.zero(self.dtype, 3)

    @ti.kernel
    def _p2g(self, t: ti.i32):
        """Fe = (F + dFc_t) Fp^-1, A = -dt V0 (4/dx^2) P(Fe) Fe^T + m C;
        mv_I += w_Ip (m (1 - dt d) v_p + A_p (x_I - x_p)),  m_I += w_Ip m_p.
        The rotation of Fe and its pair sum are kept per substep (R_q, gap_t), so the backward
        (_restore_p2g) needs no second SVD."""
        slot = t if ti.static(self.cfg.control == "per_substep") else 0
        kq = 4.0 * self.dtype(self._inv_dx) * self.dtype(self._inv_dx)
        for p in range(self.n):
            xp = self.x[t, p]
            base, fx, w, dw = self._stencil(xp)
            Fe = (self.F[t, p] + self.ctrl[slot, p]) @ self.Fp_inv[p]
            # warm start: the rotation one substep earlier. At the first substep the zero start
            # (no rotation) makes polar_from take the SVD, so a forward depends only on the loaded
            # state and the control; one call site, since each inlined SVD costs seconds of compile
            R0 = ti.Matrix.zero(self.dtype, 3, 3)
            if t > 0:
                R0 = self.R_prev[p]
            R, S, gap = self._stress_model.polar_from(Fe, R0)
            self.R_prev[p] = R
            self.R_q[t, p] = self._quaternion_of(R)
            self.gap_t[t, p] = gap
            P = self._stress_model.stress_from_polar(Fe, R)
            A = (-self.dtype(self.cfg.dt) * self.vol[p] * kq) * (P @ Fe.transpose()) + self.mass[p] * self.C[t, p]
            if ti.static(self._pressure_on):  # Kirchhoff stress -p I; constant in the frame, so the
                # backward's x adjoint (through A, restored by _restore_p2g) is all it needs
                A += (self.dtype(self.cfg.dt) * self.vol[p] * kq * self.press[p]) * ti.Matrix.identity(self.dtype, 3)
            mom = self.mass[p] * (1.0 - self.dtype(self.cfg.dt) * self.dtype(self.cfg.drag)) * self.v[t, p]
            for i, j, k in ti.ndrange(3, 3, 3):
                off, dpos, wt = self._node(fx, w, i, j, k)
                self.grid_mv[base + off] += wt * (mom + A @ dpos)
                self.grid_m[base + off] += wt * self.mass[p]

    @ti.func
    def _quaternion_of(self, R):
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
    def _rotation_of(self, q):
        """The rotation of the quaternion q (w, x, y, z), normalised first."""
        u = q / q.norm()
        w, x, y, z = u[0], u[1], u[2], u[3]
        return ti.Matrix([[1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)],
                          [2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w)],
                          [2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)]], self.dtype)

    @ti.kernel
    def _store_grid(self, t: ti.i32):
        """Keep substep t's P2G grid (m_I, mv_I) for the backward."""
        for I in ti.grouped(self.grid_m):
            self.grid_m_t[t, I] = self.grid_m[I]
            self.grid_mv_t[t, I] = self.grid_mv[I]

    @ti.kernel
    def _restore_p2g(self, t: ti.i32):
        """The backward's scratch (A, Fe, its polar factors) and substep t's grid, from the forward's stored polar factors and grid:
        Fe = (F + dFc_t) Fp^-1, R and gap as stored, S = sym(R^T Fe), A as in _p2g."""
        slot = t if ti.static(self.cfg.control == "per_substep") else 0
        kq = 4.0 * self.dtype(self._inv_dx) * self.dtype(self._inv_dx)
        for I in ti.grouped(self.grid_m):
            self.grid_m[I] = self.grid_m_t[t, I]
            self.grid_mv[I] = self.grid_mv_t[t, I]
        for p in range(self.n):
            Fe = (self.F[t, p] + self.ctrl[slot, p]) @ self.Fp_inv[p]
            R = self._rotation_of(self.R_q[t, p])
            S0 = R.transpose() @ Fe
            P = self._stress_model.stress_from_polar(Fe, R)
            A = (-self.dtype(self.cfg.dt) * self.vol[p] * kq) * (P @ Fe.transpose()) + self.mass[p] * self.C[t, p]
            if ti.static(self._pressure_on):
                A += (self.dtype(self.cfg.dt) * self.vol[p] * kq * self.press[p]) * ti.Matrix.identity(self.dtype, 3)
            self.A_s[p] = A
            self.Fe_s[p] = Fe
            self.R_s[p] = R
            self.S_s[p] = 0.5 * (S0 + S0.transpose())
            self.gap_s[p] = self.gap_t[t, p]

    @ti.kernel
    def _p2g_backward(self, t: ti.i32, pair: ti.template()):
        """Reverse of _p2g: grid adjoints -> adjoints of (x, v, C, F) of state t and of dFc_t (pair:
        also the second set's, sharing the stencil, A and the node loop)."""
        slot = t if ti.static(self.cfg.control == "per_substep") else 0
        damp = 1.0 - self.dtype(self.cfg.dt) * self.dtype(self.cfg.drag)
        for p in range(self.n):
            xp = self.x[t, p]
            base, fx, w, dw = self._stencil(xp)
            A = self.A_s[p]
            mp = self.mass[p]
            mom = mp * damp * self.v[t, p]
            vbar = ti.Vector.zero(self.dtype, 3)
            Abar = ti.Matrix.zero(self.dtype, 3, 3)
            xbar = ti.Vector.zero(self.dtype, 3)
            vbar2, Abar2, xbar2 = vbar, Abar, xbar
            for i, j, k in ti.ndrange(3, 3, 3):
                off, dpos, wt = self._node(fx, w, i, j, k)
                gw = self._node_grad(w, dw, i, j, k)
                mv = mom + A @ dpos
                mvb = self.grid_mv_adj[base + off]
                vbar += wt * mvb
                Abar += wt * mvb.outer_product(dpos)
                xbar += gw * (mvb.dot(mv) + self.grid_m_adj[base + off] * mp) - wt * (A.transpose() @ mvb)
                if ti.static(pair):
                    mvb2 = self.grid_mv_adj2[base + off]
                    vbar2 += wt * mvb2
                    Abar2 += wt * mvb2.outer_product(dpos)
                    xbar2 += gw * (mvb2.dot(mv) + self.grid_m_adj2[base + off] * mp) - wt * (A.transpose() @ mvb2)
            # one call site of the stress's differential for both sets (each inlined copy costs
            # seconds of compilation): a loop over the sets
            for which in range(2 if ti.static(pair) else 1):
                vb, Ab, xb = vbar, Abar, xbar
                if ti.static(pair):
                    if which == 1:
                        vb, Ab, xb = vbar2, Abar2, xbar2
                Fhat_bar = self._p2g_F_adjoint(p, Ab)
                if which == 0:
                    self._add_particle_adjoints(p, slot, xb, mp * damp * vb, mp * Ab, Fhat_bar, self.x_adj,
                                                self.v_adj, self.C_adj, self.F_adj, self.ctrl_grad)
                if ti.static(pair):
                    if which == 1:
                        self._add_particle_adjoints(p, slot, xb, mp * damp * vb, mp * Ab, Fhat_bar, self.x_adj2,
                                                    self.v_adj2, self.C_adj2, self.F_adj2, self.ctrl_base)

    @ti.func
    def _p2g_F_adjoint(self, p, Abar):
        """The particle part of _p2g's reverse for one adjoint set: A_bar -> P_bar = tau_bar Fe ->
        Fe_bar (the stress's self-adjoint differential) -> the adjoint of F + dFc."""
        kq = 4.0 * self.dtype(self._inv_dx) * self.dtype(self._inv_dx)
        Fe = self.Fe_s[p]
        tau_bar = (-self.dtype(self.cfg.dt) * self.vol[p] * kq) * Abar
        P, dP = self._stress_model.stress_and_diff_polar(Fe, self.R_s[p], self.S_s[p], self.gap_s[p],
                                                         tau_bar @ Fe)  # P_bar = tau_bar Fe
        Fe_bar = tau_bar.transpose() @ P + dP
        return Fe_bar @ self.Fp_inv[p].transpose()

    @ti.func
    def _add_particle_adjoints(self, p, slot, xbar, vbar, Cbar, Fbar, xa: ti.template(), va: ti.template(),
                               Ca: ti.template(), Fa: ti.template(), grad: ti.template()):
        xa[p] += xbar
        va[p] += vbar
        Ca[p] += Cbar
        Fa[p] += Fbar
        grad[slot, p] += Fbar

    def _frame_pressure(self) -> None:
        """Packing pressure of the frame (MPMConfig.volume_stiffness): m_I = sum_p w_Ip m_p at x_0,
        rho_p = sum_I w_Ip m_I / dx^3, p_p = K ln(rho_p / (c rho0)) where rho_p > c rho0, else 0."""
        self._clear_grid()
        self._splat_mass(0)
        self._pressure_from_grid_mass()

    @ti.kernel
    def _pressure_from_grid_mass(self):
        inv_cell = self.dtype(self._inv_dx) ** 3
        rho_on = self.dtype(self.cfg.volume_onset * self.cfg.density)
        for p in range(self.n):
            base, fx, w, dw = self._stencil(self.x[0, p])
            rho = ti.cast(0.0, self.dtype)
            for i, j, k in ti.ndrange(3, 3, 3):
                off, dpos, wt = self._node(fx, w, i, j, k)
                rho += wt * self.grid_m[base + off]
            rho *= inv_cell
            pr = ti.cast(0.0, self.dtype)
            if rho > rho_on:
                pr = self.dtype(self.cfg.volume_stiffness) * ti.log(rho / rho_on)
            self.press[p] = pr

    @ti.func
    def _boundary(self, I, v):
        """Zero the outward velocity component on the BOUNDARY_CELLS layer of every face."""
        out = v
        for a in ti.static(range(3)):
            if I[a] < self._bound and v[a] < 0:
                out[a] = 0.0
            if I[a] >= self._res - self._bound and v[a] > 0:
                out[a] = 0.0
        return out

    @ti.kernel
    def _grid_update(self):
        """v_I = mv_I / m_I (0 on empty nodes), then the boundary condition."""
        for I in ti.grouped(self.grid_m):
            m = self.grid_m[I]
            v = ti.Vector.zero(self.dtype, 3)
            if m > 0:
                v = self._boundary(I, self.grid_mv[I] / m)
            self.grid_v[I] = v

    @ti.kernel
    def _grid_backward(self, pair: ti.template()):
        """Reverse of _grid_update: v_bar -> (mv_bar, m_bar) through the mask and v = mv / m."""
        for I in ti.grouped(self.grid_m):
            m = self.grid_m[I]
            vfree = ti.Vector.zero(self.dtype, 3)
            vc = vfree
            if m > 0:
                vfree = self.grid_mv[I] / m
                vc = self._boundary(I, vfree)
            self._grid_adjoint_node(I, m, vfree, vc, self.grid_v_adj, self.grid_mv_adj, self.grid_m_adj)
            if ti.static(pair):
                self._grid_adjoint_node(I, m, vfree, vc, self.grid_v_adj2, self.grid_mv_adj2, self.grid_m_adj2)

    @ti.func
    def _grid_adjoint_node(self, I, m, vfree, vc, va: ti.template(), mva: ti.template(), ma: ti.template()):
        """One adjoint set at node I: the boundary's zeroed components pass nothing back."""
        mvb = ti.Vector.zero(self.dtype, 3)
        mb = ti.cast(0.0, self.dtype)
        if m > 0:
            vb = va[I]
            for a in ti.static(range(3)):
                if vc[a] == 0.0 and vfree[a] != 0.0:
                    vb[a] = 0.0
            mvb = vb / m
            mb = -vb.dot(vfree) / m
        mva[I] = mvb
        ma[I] = mb

    @ti.kernel
    def _g2p(self, t: ti.i32):
        """v' = sum w v_I, C' = 4/dx^2 sum w v_I dpos^T, x' = x + dt v', F' = (1-s)(I + dt C')F + sF."""
        for p in range(self.n):
            xp = self.x[t, p]
            base, fx, w, dw = self._stencil(xp)
            nv = ti.Vector.zero(self.dtype, 3)
            nC = ti.Matrix.zero(self.dtype, 3, 3)
            for i, j, k in ti.ndrange(3, 3, 3):
                off, dpos, wt = self._node(fx, w, i, j, k)
                gv = self.grid_v[base + off]
                nv += wt * gv
                nC += (4.0 * self.dtype(self._inv_dx) * self.dtype(self._inv_dx) * wt) * gv.outer_product(dpos)
            Fo = self.F[t, p]
            Fh = Fo
            if ti.static(self.cfg.control_in_F):
                Fh = Fo + self.ctrl[t if ti.static(self.cfg.control == "per_substep") else 0, p]
            Fn = (ti.Matrix.identity(self.dtype, 3) + self.dtype(self.cfg.dt) * nC) @ Fh
            self.v[t + 1, p] = nv
            self.C[t + 1, p] = nC
            self.x[t + 1, p] = ti.math.clamp(xp + self.dtype(self.cfg.dt) * nv, self.dtype(self._x_min), self.dtype(self._x_max))
            Fs = (1.0 - self.dtype(self.cfg.smoothing)) * Fn + self.dtype(self.cfg.smoothing) * Fo
            if ti.static(self.cfg.smoothing_mode == "isochoric"):
                Fs *= self._volume_scale(Fn, Fs)
            self.F[t + 1, p] = Fs

    @ti.func
    def _volume_target(self, Fn):
        """det F' under isochoric smoothing: max(det F_new, J_min), J_min = min_volume_ratio."""
        J = Fn.determinant()
        if ti.static(self.cfg.min_volume_ratio > 0):
            J = ti.max(J, self.dtype(self.cfg.min_volume_ratio))
        return J

    @ti.func
    def _volume_scale(self, Fn, Fs):
        """r = (max(det F_new, J_min) / det F_s)^(1/3) (smoothing_mode "isochoric"); 1 where the
        ratio is not positive (an inverted F, which the blend cannot rescale)."""
        q = self._volume_target(Fn) / Fs.determinant()
        r = ti.cast(1.0, self.dtype)
        if q > 0:
            r = ti.pow(q, self.dtype(1.0 / 3.0))
        return r

    @ti.kernel
    def _g2p_backward(self, t: ti.i32, pair: ti.template()):
        """Reverse of _g2p: adjoints of state t+1 -> grid_v_adj and the (x, F) adjoints of state t
        (pair: also the second set's, sharing the stencil and the node loop's grid loads)."""
        kq = 4.0 * self.dtype(self._inv_dx) * self.dtype(self._inv_dx)
        for p in range(self.n):
            xp = self.x[t, p]
            base, fx, w, dw = self._stencil(xp)
            slot = t if ti.static(self.cfg.control == "per_substep") else 0
            xbar, vbar, Cbar = ti.Vector.zero(self.dtype, 3), ti.Vector.zero(self.dtype, 3), ti.Matrix.zero(self.dtype, 3, 3)
            xbar2, vbar2, Cbar2 = xbar, vbar, Cbar  # set in the loop below
            # one call site of the particle part for both sets (a loop over the sets)
            for which in range(2 if ti.static(pair) else 1):
                xa, va, Ca, Fa = self.x_adj[p], self.v_adj[p], self.C_adj[p], self.F_adj[p]
                if ti.static(pair):
                    if which == 1:
                        xa, va, Ca, Fa = self.x_adj2[p], self.v_adj2[p], self.C_adj2[p], self.F_adj2[p]
                xb, vb, Cb, Fb, Fh_bar = self._g2p_particle_adjoint(t, p, xa, va, Ca, Fa)
                if which == 0:
                    xbar, vbar, Cbar = xb, vb, Cb
                    self._set_F_adjoint(p, slot, Fb, Fh_bar, self.v_adj, self.C_adj, self.F_adj, self.ctrl_grad)
                if ti.static(pair):
                    if which == 1:
                        xbar2, vbar2, Cbar2 = xb, vb, Cb
                        self._set_F_adjoint(p, slot, Fb, Fh_bar, self.v_adj2, self.C_adj2, self.F_adj2, self.ctrl_base)
            for i, j, k in ti.ndrange(3, 3, 3):
                off, dpos, wt = self._node(fx, w, i, j, k)
                gw = self._node_grad(w, dw, i, j, k)
                gv = self.grid_v[base + off]
                Cd = Cbar @ dpos
                self.grid_v_adj[base + off] += wt * (vbar + kq * Cd)
                xbar += gw * (vbar.dot(gv) + kq * gv.dot(Cd)) - (wt * kq) * (Cbar.transpose() @ gv)
                if ti.static(pair):
                    Cd2 = Cbar2 @ dpos
                    self.grid_v_adj2[base + off] += wt * (vbar2 + kq * Cd2)
                    xbar2 += gw * (vbar2.dot(gv) + kq * gv.dot(Cd2)) - (wt * kq) * (Cbar2.transpose() @ gv)
            self.x_adj[p] = xbar
            if ti.static(pair):
                self.x_adj2[p] = xbar2

    @ti.func
    def _g2p_particle_adjoint(self, t, p, xbar_n, vbar_n, Cbar_n, Fbar_n):
        """The particle part of _g2p's reverse for one adjoint set: the adjoints of x, v, C, F of
        state t+1 -> F's of state t, the adjoint of F + dFc (dFc's share where control_in_F) and
        the (x_bar, v_bar, C_bar) that the node loop scatters."""
        s = self.dtype(self.cfg.smoothing)
        dt = self.dtype(self.cfg.dt)
        xn = self.x[t + 1, p]
        for a in ti.static(range(3)):  # the clamp passes no gradient where it is active
            if xn[a] <= self.dtype(self._x_min) or xn[a] >= self.dtype(self._x_max):
                xbar_n[a] = 0.0
        slot = t if ti.static(self.cfg.control == "per_substep") else 0
        Fh = self.F[t, p]
        if ti.static(self.cfg.control_in_F):
            Fh += self.ctrl[slot, p]
        Cn = self.C[t + 1, p]
        Fbar_new = (1.0 - s) * Fbar_n
        Fbar = s * Fbar_n
        if ti.static(self.cfg.smoothing_mode == "isochoric"):
            # F' = r Fs, r = (det Fn / det Fs)^(1/3): Fs_bar = r F'_bar - (r r_bar / 3) Fs^-T,
            # Fn_bar += (r r_bar / 3) Fn^-T with r_bar = <F'_bar, Fs> (0 where the floor
            # J_min holds det F' instead of det Fn)
            Fn = (ti.Matrix.identity(self.dtype, 3) + dt * Cn) @ Fh
            Fs = (1.0 - s) * Fn + s * self.F[t, p]
            r = self._volume_scale(Fn, Fs)
            Fs_bar = r * Fbar_n
            Fbar_new = ti.Matrix.zero(self.dtype, 3, 3)
            Jt = self._volume_target(Fn)
            if (Jt / Fs.determinant()) > 0:
                k3 = r * (Fbar_n * Fs).sum() / 3.0
                Fs_bar -= k3 * Fs.inverse().transpose()
                if Jt == Fn.determinant():  # det F' follows det Fn (not held at the floor)
                    Fbar_new = k3 * Fn.inverse().transpose()
            Fbar_new += (1.0 - s) * Fs_bar
            Fbar = s * Fs_bar
        Fh_bar = (ti.Matrix.identity(self.dtype, 3) + dt * Cn).transpose() @ Fbar_new
        Fbar += Fh_bar
        Cbar = Cbar_n + dt * Fbar_new @ Fh.transpose()
        vbar = vbar_n + dt * xbar_n
        return xbar_n, vbar, Cbar, Fbar, Fh_bar

    @ti.func
    def _set_F_adjoint(self, p, slot, Fbar, Fh_bar, va: ti.template(), Ca: ti.template(), Fa: ti.template(),
                       grad: ti.template()):
        """One set's adjoints of state t after _g2p's particle part: F's written, v's and C's
        consumed (zeroed), dFc's share added where the control enters F."""
        Fa[p] = Fbar
        va[p] = ti.Vector.zero(self.dtype, 3)
        Ca[p] = ti.Matrix.zero(self.dtype, 3, 3)
        if ti.static(self.cfg.control_in_F):
            grad[slot, p] += Fh_bar

    @ti.kernel
    def _splat_mass(self, t: ti.i32):
        """m_I += sum_p w_Ip m_p of x_t (the physmorph.grid.splat_mass transfer)."""
        for p in range(self.n):
            base, fx, w, dw = self._stencil(self.x[t, p])
            for i, j, k in ti.ndrange(3, 3, 3):
                off, dpos, wt = self._node(fx, w, i, j, k)
                self.grid_m[base + off] += wt * self.mass[p]

    @ti.kernel
    def _mass_loss(self, log_eps: ti.f64, overfill_w: ti.f64):
        """Loss and dL/dm_I into grid_m_adj. squared: (m - m*)^2; log: (log(m+e) - log(m*+e))^2;
        sqrt: (sqrt(m+e) - sqrt(m*+e))^2; log_bounded: log below m*, 4 (sqrt(m+e) - sqrt(m*+e))^2 / (m*+e)
        above it; plus the packing term _overfill_term with weight overfill_w where the
        configuration has one (overfill_weight > 0)."""
        self.loss_acc[None] = 0.0
        for I in ti.grouped(self.grid_m):
            r2, adj = self._node_loss(self.grid_m[I], self.target_m[I], log_eps)
            if ti.static(self.cfg.overfill_weight > 0):
                o2, oadj = self._overfill_term(self.grid_m[I], self.target_m[I], log_eps, overfill_w)
                r2 += o2
                adj += oadj
            self.loss_acc[None] += r2
            self.grid_m_adj[I] = adj

    @ti.func
    def _overfill_term(self, m, mt, log_eps: ti.f64, overfill_w: ti.f64):
        """The packing term of MPMConfig.overfill_weight: w max(0, r)^2 with r = log(m + e) -
        log(c + e), c = max(overfill_ratio density dx^3, m*), and its derivative 2 w max(0, r) / (m + e);
        with mass_loss = "log_convex", r^2 continued linearly in m above r = 1 (_log_convex_term)."""
        e = ti.cast(log_eps, self.dtype)
        w = ti.cast(overfill_w, self.dtype)
        cap = ti.max(self.dtype(self.cfg.overfill_ratio * self.cfg.density * self.cfg.dx ** 3), mt)
        r2 = ti.cast(0.0, ti.f64)
        adj = ti.cast(0.0, self.dtype)
        if ti.static(self.cfg.mass_loss == "log_convex"):
            if m > cap:
                r2, adj = self._log_convex_term(m, cap, e)
        else:
            r = ti.max(ti.log(m + e) - ti.log(cap + e), 0.0)
            r2, adj = ti.cast(r * r, ti.f64), 2.0 * r / (m + e)
        return ti.cast(w, ti.f64) * r2, w * adj

    @ti.func
    def _node_loss(self, m, mt, log_eps: ti.f64):
        """One node's loss term and its derivative dL/dm: squared (m - m*)^2, 2 (m - m*); log
        (log(m + e) - log(m* + e))^2, 2 r / (m + e); sqrt (sqrt(m + e) - sqrt(m* + e))^2,
        r / sqrt(m + e); log_bounded: log for m <= m*, else k r^2 and k r / sqrt(m + e) with
        r = sqrt(m + e) - sqrt(m* + e) and k = 4 / (m* + e); log_convex: _log_convex_term."""
        r2 = ti.cast(0.0, ti.f64)
        adj = ti.cast(0.0, self.dtype)
        e = ti.cast(log_eps, self.dtype)
        if ti.static(self.cfg.mass_loss == "squared"):
            r = m - mt
            r2 = ti.cast(r * r, ti.f64)
            adj = 2.0 * r
        elif ti.static(self.cfg.mass_loss == "log_bounded"):
            if m <= mt:
                r2, adj = self._log_term(m, mt, e)
            else:
                k = 4.0 / (mt + e)
                r2, adj = self._sqrt_term(m, mt, e)
                r2, adj = ti.cast(k, ti.f64) * r2, k * adj
        elif ti.static(self.cfg.mass_loss == "sqrt"):
            r2, adj = self._sqrt_term(m, mt, e)
        elif ti.static(self.cfg.mass_loss == "log_convex"):
            r2, adj = self._log_convex_term(m, mt, e)
        else:
            r2, adj = self._log_term(m, mt, e)
        return r2, adj

    @ti.func
    def _log_term(self, m, mt, e):
        """(log(m + e) - log(m* + e))^2 and its derivative 2 r / (m + e)."""
        r = ti.log(m + e) - ti.log(mt + e)
        return ti.cast(r * r, ti.f64), 2.0 * r / (m + e)

    @ti.func
    def _log_convex_term(self, m, mt, e):
        """The log term r^2, r = log(m + e) - log(m* + e), up to r = 1, where it turns concave in m,
        and its tangent above: 1 + s (m - m1), m1 = (m* + e) exp(1) - e, s = 2 / (m1 + e); its
        derivative 2 r / (m + e), then s. Convex in m, so packing mass into fewer nodes never lowers it."""
        r = ti.log(m + e) - ti.log(mt + e)
        r2 = ti.cast(r * r, ti.f64)
        adj = 2.0 * r / (m + e)
        if r > 1.0:
            m1 = (mt + e) * self.dtype(np.e) - e
            s = 2.0 / (m1 + e)
            r2 = ti.cast(1.0 + s * (m - m1), ti.f64)
            adj = s
        return r2, adj

    @ti.func
    def _sqrt_term(self, m, mt, e):
        """(sqrt(m + e) - sqrt(m* + e))^2 and its derivative r / sqrt(m + e)."""
        root = ti.sqrt(m + e)
        r = root - ti.sqrt(mt + e)
        return ti.cast(r * r, ti.f64), r / root

    @ti.kernel
    def _pyramid_loss(self, cm: ti.template(), ct: ti.template(), ca: ti.template(), block: ti.i32,
                      log_eps: ti.f64):
        """One coarse level of the mass loss (MPMConfig.mass_loss_levels): M_J = sum of m_I over
        the block^3 nodes I of block J; the node loss of _node_loss on M and M* added to
        loss_acc, and its adjoint dL/dM_J added to dL/dm_I of every node of the block."""
        for J in ti.grouped(cm):
            cm[J] = 0.0
        for I in ti.grouped(self.grid_m):
            cm[I // block] += self.grid_m[I]
        for J in ti.grouped(cm):
            r2, adj = self._node_loss(cm[J], ct[J], log_eps)
            self.loss_acc[None] += r2
            ca[J] = adj
        for I in ti.grouped(self.grid_m):
            self.grid_m_adj[I] += ca[I // block]

    @ti.kernel
    def _blur_axis(self, src: ti.template(), dst: ti.template(), axis: ti.template()):
        """One separable pass of MPMConfig.mass_loss_blur: dst_I = sum_k w_k src_(I + k e_axis) over
        |k| <= r, nodes outside the grid counting as zero (so the pass is a symmetric matrix)."""
        R = self.cfg.grid_res
        r = ti.static(self._blur_radius)
        for I in ti.grouped(dst):
            acc = ti.cast(0.0, self.dtype)
            for k in ti.static(range(-r, r + 1)):
                J = I + ti.Vector([k if axis == 0 else 0, k if axis == 1 else 0, k if axis == 2 else 0])
                if 0 <= J[axis] < R:
                    acc += self.blur_w[k + r] * src[J]
            dst[I] = acc

    def _blur(self, src, dst) -> None:
        """dst = B src, B the 3D Gaussian blur (three passes through the scratch grids)."""
        t1, t2 = self.blur_grids[3], self.blur_grids[4]
        self._blur_axis(src, t1, 0)
        self._blur_axis(t1, t2, 1)
        self._blur_axis(t2, dst, 2)

    @ti.kernel
    def _blur_level_loss(self, bm: ti.template(), bt: ti.template(), ba: ti.template(), log_eps: ti.f64,
                         weight: ti.f64):
        """The blurred level (MPMConfig.mass_loss_blur): weight x _node_loss of B m against B m* added
        to loss_acc, its adjoint into ba."""
        for I in ti.grouped(bm):
            r2, adj = self._node_loss(bm[I], bt[I], log_eps)
            self.loss_acc[None] += weight * r2
            ba[I] = ti.cast(weight, self.dtype) * adj

    @ti.kernel
    def _add_to_mass_adjoint(self, a: ti.template()):
        """dL/dm_I += a_I (a coarser or blurred level's adjoint brought back to the grid)."""
        for I in ti.grouped(a):
            self.grid_m_adj[I] += a[I]

    def _loss_with_adjoint(self) -> None:
        """Mass loss of the splatted grid_m into loss_acc, dL/dm_I into grid_m_adj (all levels)."""
        self._mass_loss(self._log_eps, self._overfill_weight)
        for lv, (cm, ct, ca) in enumerate(self.pyramid, start=1):
            self._pyramid_loss(cm, ct, ca, 1 << lv, self._log_eps * 8.0 ** lv)
        if self.blur_grids:
            bm, bt, ba = self.blur_grids[:3]
            self._blur(self.grid_m, bm)
            self._blur_level_loss(bm, bt, ba, self._log_eps, self.cfg.mass_loss_blur_weight)
            self._blur(ba, bm)  # B is symmetric: dL/dm = B dL/d(B m)
            self._add_to_mass_adjoint(bm)

    @ti.kernel
    def _anchor_loss(self):
        """The anchors' term of the loss (set_position_anchors): loss_acc += sum_p w_p |x_T,p - a_p|^2."""
        T = self.cfg.substeps
        for p in range(self.n):
            d = self.x[T, p] - self.anchor[p]
            self.loss_acc[None] += ti.cast(self.anchor_w[p] * d.dot(d), ti.f64)

    @ti.kernel
    def _anchor_backward(self, xa: ti.template()):
        """Reverse of _anchor_loss: x_bar_T,p += 2 w_p (x_T,p - a_p)."""
        T = self.cfg.substeps
        for p in range(self.n):
            xa[p] += 2.0 * self.anchor_w[p] * (self.x[T, p] - self.anchor[p])

    @ti.kernel
    def _loss_backward(self, xa: ti.template()):
        """Reverse of _splat_mass(T) and _mass_loss: x_bar_T += sum_I grad(w_Ip) m_p dL/dm_I (on top
        of the injected g^x already there)."""
        T = self.cfg.substeps
        for p in range(self.n):
            base, fx, w, dw = self._stencil(self.x[T, p])
            g = ti.Vector.zero(self.dtype, 3)
            for i, j, k in ti.ndrange(3, 3, 3):
                off, dpos, wt = self._node(fx, w, i, j, k)
                gw = self._node_grad(w, dw, i, j, k)
                g += gw * (self.mass[p] * self.grid_m_adj[base + off])
            xa[p] += g

    # ------------------------------------------------------------------ kernels: utilities
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

    @ti.kernel
    def _zero_control_field(self, g: ti.template()):
        for s, p in g:
            g[s, p] = ti.Matrix.zero(self.dtype, 3, 3)

    @ti.kernel
    def _norm_sq(self, g: ti.template()):
        self.norm_acc[None] = 0.0
        for s, p in g:
            self.norm_acc[None] += ti.cast((g[s, p] * g[s, p]).sum(), ti.f64)

    def _grad_norm_sq(self) -> None:
        self._norm_sq(self.ctrl_grad)

    @ti.kernel
    def _scale_ctrl(self, factor: ti.f64):
        for s, p in self.ctrl:
            self.ctrl[s, p] = ti.cast(factor, self.dtype) * self.ctrl[s, p]

    @ti.kernel
    def _save_ctrl_base(self):
        for s, p in self.ctrl:
            self.ctrl_base[s, p] = self.ctrl[s, p]

    @ti.kernel
    def _restore_ctrl_base(self):
        for s, p in self.ctrl:
            self.ctrl[s, p] = self.ctrl_base[s, p]

    @ti.kernel
    def _copy_slots(self, dst: ti.template(), src: ti.template()):
        for s, p in src:
            dst[s, p] = src[s, p]

    def keep_control(self) -> None:
        """Copy the control (and the Adam moments where Adam has run) into fields of their own, for
        :meth:`restore_kept_control`: the settle phase's undo without a host copy (340 MB at 471K
        particles)."""
        if self._kept is None:
            mat = ti.types.matrix(3, 3, self.dtype)
            self._kept = {"ctrl": mat.field(shape=(self.cfg.n_control_slots, self.n))}
        self._copy_slots(self._kept["ctrl"], self.ctrl)
        if self.adam_m is not None:
            for name, src in (("adam_m", self.adam_m), ("adam_v", self.adam_v)):
                if name not in self._kept:
                    self._kept[name] = ti.types.matrix(3, 3, self.dtype).field(shape=src.shape)
                self._copy_slots(self._kept[name], src)
        self._kept_adam_step = (int(self._adam_step), self.adam_m is not None)

    def restore_kept_control(self) -> None:
        """Put back what :meth:`keep_control` copied (moments Adam made since then: zero)."""
        if self._kept is None:
            raise MPMStateError("restore_kept_control before keep_control")
        self._copy_slots(self.ctrl, self._kept["ctrl"])
        step, had_moments = self._kept_adam_step
        if self.adam_m is not None:
            if had_moments:
                self._copy_slots(self.adam_m, self._kept["adam_m"])
                self._copy_slots(self.adam_v, self._kept["adam_v"])
            else:
                self.adam_m.fill(0.0)
                self.adam_v.fill(0.0)
        self._adam_step = step
        self._forward_current = False

    @ti.kernel
    def _copy_grad_to_base(self):
        for s, p in self.ctrl_grad:
            self.ctrl_base[s, p] = self.ctrl_grad[s, p]

    @ti.kernel
    def _combine_gradients(self, scale: ti.f64):
        """g = g_mass + scale g_inj: ctrl_base holds g_mass, ctrl_grad g_inj (calibration_gradients)."""
        for s, p in self.ctrl_grad:
            self.ctrl_grad[s, p] = self.ctrl_base[s, p] + ti.cast(scale, self.dtype) * self.ctrl_grad[s, p]

    @ti.kernel
    def _control_mean(self, out: ti.types.ndarray()):
        """out_p = (1 / Tc) sum_t dFc_t,p, in float64."""
        for p in range(self.n):
            acc = ti.Matrix.zero(ti.f64, 3, 3)
            for s in range(ti.static(self.cfg.n_control_slots)):
                acc += ti.cast(self.ctrl[s, p], ti.f64)
            for a, b in ti.static(ti.ndrange(3, 3)):
                out[p, a, b] = acc[a, b] / ti.static(self.cfg.n_control_slots)

    @ti.kernel
    def _rebase_ctrl(self, F: ti.types.ndarray(), M: ti.types.ndarray()):
        """dFc_t <- (F + dFc_t) M - F for every slot t (physmorph.plasticity.rebase_control), in
        float64 as the NumPy formula, stored in the solver's precision."""
        for s, p in self.ctrl:
            Fp = ti.Matrix.zero(ti.f64, 3, 3)
            Mp = ti.Matrix.zero(ti.f64, 3, 3)
            for a, b in ti.static(ti.ndrange(3, 3)):
                Fp[a, b] = F[p, a, b]
                Mp[a, b] = M[p, a, b]
            self.ctrl[s, p] = ti.cast((Fp + ti.cast(self.ctrl[s, p], ti.f64)) @ Mp - Fp, self.dtype)

    @ti.func
    def _step_direction(self, direction: ti.template(), s, p, use_weight: ti.i32, volume_mode: ti.template()):
        """w_p d_sp (w the particle's step weight, 1 unless step_per_volume or use_weight 0), less
        its first-order change of volume (MPMConfig.step_volume; A = F_0 + dFc with dFc the
        iteration's base control and F_0 the frame's start, n = A^-T). volume_mode 1 ("particle"):
        the share beta (step_volume_share) of each particle's, d - beta (<d, n> / <n, n>) n;
        2 ("body"): the body's, d - lambda_s N with N = V_p det(A) n, the gradient of
        sum_p V_p det(A_p), and lambda_s from _body_volume_coefficients."""
        wp = self.step_weight[p] if use_weight else self.dtype(1.0)
        d = direction[s, p] * wp
        # volume_mode is a compile-time constant: the full step's kernels carry no 3x3 inverse
        if ti.static(volume_mode != 0):
            A = self.F[0, p] + self.ctrl_base[s, p]
            n = A.inverse().transpose()
            if ti.static(volume_mode == 1):
                d -= (ti.cast(self.step_volume_share[None], self.dtype) * (d * n).sum() / (n * n).sum()) * n
            else:
                d -= ti.cast(self.step_volume_coef[s], self.dtype) * (self.vol[p] * A.determinant()) * n
        return d

    @ti.kernel
    def _body_volume_coefficients(self, direction: ti.template(), use_weight: ti.i32):
        """lambda_s = <d_s, N_s> / <N_s, N_s> over every particle of slot s (d = w g, N as in
        _step_direction): the step's component that changes the body's volume to first order."""
        for s in self.step_volume_acc:
            self.step_volume_acc[s] = ti.Vector([0.0, 0.0], ti.f64)
        for s, p in self.ctrl:
            wp = self.step_weight[p] if use_weight else self.dtype(1.0)
            d = direction[s, p] * wp
            A = self.F[0, p] + self.ctrl_base[s, p]
            N = (self.vol[p] * A.determinant()) * A.inverse().transpose()
            self.step_volume_acc[s] += ti.Vector([ti.cast((d * N).sum(), ti.f64), ti.cast((N * N).sum(), ti.f64)])
        for s in self.step_volume_coef:
            acc = self.step_volume_acc[s]
            self.step_volume_coef[s] = acc[0] / acc[1] if acc[1] > 0 else 0.0

    @ti.kernel
    def _normalized_step(self, direction: ti.template(), alpha: ti.f64, inv_rms: ti.f64, clip: ti.f64,
                         use_weight: ti.i32, volume_mode: ti.template()):
        """dFc = base - alpha clip(d / rms(d), -clip, clip) (clip <= 0: unclipped), d the step's
        direction (_step_direction: the weighted gradient w g, or the smoothed direction with
        use_weight 0, less its change of volume where asked): the normalised gradient step of
        DiffMPMLib3D's optimiser, in place (tests: the NumPy formula, test_mpm)."""
        for s, p in self.ctrl:
            d = self._step_direction(direction, s, p, use_weight, volume_mode) * ti.cast(inv_rms, self.dtype)
            if clip > 0:
                d = ti.math.clamp(d, -ti.cast(clip, self.dtype), ti.cast(clip, self.dtype))
            self.ctrl[s, p] = self.ctrl_base[s, p] - ti.cast(alpha, self.dtype) * d

    @ti.kernel
    def _direction_dot_gradient(self, direction: ti.template(), inv_rms: ti.f64, clip: ti.f64, use_weight: ti.i32,
                                volume_mode: ti.template()):
        """norm_acc = <g, d>, d = clip(d / rms(d), -clip, clip) as in _normalized_step: the
        objective's first-order fall per unit alpha along the normalised step (the Armijo test's
        rate)."""
        self.norm_acc[None] = 0.0
        for s, p in self.ctrl_grad:
            g = self.ctrl_grad[s, p]
            d = self._step_direction(direction, s, p, use_weight, volume_mode) * ti.cast(inv_rms, self.dtype)
            if clip > 0:
                d = ti.math.clamp(d, -ti.cast(clip, self.dtype), ti.cast(clip, self.dtype))
            self.norm_acc[None] += ti.cast((g * d).sum(), ti.f64)

    @ti.kernel
    def _direction_norm_sq(self, direction: ti.template(), use_weight: ti.i32, volume_mode: ti.template(),
                           by_volume: ti.i32, inv_mean_volume: ti.f64):
        """norm_acc = sum_sp c_p |d_sp|^2, d the step's direction (_step_direction), c_p = 1 or,
        by_volume (MPMConfig.step_rms = "volume"), V_p / mean V: each particle counted by its volume."""
        self.norm_acc[None] = 0.0
        for s, p in direction:
            d = self._step_direction(direction, s, p, use_weight, volume_mode)
            c = ti.cast(self.vol[p], ti.f64) * inv_mean_volume if by_volume else 1.0
            self.norm_acc[None] += ti.cast((d * d).sum(), ti.f64) * c

    def _ensure_step_grid(self) -> None:
        """Allocate the step smoothing's grid and direction (MPMConfig.step_smoothing) on first use."""
        if self.step_grid is None:
            R = self.cfg.grid_res
            mat = ti.types.matrix(3, 3, self.dtype)
            self.step_grid = mat.field(shape=(R, R, R))
            self.step_grid_w = ti.field(self.dtype, shape=(R, R, R))
            self.step_dir = mat.field(shape=(self.cfg.n_control_slots, self.n))

    @ti.kernel
    def _smooth_step_slot(self, s: ti.i32):
        """Slot s of step_dir: the grid's share of the weighted gradient
        (MPMConfig.step_smoothing = "grid"): G_I = sum_p w_Ip V_p w_p g_p / sum_p w_Ip V_p on the
        MPM grid, with the B-spline weights w_Ip of x at the frame's start, then back to the
        particles, d_p = sum_I w_Ip G_I over the nodes that hold material (a partition of unity
        there). What varies from particle to particle within a cell, which the grid the body
        moves on does not see, is removed."""
        for I in ti.grouped(self.step_grid_w):
            self.step_grid[I] = ti.Matrix.zero(self.dtype, 3, 3)
            self.step_grid_w[I] = 0.0
        for p in range(self.n):
            base, fx, w, dw = self._stencil(self.x[0, p])
            g = self.ctrl_grad[s, p] * self.step_weight[p]
            for i, j, k in ti.ndrange(3, 3, 3):
                off, dpos, wip = self._node(fx, w, i, j, k)
                wv = wip * self.vol[p]
                self.step_grid[base + off] += wv * g
                self.step_grid_w[base + off] += wv
        for p in range(self.n):
            base, fx, w, dw = self._stencil(self.x[0, p])
            acc = ti.Matrix.zero(self.dtype, 3, 3)
            for i, j, k in ti.ndrange(3, 3, 3):
                off, dpos, wip = self._node(fx, w, i, j, k)
                m = self.step_grid_w[base + off]
                if m > 0:
                    acc += wip * self.step_grid[base + off] / m
            self.step_dir[s, p] = acc

    @ti.kernel
    def _adam(self, lr_t: ti.f64):
        """Adam (Kingma & Ba) on dFc; lr_t already carries the bias corrections."""
        b1 = self.dtype(self.cfg.adam_beta1)
        b2 = self.dtype(self.cfg.adam_beta2)
        for s, p in self.ctrl:
            g = self.ctrl_grad[s, p]
            m = b1 * self.adam_m[s, p] + (1.0 - b1) * g
            v = b2 * self.adam_v[s, p] + (1.0 - b2) * g * g
            self.adam_m[s, p] = m
            self.adam_v[s, p] = v
            step = ti.Matrix.zero(self.dtype, 3, 3)
            for a, b in ti.static(ti.ndrange(3, 3)):
                step[a, b] = m[a, b] / (ti.sqrt(v[a, b]) + self.dtype(self._eps_hat))
            c = self.ctrl[s, p] - ti.cast(lr_t, self.dtype) * step
            if ti.static(self._clip_on):
                c = ti.math.clamp(c, -self.dtype(self.cfg.control_clip), self.dtype(self.cfg.control_clip))
            self.ctrl[s, p] = c

    # ------------------------------------------------------------------ public API
    def set_target_grid_mass(self, m: np.ndarray) -> None:  # m: [res, res, res]
        """Target grid mass (physmorph.grid.splat_mass convention)."""
        m = np.asarray(m, dtype=np.float64)
        R = self.cfg.grid_res
        if m.shape != (R, R, R):
            raise MPMStateError(f"target grid mass must have shape {(R, R, R)}, got {m.shape}")
        if not np.isfinite(m).all() or (m < 0).any():
            raise MPMStateError("target grid mass must be finite and >= 0")
        self.target_m.from_numpy(m.astype(self.np_dtype))
        for lv, (_, ct, _) in enumerate(self.pyramid, start=1):
            b = 1 << lv
            ct.from_numpy(m.reshape(R // b, b, R // b, b, R // b, b).sum(axis=(1, 3, 5)).astype(self.np_dtype))
        if self.blur_grids:
            self._blur(self.target_m, self.blur_grids[1])
        self._has_target = True
        self._forward_current = False  # the cached loss refers to the old target

    def load_state(self, state: ParticleState) -> None:
        """Set the frame's initial state (x, v, F, C at t = 0 and the constants Fp, m, V0)."""
        st = state.validated()
        if st.n != self.n:
            raise MPMStateError(f"state has {st.n} particles, solver was built for {self.n}")
        bad = ((st.x < self._x_min) | (st.x > self._x_max)).any(axis=1)
        if bad.any():
            p = int(np.argmax(bad))
            raise MPMStateError(
                f"x of particle {p} = {st.x[p].tolist()} is outside the usable domain "
                f"[{self._x_min}, {self._x_max}] (the B-spline stencil would leave the grid)")
        dt_ = self.np_dtype
        self._load_initial(st.x.astype(dt_), st.v.astype(dt_), st.F.astype(dt_), st.C.astype(dt_))
        self.Fp_inv.from_numpy(np.linalg.inv(st.Fp).astype(dt_))
        self.mass.from_numpy(st.mass.astype(dt_))
        self.vol.from_numpy(st.volume.astype(dt_))
        weight = ((st.volume.max() / st.volume) ** self.cfg.step_volume_power if self.cfg.step_per_volume
                  else np.ones(self.n))
        self.step_weight.from_numpy(weight.astype(dt_))
        self._weighted_step = bool(self.cfg.step_per_volume and (weight != 1.0).any())
        self._inv_mean_volume = float(1.0 / st.volume.mean())
        if self._pressure_on:
            self._frame_pressure()
        self._Fp = st.Fp.copy()
        self._log_eps = float(self.cfg.log_mass_eps * st.mass.mean())
        self._loaded = True
        self._forward_done = False
        self._forward_current = False
        if not self.cfg.warm_start:
            self.reset_control()

    def reset_control(self) -> None:
        """Zero dFc and the Adam moments (and the Adam step counter)."""
        self.ctrl.fill(0.0)
        self.ctrl_grad.fill(0.0)
        if self.adam_m is not None:
            self.adam_m.fill(0.0)
            self.adam_v.fill(0.0)
        self._adam_step = 0
        self._forward_current = False

    def forward(self) -> float:
        """T substeps from the loaded state with the current dFc; returns the mass loss (or nan
        without a target). Raises MPMDivergenceError if the state became non-finite."""
        self._require_loaded()
        self._rollout_id += 1
        for t in range(self.cfg.substeps):
            self._clear_grid()
            self._p2g(t)
            self._store_grid(t)
            self._grid_update()
            self._g2p(t)
        self._forward_current = False
        self._check_finite_rollout()
        self._forward_done = True
        self._forward_current = True
        if self._has_target:
            self._clear_grid()
            self._splat_mass(self.cfg.substeps)
            self._loss_with_adjoint()
            self._last_mass_loss = float(self.loss_acc[None])
            if self._anchored:
                self._anchor_loss()
                self._last_loss = float(self.loss_acc[None])
            else:
                self._last_loss = self._last_mass_loss
        else:
            self._last_loss = self._last_mass_loss = float("nan")
        return self._last_loss

    def backward(self, grad_F_final: np.ndarray | None = None,  # [N, 3, 3]
                 grad_x_final: np.ndarray | None = None,  # [N, 3]
                 include_mass_loss: bool = True) -> None:
        """Reverse the last forward: d(L + <gF, F_T> + <gx, x_T>)/d(dFc) into the control
        gradient, and the adjoint of the initial state (see initial_state_gradients).
        ``include_mass_loss=False`` pulls back the injected adjoints alone (the morph loop uses
        it to compare their size with the mass loss's without float32 cancellation)."""
        self._reverse(grad_F_final, grad_x_final, include_mass_loss, pair=False)

    def backward_pair(self, grad_F_final: np.ndarray | None = None,  # [N, 3, 3]
                      grad_x_final: np.ndarray | None = None) -> tuple[float, float]:  # [N, 3]
        """One reverse sweep of the last forward carrying two adjoints: the mass loss's dFc
        gradient into the line search's base field and the injected adjoints' alone, d(<gF, F_T>
        + <gx, x_T>)/d(dFc), into the control gradient. Equal to backward(None, None) and
        backward(gF, gx, include_mass_loss=False) run one after the other, for the cost of about
        one and a half: the restored forward state, the stencils and the grid loads are shared.
        Returns the two gradients' norms (mass, injected)."""
        self._ensure_pair()
        self._reverse(grad_F_final, grad_x_final, include_mass_loss=False, pair=True)
        self._norm_sq(self.ctrl_base)
        n_mass = float(self.norm_acc[None])
        if not np.isfinite(n_mass):
            raise MPMDivergenceError("the mass loss's dFc gradient became non-finite (NaN/Inf) in the backward pass")
        return float(np.sqrt(n_mass)), self._grad_norm

    def _ensure_pair(self) -> None:
        """Allocate the second adjoint set (backward_pair) on first use."""
        if self.x_adj2 is None:
            f, N, R = self.dtype, self.n, self.cfg.grid_res
            vec, mat = ti.types.vector(3, f), ti.types.matrix(3, 3, f)
            self.x_adj2, self.v_adj2 = vec.field(shape=N), vec.field(shape=N)
            self.C_adj2, self.F_adj2 = mat.field(shape=N), mat.field(shape=N)
            self.grid_v_adj2, self.grid_mv_adj2 = vec.field(shape=(R, R, R)), vec.field(shape=(R, R, R))
            self.grid_m_adj2 = ti.field(f, shape=(R, R, R))

    def _reverse(self, grad_F_final, grad_x_final, include_mass_loss: bool, pair: bool) -> None:
        """The reverse sweep: the injected adjoints (and the mass loss unless excluded) in the
        first adjoint set into ctrl_grad; with pair, the mass loss alone in the second into
        ctrl_base."""
        if not self._forward_current:
            raise RuntimeError("backward needs a forward() of the current state and dFc first")
        self._calibrated_for = self._combined_for = -1  # ctrl_grad is overwritten
        N = self.n
        gx = np.zeros((N, 3)) if grad_x_final is None else self._check_adjoint(grad_x_final, (N, 3), "grad_x_final")
        gF = np.zeros((N, 3, 3)) if grad_F_final is None else self._check_adjoint(grad_F_final, (N, 3, 3), "grad_F_final")
        self.x_adj.from_numpy(gx.astype(self.np_dtype))
        self.F_adj.from_numpy(gF.astype(self.np_dtype))
        self.v_adj.fill(0.0)
        self.C_adj.fill(0.0)
        self._zero_control_field(self.ctrl_grad)
        if pair:
            for f in (self.x_adj2, self.v_adj2, self.C_adj2, self.F_adj2):
                f.fill(0.0)
            self._zero_control_field(self.ctrl_base)
        if self._has_target and (include_mass_loss or pair):
            self._clear_grid()
            self._splat_mass(self.cfg.substeps)
            self._loss_with_adjoint()
            self._loss_backward(self.x_adj2 if pair else self.x_adj)
            if self._anchored:
                self._anchor_backward(self.x_adj2 if pair else self.x_adj)
        for t in reversed(range(self.cfg.substeps)):
            self._restore_p2g(t)
            self._grid_update()
            self._clear_grid_adj(pair)
            self._g2p_backward(t, pair)
            self._grid_backward(pair)
            self._p2g_backward(t, pair)
        self._grad_norm_sq()
        gn = float(self.norm_acc[None])
        if not np.isfinite(gn):
            raise MPMDivergenceError("the dFc gradient became non-finite (NaN/Inf) in the backward pass")
        self._grad_norm = float(np.sqrt(gn))

    def _ensure_adam(self) -> None:
        """Allocate Adam's moments (zero) on first use."""
        if self.adam_m is None:
            mat = ti.types.matrix(3, 3, self.dtype)
            shape = (self.cfg.n_control_slots, self.n)
            self.adam_m = mat.field(shape=shape)
            self.adam_v = mat.field(shape=shape)
            self.adam_m.fill(0.0)
            self.adam_v.fill(0.0)

    def optimizer_state(self) -> dict:
        """dFc (in the solver's precision: exact), the Adam moments where Adam has run, and the
        step count: everything needed to resume the optimization."""
        out = {"control": self.ctrl.to_numpy(), "adam_step": int(self._adam_step)}
        if self.adam_m is not None:
            out.update(adam_m=self.adam_m.to_numpy(), adam_v=self.adam_v.to_numpy())
        return out

    def set_optimizer_state(self, state: dict) -> None:
        """Restore what :meth:`optimizer_state` returned (moments absent: zero)."""
        self.set_control(state["control"])
        shape = (self.cfg.n_control_slots, self.n, 3, 3)
        has_moments = "adam_m" in state or "adam_v" in state
        if has_moments:
            for key in ("adam_m", "adam_v"):
                arr = np.asarray(state[key])
                if arr.shape != shape or not np.isfinite(arr).all():
                    raise MPMStateError(f"{key} must be finite with shape {shape}, got {arr.shape}")
            self._ensure_adam()
            self.adam_m.from_numpy(np.asarray(state["adam_m"]).astype(self.np_dtype, copy=False))
            self.adam_v.from_numpy(np.asarray(state["adam_v"]).astype(self.np_dtype, copy=False))
        elif self.adam_m is not None:
            self.adam_m.fill(0.0)
            self.adam_v.fill(0.0)
        self._adam_step = int(state["adam_step"])
        self._forward_current = False

    def adam_step(self, learning_rate: float | None = None) -> None:
        """One Adam step on dFc with the gradient of the last backward (step cfg.step_size unless
        given)."""
        self._adam_step += 1
        k = self._adam_step
        b1, b2 = self.cfg.adam_beta1, self.cfg.adam_beta2
        lr = self.cfg.step_size if learning_rate is None else learning_rate
        # folded bias correction: lr_t = lr sqrt(1 - b2^k) / (1 - b1^k), eps_hat = eps sqrt(1 - b2^k)
        lr_t = lr * np.sqrt(1.0 - b2 ** k) / (1.0 - b1 ** k)
        self._ensure_adam()
        self._adam(lr_t)
        self._forward_current = False

    @property
    def _eps_hat(self) -> float:
        # a compile-time constant of _adam: eps without the step-dependent factor (a tiny
        # difference from textbook Adam, whose eps is added after the bias correction)
        return self.cfg.adam_eps

    def optimize_control(self, grad_F_final: np.ndarray | None = None,  # [N, 3, 3]
                         grad_x_final: np.ndarray | None = None,  # [N, 3]
                         iters: int | None = None,
                         gradient_ready: bool = False,
                         learning_rate: float | None = None) -> dict:
        """J iterations of forward -> mass loss -> backward (+ injected adjoints) -> a step on dFc (cfg.optimizer),
        then a last forward with the updated dFc (its loss is loss_final; rollout() returns it).

        gradient_ready: the first iteration's dFc gradient (mass loss + injected terms) is already
        in place for the current rollout (combine_calibration after calibration_gradients: the
        morph loop's injection calibration); that iteration's forward and backward are skipped.
        learning_rate: this call's step (normalised GD: the initial alpha; Adam: lr) instead of
        cfg.step_size (the morph loop's adaptive step, MorphConfig.step_backoff)."""
        if not self._has_target:
            raise RuntimeError("optimize_control needs set_target_grid_mass first")
        J = self.cfg.grad_iters if iters is None else int(iters)
        if J < 1:
            raise ValueError(f"iters must be >= 1, got {J}")
        if gradient_ready and not (self._forward_current and self._combined_for == self._rollout_id):
            raise RuntimeError("gradient_ready needs calibration_gradients and combine_calibration on a "
                               "forward() of the current state and dFc")
        lr = self.cfg.step_size if learning_rate is None else float(learning_rate)
        if not (np.isfinite(lr) and lr > 0):
            raise ValueError(f"learning_rate must be finite and > 0, got {learning_rate!r}")
        if self.cfg.optimizer == "normalized_gd":
            return self._optimize_normalized_gd(grad_F_final, grad_x_final, J, gradient_ready, lr)
        losses = []
        for j in range(J):
            if j == 0 and gradient_ready:
                losses.append(self._last_loss)
            else:
                losses.append(self.forward())
                self.backward(grad_F_final, grad_x_final)
            self.adam_step(lr)
        loss_final = self.forward()
        return {"loss_initial": losses[0], "loss_final": loss_final, "losses": losses,
                "grad_norm": self._grad_norm, "iters": J,
                "delta_E_percent": 100.0 * (losses[0] - loss_final) / losses[0] if losses[0] > 0 else 0.0}

    def calibration_gradients(self, grad_F_final: np.ndarray | None = None,  # [N, 3, 3]
                              grad_x_final: np.ndarray | None = None,  # [N, 3]
                              pair: bool | None = None) -> tuple[float, float]:
        """The injection calibration's two dFc gradients on one rollout of the current state and
        dFc (run here): the mass loss's and the injected adjoint's alone (a difference of two
        backwards would drown in float32 round-off). Returns their norms; the gradients stay in
        the solver (no [Tc, N, 3, 3] copies) for combine_calibration.

        pair: one reverse sweep for both (backward_pair) or two backwards; by default the pair
        from PAIR_MIN_PARTICLE_STEPS particle-substeps on, where its saving a frame pays back its
        compilation within a few frames."""
        if pair is None:
            pair = self.n * self.cfg.substeps >= PAIR_MIN_PARTICLE_STEPS
        self.forward()
        if pair:
            n_mass, n_inj = self.backward_pair(grad_F_final, grad_x_final)
        else:
            self.backward(None, None)
            n_mass = self._grad_norm
            self._copy_grad_to_base()
            self.backward(grad_F_final, grad_x_final, include_mass_loss=False)
            n_inj = self._grad_norm
        self._calibrated_for = self._rollout_id
        return n_mass, n_inj

    def combine_calibration(self, scale: float) -> None:
        """The dFc gradient of mass loss + scale <g, final state> from calibration_gradients' two
        (the backward is linear in the injected adjoint), in place, as the last backward's
        gradient: optimize_control(gradient_ready=True) starts from it."""
        if not (self._forward_current and self._calibrated_for == self._rollout_id):
            raise RuntimeError("combine_calibration needs calibration_gradients on the current rollout")
        if not np.isfinite(scale):
            raise ValueError(f"scale must be finite, got {scale!r}")
        self._combine_gradients(float(scale))
        self._calibrated_for = -1  # the mass gradient's copy is consumed (the line search reuses its field)
        self._combined_for = self._rollout_id
        self._grad_norm_sq()
        self._grad_norm = float(np.sqrt(self.norm_acc[None]))

    def _objective(self, grad_F_final, grad_x_final, run_forward: bool = True) -> float:
        """Forward (unless the stored rollout is current and run_forward is False), then mass
        loss + <gF, F_T> + <gx, x_T> (what the backward differentiates)."""
        J = self.forward() if run_forward or not self._forward_current else self._last_loss
        if grad_F_final is not None or grad_x_final is not None:
            x, _, F, _ = self._export_raw(self.cfg.substeps)
            if grad_F_final is not None:
                J += float((np.asarray(grad_F_final) * F).sum())
            if grad_x_final is not None:
                J += float((np.asarray(grad_x_final) * x).sum())
        return J

    def _step_norm(self, direction, use_weight: int, volume_mode: int) -> float:
        """|d| of the step's direction (_step_direction; the smoothed direction already carries w),
        each particle counted once or by its volume (MPMConfig.step_rms)."""
        by_volume = self.cfg.step_rms == "volume"
        if use_weight and not (self._weighted_step or volume_mode or by_volume):
            return self._grad_norm  # the backward's own |g|
        self._direction_norm_sq(direction, use_weight, volume_mode, int(by_volume), self._inv_mean_volume)
        return float(np.sqrt(self.norm_acc[None]))

    def _optimize_normalized_gd(self, grad_F_final, grad_x_final, iters: int,
                                gradient_ready: bool, learning_rate: float) -> dict:
        """Normalised gradient descent with backtracking (DiffMPMLib3D's optimiser): per
        iteration dFc <- dFc - alpha g / rms(g), alpha starting at learning_rate and halved
        until the objective decreases (at most line_search_iters tries; else the step is undone
        and the frame's optimisation stops)."""
        losses = []
        obj = self._objective(grad_F_final, grad_x_final, run_forward=not gradient_ready)
        loss_initial = self._last_loss
        alpha = learning_rate  # optimize_control resolved it (cfg.learning_rate unless given)
        accepted = 0
        for j in range(iters):
            losses.append(self._last_loss)
            if not (j == 0 and gradient_ready):
                self.backward(grad_F_final, grad_x_final)
            # the norm was accumulated in float64 by the kernel; the step is taken in place
            # (_normalized_step), from the control saved at the iteration's start
            direction, use_weight = self.ctrl_grad, 1
            if self.cfg.step_smoothing == "grid":
                self._ensure_step_grid()
                for slot in range(self.cfg.n_control_slots):
                    self._smooth_step_slot(slot)
                direction, use_weight = self.step_dir, 0  # the weights are in the smoothed direction
            volume_mode = STEP_VOLUME_MODES.index(self.cfg.step_volume)
            # the base first: the step's change of volume is taken at the iteration's control
            self._save_ctrl_base()
            if self.cfg.step_volume == "body":
                self._body_volume_coefficients(direction, use_weight)
            self.step_volume_share[None] = self.cfg.step_volume_share
            rms = self._step_norm(direction, use_weight, volume_mode) / np.sqrt(self.cfg.n_control_slots * self.n * 9)
            if not rms > 0:
                break
            rate = 0.0
            if self.cfg.sufficient_decrease > 0:
                self._direction_dot_gradient(direction, 1.0 / rms, self.cfg.step_clip, use_weight, volume_mode)
                rate = self.cfg.sufficient_decrease * float(self.norm_acc[None])
            found = False
            for _ in range(self.cfg.line_search_iters):
                self._normalized_step(direction, alpha, 1.0 / rms, self.cfg.step_clip, use_weight, volume_mode)
                self._forward_current = False
                try:
                    trial = self._objective(grad_F_final, grad_x_final)
                except MPMDivergenceError:  # a step so large the rollout blows up: shorten it
                    trial = float("inf")
                if trial < obj - alpha * rate:
                    obj, found = trial, True
                    break
                alpha *= 0.5
            if not found:
                self._restore_ctrl_base()
                self._forward_current = False
                self.forward()
                break
            accepted += 1
        if not self._forward_current:
            self.forward()
        loss_final = self._last_loss
        self._ls_alpha = alpha
        return {"loss_initial": loss_initial, "loss_final": loss_final, "losses": losses,
                "grad_norm": self._grad_norm, "iters": accepted, "step": alpha,
                "delta_E_percent": 100.0 * (loss_initial - loss_final) / loss_initial if loss_initial > 0 else 0.0}

    def rollout(self) -> ParticleState:
        """Forward with the current dFc and return the state at t = T (the forward is skipped
        when the stored trajectory already belongs to the current state, dFc and target, e.g.
        right after optimize_control)."""
        if not self._forward_current:
            self.forward()
        return self.state_at(self.cfg.substeps)

    def loss(self) -> float:
        """The last forward's loss: the end-layer mass loss plus the anchors' term
        (set_position_anchors), what forward() returned."""
        if self._last_loss is None:
            raise RuntimeError("loss needs a forward first")
        return self._last_loss

    def mass_loss(self) -> float:
        """The last forward's end-layer mass loss (with the packing term), without the anchors' term."""
        if self._last_mass_loss is None:
            raise RuntimeError("mass_loss needs a forward first")
        return self._last_mass_loss

    def state_at(self, t: int) -> ParticleState:
        """Stored particle state at substep t (0..T) of the last forward, float64."""
        T = self.cfg.substeps
        if not 0 <= t <= T:
            raise IndexError(f"substep t must be in [0, {T}], got {t}")
        self._require_loaded()
        x, v, F, C = self._export_raw(t)
        return ParticleState(x=x.astype(np.float64), v=v.astype(np.float64), F=F.astype(np.float64),
                             C=C.astype(np.float64), Fp=self._Fp.copy(),
                             mass=self.mass.to_numpy().astype(np.float64),
                             volume=self.vol.to_numpy().astype(np.float64))

    def grid_mass(self) -> np.ndarray:  # [res, res, res]
        """Grid mass of x_T from the last forward (valid right after forward/rollout)."""
        self._clear_grid()
        self._splat_mass(self.cfg.substeps)
        return self.grid_m.to_numpy().astype(np.float64)

    def frame_pressure(self) -> np.ndarray:  # [N]
        """The loaded frame's packing pressure per particle (zeros when volume_stiffness is 0)."""
        self._require_loaded()
        return self.press.to_numpy().astype(np.float64) if self._pressure_on else np.zeros(self.n)

    def control(self, native: bool = False) -> np.ndarray:  # [Tc, N, 3, 3]
        """dFc, float64 (native: in the solver's precision, no conversion)."""
        c = self.ctrl.to_numpy()
        return c if native else c.astype(np.float64)

    def set_control(self, dFc: np.ndarray) -> None:  # [Tc, N, 3, 3]
        dFc = np.asarray(dFc)
        if not np.issubdtype(dFc.dtype, np.floating):
            dFc = dFc.astype(np.float64)
        shape = (self.cfg.n_control_slots, self.n, 3, 3)
        if dFc.shape != shape or not np.isfinite(dFc).all():
            raise MPMStateError(f"dFc must be finite with shape {shape}, got {dFc.shape}")
        self.ctrl.from_numpy(np.ascontiguousarray(dFc, dtype=self.np_dtype))
        self._forward_current = False

    def set_overfill_weight(self, weight: float) -> None:
        """The packing term's weight from now on (MorphConfig.overfill_onset switches it on during a
        run): 0 leaves the configured mass loss alone; any weight needs a solver built with
        overfill_weight > 0, whose kernels carry the term."""
        if not (np.isfinite(weight) and weight >= 0):
            raise ValueError(f"overfill weight must be finite and >= 0, got {weight!r}")
        if weight > 0 and not self.cfg.overfill_weight > 0:
            raise MPMConfigError("set_overfill_weight > 0 needs a solver built with overfill_weight > 0")
        self._overfill_weight = float(weight)
        self._forward_current = False

    def set_position_anchors(self, anchor: np.ndarray | None,  # [N, 3]
                             weight: np.ndarray | None = None) -> None:  # [N]
        """Add sum_p w_p |x_T,p - a_p|^2 to the loss from now on (the morph loop's stray pull,
        MorphConfig.stray_pull); None removes the term. The fields are allocated on first use."""
        if anchor is None:
            self._anchored = False
            self._forward_current = False
            return
        a = self._check_adjoint(anchor, (self.n, 3), "anchor")
        w = np.asarray(weight, dtype=np.float64)
        if w.shape != (self.n,) or not np.isfinite(w).all() or (w < 0).any():
            raise MPMStateError(f"anchor weights must be [{self.n}], finite and >= 0")
        if self.anchor is None:
            self.anchor = ti.types.vector(3, self.dtype).field(shape=self.n)
            self.anchor_w = ti.field(self.dtype, shape=self.n)
        self.anchor.from_numpy(a.astype(self.np_dtype))
        self.anchor_w.from_numpy(w.astype(self.np_dtype))
        self._anchored = bool((w > 0).any())
        self._forward_current = False

    @property
    def overfill_weight(self) -> float:
        """The packing term's weight in use (MPMConfig.overfill_weight unless set_overfill_weight)."""
        return self._overfill_weight

    def scale_control(self, factor: float) -> None:
        """dFc <- factor dFc, in place (the morph loop's leak and restart; no copy of the control)."""
        if not np.isfinite(factor):
            raise ValueError(f"factor must be finite, got {factor!r}")
        self._scale_ctrl(float(factor))
        self._forward_current = False

    def control_mean(self) -> np.ndarray:  # [N, 3, 3]
        """mean_t dFc_t, float64 (no [Tc, N, 3, 3] copy of the control)."""
        out = np.empty((self.n, 3, 3))
        self._control_mean(out)
        return out

    def rebase_control(self, F: np.ndarray,  # [N, 3, 3]
                       M: np.ndarray) -> None:  # [N, 3, 3]
        """dFc_t <- (F + dFc_t) M - F for every slot, in place (physmorph.plasticity.rebase_control
        with M = Fp_old^-1 Fp_new; no [Tc, N, 3, 3] copy of the control)."""
        F = np.ascontiguousarray(F, dtype=np.float64)
        M = np.ascontiguousarray(M, dtype=np.float64)
        if F.shape != (self.n, 3, 3) or M.shape != (self.n, 3, 3):
            raise MPMStateError(f"F and M must have shape {(self.n, 3, 3)}, got {F.shape} and {M.shape}")
        if not (np.isfinite(F).all() and np.isfinite(M).all()):
            raise MPMStateError("F and M must be finite")
        self._rebase_ctrl(F, M)
        self._forward_current = False

    def control_gradient(self, native: bool = False) -> np.ndarray:  # [Tc, N, 3, 3]
        """The last backward's dFc gradient, float64 (native: in the solver's precision)."""
        g = self.ctrl_grad.to_numpy()
        return g if native else g.astype(np.float64)

    def initial_state_gradients(self) -> dict:
        """Adjoints of the initial x, v, C, F after backward(): {"x": [N,3], "v", "C", "F"}."""
        return {"x": self.x_adj.to_numpy().astype(np.float64),
                "v": self.v_adj.to_numpy().astype(np.float64),
                "C": self.C_adj.to_numpy().astype(np.float64),
                "F": self.F_adj.to_numpy().astype(np.float64)}

    @property
    def grad_norm(self) -> float:
        return self._grad_norm

    def bytes_per_particle_substep(self) -> int:
        """Stored per particle per substep: x, v (3 each), C, F (9 each) and the forward's polar
        rotation (a quaternion, 4) and pair sum (1): 29 floats."""
        return 29 * np.dtype(self.np_dtype).itemsize

    # ------------------------------------------------------------------ helpers
    def _require_loaded(self) -> None:
        if not self._loaded:
            raise RuntimeError("call load_state before running the solver")

    def _export_raw(self, t: int):
        n, d = self.n, self.np_dtype
        x, v = np.empty((n, 3), d), np.empty((n, 3), d)
        F, C = np.empty((n, 3, 3), d), np.empty((n, 3, 3), d)
        self._export(t, x, v, F, C)
        return x, v, F, C

    def _check_adjoint(self, g, shape, name) -> np.ndarray:
        g = np.asarray(g, dtype=np.float64)
        if g.shape != shape:
            raise MPMStateError(f"{name} must have shape {shape}, got {g.shape}")
        if not np.isfinite(g).all():
            raise MPMStateError(f"{name} is not finite (NaN/Inf)")
        return g

    def _check_finite_rollout(self) -> None:
        """Cheap check of the final state; on failure find the first bad substep/particle."""
        T = self.cfg.substeps
        def bad_rows(t):
            x, v, F, _ = self._export_raw(t)
            for name, a in (("x", x), ("v", v), ("F", F)):
                a = a.reshape(self.n, -1)
                bad = ~(np.abs(a) <= _BLOWUP).all(axis=1)
                if bad.any():
                    return name, int(np.argmax(bad))
            return None

        if bad_rows(T) is None:
            return
        for t in range(1, T + 1):
            hit = bad_rows(t)
            if hit is not None:
                name, p = hit
                raise MPMDivergenceError(
                    f"{name} became non-finite (NaN/Inf or |{name}| > {_BLOWUP:g}) at substep "
                    f"{t - 1} (particle {p})")


# Every solver solver_for built, with its config's kernel settings and size. Taichi does not free a
# dropped solver's fields, so keeping them costs no memory, and a process that alternates settings
# (the tests, the study scripts) compiles each set once.
_reusable: list = []


def solver_for(cfg: MPMConfig, n_particles: int) -> MPMSolver:
    """A reset MPMSolver for (cfg, n_particles): the one an earlier call built for this particle
    count and these kernel settings (every field but DRIVER_FIELDS: learning rate, optimiser, line
    search, ...), given cfg, else a new one. Building a solver compiles its kernels (about 36
    Taichi kernels: 18 s on a 2-core CPU with Taichi's offline cache empty, 5 s with it filled by
    an earlier process; a second instance in one process pays again), so several runs in one
    process share it. Not for two runs of one setting at once: each call resets the solver."""
    n = int(n_particles)
    settings = cfg.kernel_settings()
    for kept_settings, kept_n, solver in _reusable:
        if kept_n == n and kept_settings == settings:
            solver.reset()
            solver.configure(cfg)
            return solver
    solver = MPMSolver(cfg, n)
    _reusable.append((settings, n, solver))
    return solver
