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

The split is warp.sim's: a static model (physmorph.mpm.model: constants, the particles' constants,
the target, the stencil), the state the substeps write (physmorph.mpm.trajectory), the control
(physmorph.mpm.control), the reverse sweep's adjoints (physmorph.mpm.adjoint), and steps that
act on them and hold nothing of their own: the transfers (physmorph.mpm.transfers), their
adjoints (physmorph.mpm.transfer_adjoints), the mass loss (physmorph.mpm.physics_loss) and the
control's steps (physmorph.mpm.step_kernels), driven by the optimisers (physmorph.mpm.optimiser).
MPMSolver assembles them for one frame and keeps the public API.
"""

import functools

import numpy as np

from physmorph.settings.mpm import MPMConfig, MPMConfigError, MPMDivergenceError
from physmorph.settings.solver_memory import bytes_per_particle_substep

from .adjoint import Adjoint
from .control import ControlField
from .currency import Currency
from .kept_control import KeptControl
from .model import MPMModel, checked_array
from .optimiser import Adam, NormalizedGD, calibration_gradients, combine_calibration, optimize_control
from .physics_loss import MassLoss
from .state import ParticleState
from .step_kernels import ControlSteps
from .trajectory import Trajectory
from .transfer_adjoints import TransferAdjoints
from .transfers import Transfers


def _delegated(part: str, method):
    """A solver method that calls ``method`` of its component ``part`` (the docstring is its)."""
    @functools.wraps(method)
    def call(self, *args, **kwargs):
        return method(getattr(self, part), *args, **kwargs)
    return call


class MPMSolver:
    """Differentiable MPM over one frame of T substeps, with the control field dFc and its optimisers (normalised GD, Adam).

    Built once per (config, particle count); ``load_state`` each frame. The model, state, control
    and adjoint are its parts; the steps (transfers and their adjoints, the mass loss, the
    control's steps) act on them; what the stored results belong to is ``self.current``
    (physmorph.mpm.currency). See physmorph/mpm/__init__.py for the design decisions.
    """

    def __init__(self, cfg: MPMConfig, n_particles: int):
        self.model = MPMModel(cfg, n_particles)
        self.n, self.grid = self.model.n, self.model.grid
        self.current = Currency()
        self.trajectory = Trajectory(self.model)
        self.control_field = ControlField(self.model, self.current)
        self.kept_control = KeptControl(self.control_field)
        self.adjoint = Adjoint(self.model)
        self.physics_loss = MassLoss(self.model, self.trajectory, self.adjoint, self.current)
        self.transfers = Transfers(self.model, self.trajectory, self.control_field)
        self.transfer_adjoints = TransferAdjoints(self.model, self.trajectory, self.control_field, self.adjoint,
                                                  unrolled=self.transfers.unrolled)
        self.control_steps = ControlSteps(self.model, self.trajectory, self.control_field)
        self.reset()

    @property
    def cfg(self) -> MPMConfig:
        return self.model.cfg

    def reset(self) -> None:
        """Back to a freshly built solver: no state or target loaded, dFc and the Adam moments
        zero. Every other field is written before it is read (load_state, set_target_grid_mass,
        forward, backward), so a reset solver computes what a new one would."""
        self.current.clear()
        self.grad_norm = float("nan")  # |dL/d(dFc)| of the last backward
        self.model.Fp = None
        self.adam, self.normalized_gd = Adam(self), NormalizedGD(self)
        self.kept_control.clear()
        self.physics_loss.reset()
        self.control_field.reset()

    def configure(self, cfg: MPMConfig) -> None:
        """Take cfg's driver settings (DRIVER_FIELDS: learning rate, optimiser, line search, ...)
        without compiling again; every other field must equal the built solver's."""
        if cfg.kernel_settings() != self.cfg.kernel_settings():
            changed = [k for (k, a), (_, b) in zip(cfg.kernel_settings(), self.cfg.kernel_settings()) if a != b]
            raise MPMConfigError(f"configure can only change driver settings; {', '.join(changed)} "
                                 "would need a new solver (its kernels bake them in)")
        self.model.cfg = cfg

    def load_state(self, state: ParticleState) -> None:
        """Set the frame's initial state (x, v, F, C at t = 0 and the constants Fp, m, V0)."""
        st = state.validated()
        self.model.load_constants(st)
        self.trajectory.load(st)
        self.physics_loss.load_frame(st)
        self.current.loaded = True
        self.current.stale()

    def forward(self) -> float:
        """T substeps from the loaded state with the current dFc; returns the mass loss (or nan
        without a target). Raises MPMDivergenceError if the state became non-finite."""
        self._require_loaded()
        self.current.new_rollout()
        step = self.transfers
        atomic = not self.model.lanes.private  # P2G adds into the grid itself (a GPU)
        for t in range(self.cfg.substeps):
            if atomic:
                step.clear_grid()
            step.run_p2g(t)
            step.grid_update(t)
            step.g2p(t)
        self.current.stale()
        self.trajectory.check_finite()
        self.current.trajectory_current = True
        if not self.current.has_target:
            return self.physics_loss.no_target()
        step.clear_grid()
        return self.physics_loss.evaluate()

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
        self.adjoint.ensure_pair()
        self._reverse(grad_F_final, grad_x_final, include_mass_loss=False, pair=True)
        control = self.control_field
        control.norm_sq(control.ctrl_base)
        n_mass = float(control.norm_acc[None])
        if not np.isfinite(n_mass):
            raise MPMDivergenceError("the mass loss's dFc gradient became non-finite (NaN/Inf) in the backward pass",
                                      quantity="mass loss's dFc gradient")
        return float(np.sqrt(n_mass)), self.grad_norm

    def _reverse(self, grad_F_final, grad_x_final, include_mass_loss: bool, pair: bool) -> None:
        """The reverse sweep: the injected adjoints (and the mass loss unless excluded) in the
        first adjoint set into ctrl_grad; with pair, the mass loss alone in the second into
        ctrl_base."""
        if not self.current.trajectory_current:
            raise RuntimeError("backward needs a forward() of the current state and dFc first")
        self.current.gradients_overwritten()  # ctrl_grad is overwritten
        N, d = self.n, self.model.np_dtype
        gx = np.zeros((N, 3)) if grad_x_final is None else checked_array(grad_x_final, (N, 3), "grad_x_final")
        gF = np.zeros((N, 3, 3)) if grad_F_final is None else checked_array(grad_F_final, (N, 3, 3), "grad_F_final")
        adjoint, control, step = self.adjoint, self.control_field, self.transfer_adjoints
        adjoint.seed(gx.astype(d), gF.astype(d), pair)
        control.zero(control.ctrl_grad)
        if pair:
            control.zero(control.ctrl_base)
        if self.current.has_target and (include_mass_loss or pair):
            self.transfers.clear_grid()
            xa, Fa = (adjoint.x_adj2, adjoint.F_adj2) if pair else (adjoint.x_adj, adjoint.F_adj)
            self.physics_loss.backward(xa, Fa)
        for t in reversed(range(self.cfg.substeps)):
            step.restore_grid(t, self.transfers)
            if not self.model.lanes.private:  # G2P's reverse adds into grid_v_adj itself (a GPU)
                step.clear_grid_adjoint(pair)
            step.g2p_backward(t, pair)
            step.grid_backward(pair)
            step.p2g_backward(t, pair)
        control.gradient_norm_sq()
        gn = float(control.norm_acc[None])
        if not np.isfinite(gn):
            raise MPMDivergenceError("the dFc gradient became non-finite (NaN/Inf) in the backward pass",
                                      quantity="dFc gradient")
        self.grad_norm = float(np.sqrt(gn))

    optimize_control = optimize_control
    calibration_gradients = calibration_gradients
    combine_calibration = combine_calibration

    def adam_step(self, learning_rate: float | None = None) -> None:
        """One Adam step on dFc with the gradient of the last backward (step cfg.step_size unless given)."""
        self.adam.step(learning_rate)

    def rollout(self) -> ParticleState:
        """Forward with the current dFc and return the state at t = T (the forward is skipped
        when the stored trajectory already belongs to the current state, dFc and target, e.g.
        right after optimize_control)."""
        if not self.current.trajectory_current:
            self.forward()
        return self.state_at(self.cfg.substeps)

    def state_at(self, t: int) -> ParticleState:
        """Stored particle state at substep t (0..T) of the last forward, float64."""
        self._require_loaded()
        return self.trajectory.state_at(t)

    def initial_state_gradients(self) -> dict:
        """Adjoints of the initial x, v, C, F after backward(): {"x": [N,3], "v", "C", "F"}."""
        a = self.adjoint
        return {name: f.to_numpy().astype(np.float64)
                for name, f in (("x", a.x_adj), ("v", a.v_adj), ("C", a.C_adj), ("F", a.F_adj))}

    def end_loss(self) -> float:
        """The physics loss of the last forward's end state against the target set now (e.g. another
        one since), without running the substeps again; loss() and mass_loss() then report it."""
        self._require_loaded()
        if self.current.rollout == 0:
            raise RuntimeError("end_loss needs a forward first")
        self.transfers.clear_grid()
        return self.physics_loss.evaluate()

    def grid_mass(self) -> np.ndarray:  # [res, res, res]
        """Grid mass of x_T from the last forward (valid right after forward/rollout)."""
        self.transfers.clear_grid()
        self.physics_loss.splat.splat_mass(self.cfg.substeps)
        return self.trajectory.grid_m.to_numpy().astype(np.float64)

    def bytes_per_particle_substep(self) -> int:
        """Stored per particle per substep (physmorph.settings.solver_memory: x, v, C, F, the rotation's
        quaternion and pair sum)."""
        return bytes_per_particle_substep(self.cfg)

    def _require_loaded(self) -> None:
        if not self.current.loaded:
            raise RuntimeError("call load_state before running the solver")

    # the control's and the loss's operations, called on the solver
    reset_control = _delegated("control_field", ControlField.reset)
    control = _delegated("control_field", ControlField.values)
    set_control = _delegated("control_field", ControlField.set_values)
    scale_control = _delegated("control_field", ControlField.scale)
    control_mean = _delegated("control_field", ControlField.mean)
    rebase_control = _delegated("control_field", ControlField.rebase)
    control_gradient = _delegated("control_field", ControlField.gradient)
    keep_control = _delegated("kept_control", KeptControl.keep)
    restore_kept_control = _delegated("kept_control", KeptControl.restore)
    optimizer_state = _delegated("control_field", ControlField.optimizer_state)
    set_optimizer_state = _delegated("control_field", ControlField.set_optimizer_state)
    set_target_grid_mass = _delegated("physics_loss", MassLoss.set_target_grid_mass)
    set_overfill_weight = _delegated("physics_loss", MassLoss.set_overfill_weight)
    set_position_anchors = _delegated("physics_loss", MassLoss.set_position_anchors)
    loss = _delegated("physics_loss", MassLoss.loss)
    mass_loss = _delegated("physics_loss", MassLoss.mass_loss)

    @property
    def overfill_weight(self) -> float:
        """The packing term's weight in use (MPMConfig.overfill_weight unless set_overfill_weight)."""
        return self.physics_loss.overfill_weight


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
