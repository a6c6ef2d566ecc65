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

P = 2 mu (Fe - R) + lam (J - 1) cof(Fe), with cof(Fe) = J Fe^-T written with cross products
so it stays finite for singular Fe. The control dFc enters the stress only (it acts like an
actuation); F itself is advected by the grid velocity. The end-layer mass loss compares the
grid mass of x_T (same quadratic B-spline as physmorph.base.grid.splat_mass) with the target.

Backward: the adjoint of each substep is written by hand (reverse of G2P, grid update, P2G);
the per-substep particle state (x, v, C, F), the rotation of Fe with its smallest pair sum, and
the P2G grid are stored in the forward; the backward restores A and Fe from them (no second SVD). The stress model and its
hand-written differential, the rotation derivative included, are in physmorph.mpm.stress.
"""

import numpy as np
import taichi as ti

from physmorph.base.grid import BOUNDARY_CELLS, Grid
from physmorph.base.taichi_runtime import init_taichi
from physmorph.settings.mpm import MPMConfig, MPMConfigError, MPMDivergenceError, MPMStateError
from .control import ControlField
from .currency import Currency
from .fields import SolverFields
from physmorph.settings.solver_memory import bytes_per_particle_substep
from .optimiser import Adam, NormalizedGD
from .physics_loss import PhysicsLoss
from .state import ParticleState
from .step_kernels import StepKernels
from .stress import evaluate_stress, make_stress_funcs  # noqa: F401 (evaluate_stress re-exported)
from .transfers import Transfers

# |F| or |v| entries above this are treated as a divergence (Inf follows soon after).
_BLOWUP = 1e8
# the injection calibration's backward_pair from this many particle-substeps on (n x substeps;
# below, its kernels' compilation costs more than it saves in a run: docs/performance.md)
PAIR_MIN_PARTICLE_STEPS = 1_000_000


@ti.data_oriented
class MPMSolver(SolverFields, Transfers, PhysicsLoss, ControlField, StepKernels):
    """Differentiable MPM over one frame of T substeps, with the control field dFc and its optimisers (normalised GD, Adam).

    Built once per (config, particle count); ``load_state`` each frame. The kernels live in the
    mixins by concern (fields, transfers, physics_loss, control, step_kernels), the optimisers in
    physmorph.mpm.optimiser, what the stored results belong to in ``self.current``
    (physmorph.mpm.currency). See physmorph/mpm/__init__.py for the design decisions.
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
        self._allocate_fields()
        self._stress_model = make_stress_funcs(self.dtype, cfg.mu, cfg.lam)
        # compile-time constants of the kernels
        self._dx = cfg.dx
        self._inv_dx = 1.0 / cfg.dx
        self._lo = cfg.domain_lo
        self._res = cfg.grid_res
        self._bound = BOUNDARY_CELLS
        # positions are clamped so the 3x3x3 stencil never leaves the grid: x_g in [1, res - 2]
        self._x_min = cfg.domain_lo + 1.0 * cfg.dx
        self._x_max = cfg.domain_lo + (cfg.grid_res - 2.0) * cfg.dx
        self.reset()

    def reset(self) -> None:
        """Back to a freshly built solver: no state or target loaded, dFc and the Adam moments
        zero. Every other field is written before it is read (load_state, set_target_grid_mass,
        forward, backward), so a reset solver computes what a new one would."""
        self.current = Currency()
        self._grad_norm = float("nan")
        self._Fp = None
        self._last_loss: float | None = None
        self._last_mass_loss: float | None = None  # the last forward's loss without the anchors' term
        self.adam, self.normalized_gd = Adam(self), NormalizedGD(self)
        self._kept = None  # keep_control: its fields (allocated on first use) or its file
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
        weight = st.volume.max() / st.volume if self.cfg.step_per_volume else np.ones(self.n)
        self.step_weight.from_numpy(weight.astype(dt_))
        self._weighted_step = bool(self.cfg.step_per_volume and (weight != 1.0).any())
        self._Fp = st.Fp.copy()
        self._log_eps = float(self.cfg.log_mass_eps * st.mass.mean())
        self.current.loaded = True
        self.current.stale()

    def forward(self) -> float:
        """T substeps from the loaded state with the current dFc; returns the mass loss (or nan
        without a target). Raises MPMDivergenceError if the state became non-finite."""
        self._require_loaded()
        self.current.new_rollout()
        for t in range(self.cfg.substeps):
            self._clear_grid()
            self._p2g(t)
            self._store_grid(t)
            self._grid_update()
            self._g2p(t)
        self.current.stale()
        self._check_finite_rollout()
        self.current.trajectory_current = True
        if self.current.has_target:
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
            raise MPMDivergenceError("the mass loss's dFc gradient became non-finite (NaN/Inf) in the backward pass",
                                      quantity="mass loss's dFc gradient")
        return float(np.sqrt(n_mass)), self._grad_norm

    def _reverse(self, grad_F_final, grad_x_final, include_mass_loss: bool, pair: bool) -> None:
        """The reverse sweep: the injected adjoints (and the mass loss unless excluded) in the
        first adjoint set into ctrl_grad; with pair, the mass loss alone in the second into
        ctrl_base."""
        if not self.current.trajectory_current:
            raise RuntimeError("backward needs a forward() of the current state and dFc first")
        self.current.gradients_overwritten()  # ctrl_grad is overwritten
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
        if self.current.has_target and (include_mass_loss or pair):
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
            raise MPMDivergenceError("the dFc gradient became non-finite (NaN/Inf) in the backward pass",
                                      quantity="dFc gradient")
        self._grad_norm = float(np.sqrt(gn))

    def optimize_control(self, grad_F_final: np.ndarray | None = None,  # [N, 3, 3]
                         grad_x_final: np.ndarray | None = None,  # [N, 3]
                         iters: int | None = None,
                         gradient_ready: bool = False,
                         learning_rate: float | None = None) -> dict:
        """J iterations of forward -> mass loss -> backward (+ injected adjoints) -> a step on dFc
        (cfg.optimizer: physmorph.mpm.optimiser), then a last forward with the updated dFc (its
        loss is loss_final; rollout() returns it).

        gradient_ready: the first iteration's dFc gradient (mass loss + injected terms) is already
        in place for the current rollout (combine_calibration after calibration_gradients: the
        morph loop's injection calibration); that iteration's forward and backward are skipped.
        learning_rate: this call's step (normalised GD: the initial alpha; Adam: lr) instead of
        cfg.step_size (the morph loop's step, backed off after an undone frame: MorphConfig.settle_backoff)."""
        if not self.current.has_target:
            raise RuntimeError("optimize_control needs set_target_grid_mass first")
        J = self.cfg.grad_iters if iters is None else int(iters)
        if J < 1:
            raise ValueError(f"iters must be >= 1, got {J}")
        now = self.current
        if gradient_ready and not (now.trajectory_current and now.combined_for == now.rollout):
            raise RuntimeError("gradient_ready needs calibration_gradients and combine_calibration on a "
                               "forward() of the current state and dFc")
        lr = self.cfg.step_size if learning_rate is None else float(learning_rate)
        if not (np.isfinite(lr) and lr > 0):
            raise ValueError(f"learning_rate must be finite and > 0, got {learning_rate!r}")
        optimiser = self.normalized_gd if self.cfg.optimizer == "normalized_gd" else self.adam
        return optimiser.run(grad_F_final, grad_x_final, J, gradient_ready, lr)

    def adam_step(self, learning_rate: float | None = None) -> None:
        """One Adam step on dFc with the gradient of the last backward (step cfg.step_size unless given)."""
        self.adam.step(learning_rate)

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
        self.current.calibrated_for = self.current.rollout
        return n_mass, n_inj

    def combine_calibration(self, scale: float) -> None:
        """The dFc gradient of mass loss + scale <g, final state> from calibration_gradients' two
        (the backward is linear in the injected adjoint), in place, as the last backward's
        gradient: optimize_control(gradient_ready=True) starts from it."""
        if not (self.current.trajectory_current and self.current.calibrated_for == self.current.rollout):
            raise RuntimeError("combine_calibration needs calibration_gradients on the current rollout")
        if not np.isfinite(scale):
            raise ValueError(f"scale must be finite, got {scale!r}")
        self._combine_gradients(float(scale))
        self.current.calibrated_for = -1  # the mass gradient's copy is consumed (the line search reuses its field)
        self.current.combined_for = self.current.rollout
        self._grad_norm_sq()
        self._grad_norm = float(np.sqrt(self.norm_acc[None]))

    def rollout(self) -> ParticleState:
        """Forward with the current dFc and return the state at t = T (the forward is skipped
        when the stored trajectory already belongs to the current state, dFc and target, e.g.
        right after optimize_control)."""
        if not self.current.trajectory_current:
            self.forward()
        return self.state_at(self.cfg.substeps)

    def grid_mass(self) -> np.ndarray:  # [res, res, res]
        """Grid mass of x_T from the last forward (valid right after forward/rollout)."""
        self._clear_grid()
        self._splat_mass(self.cfg.substeps)
        return self.grid_m.to_numpy().astype(np.float64)

    @property
    def grad_norm(self) -> float:
        return self._grad_norm

    def bytes_per_particle_substep(self) -> int:
        """Stored per particle per substep (physmorph.settings.solver_memory: x, v, C, F, the rotation's
        quaternion and pair sum)."""
        return bytes_per_particle_substep(self.cfg)

    def _require_loaded(self) -> None:
        if not self.current.loaded:
            raise RuntimeError("call load_state before running the solver")

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
                    f"{t - 1} (particle {p})", quantity=name, substep=t - 1, particle=p)


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
