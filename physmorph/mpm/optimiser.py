"""The optimisers of the control dFc (paper section 4, "Physics rollout": J iterations of forward,
mass loss, backward and a step on dFc per frame), as small objects acting on a solver's control.

NormalizedGD (the default, DiffMPMLib3D's): dFc <- dFc - alpha g / rms(g), alpha halved until the
objective decreases (MPMConfig.line_search_iters tries), with the step-volume projection and
per-volume weights of the step (physmorph.mpm.step_kernels). Adam (the paper's): bias-corrected moments warm-started across
frames. Both end with a forward of the updated dFc, so the solver's rollout() returns it; with
MPMConfig.frame_end "last_forward" the last iteration's step is taken without that forward (nor
the line search's trial), the stored trajectory stays the one its gradient was taken on, and
state_at(T) returns that rollout's end (the frame's state, as Algorithm 1 promotes it).
"""

import numpy as np

from physmorph.settings.mpm import STEP_VOLUME_MODES, MPMDivergenceError
from physmorph.settings.solver_memory import PAIR_MIN_PARTICLE_STEPS


def frame_summary(loss_initial: float, loss_final: float, losses: list, grad_norm: float, iters: int,
                  **extra) -> dict:
    """What optimize_control returns: the losses, the last |g|, the accepted iterations and
    Delta E % = 100 (L_0 - L_J) / L_0."""
    return {"loss_initial": loss_initial, "loss_final": loss_final, "losses": losses, "grad_norm": grad_norm,
            "iters": iters, **extra,
            "delta_E_percent": 100.0 * (loss_initial - loss_final) / loss_initial if loss_initial > 0 else 0.0}


class Adam:
    """Adam on dFc; its moments and step count are the control's (allocated on first use)."""

    def __init__(self, solver):
        self.solver = solver

    def step(self, learning_rate: float | None = None) -> None:
        """One Adam step on dFc with the gradient of the last backward (cfg.step_size unless given)."""
        s = self.solver
        s.control_field.adam_steps += 1
        k = s.control_field.adam_steps
        b1, b2 = s.cfg.adam_beta1, s.cfg.adam_beta2
        lr = s.cfg.step_size if learning_rate is None else learning_rate
        # folded bias correction: lr_t = lr sqrt(1 - b2^k) / (1 - b1^k), eps_hat = eps sqrt(1 - b2^k)
        lr_t = lr * np.sqrt(1.0 - b2 ** k) / (1.0 - b1 ** k)
        s.control_field.ensure_adam()
        s.control_steps.adam(lr_t)
        s.current.stale()

    def run(self, grad_F_final, grad_x_final, iters: int, gradient_ready: bool, learning_rate: float) -> dict:
        """``iters`` x (forward, backward, step), then the forward of the updated dFc."""
        s = self.solver
        losses = []
        for j in range(iters):
            if j == 0 and gradient_ready:
                losses.append(s.physics_loss.last_loss)
            else:
                losses.append(s.forward())
                s.backward(grad_F_final, grad_x_final)
            self.step(learning_rate)
        loss_final = losses[-1] if s.cfg.frame_end == "last_forward" else s.forward()
        return frame_summary(losses[0], loss_final, losses, s.grad_norm, iters)


class NormalizedGD:
    """Normalised gradient descent with backtracking on dFc."""

    def __init__(self, solver):
        self.solver = solver
        self.last_step = None  # the step length alpha the last run ended with

    def objective(self, grad_F_final, grad_x_final, run_forward: bool = True) -> float:
        """Forward (unless the stored rollout is current and run_forward is False), then mass
        loss + <gF, F_T> + <gx, x_T> (what the backward differentiates)."""
        s = self.solver
        J = s.forward() if run_forward or not s.current.trajectory_current else s.physics_loss.last_loss
        if grad_F_final is not None or grad_x_final is not None:
            x, _, F, _ = s.trajectory.export_raw(s.cfg.substeps)
            if grad_F_final is not None:
                J += float((np.asarray(grad_F_final) * F).sum())
            if grad_x_final is not None:
                J += float((np.asarray(grad_x_final) * x).sum())
        return J

    def step_norm(self, volume_mode: int, start: int = 0) -> float:
        """|d| of the step's direction (ControlSteps._step_direction: the weighted gradient, less a share of its
        change of volume where asked, at substep ``start``'s F)."""
        s = self.solver
        if not (s.model.weighted_step or volume_mode):
            return s.grad_norm  # the backward's own |g|
        s.control_steps.direction_norm_sq(s.control_field.ctrl_grad, volume_mode, start)
        return float(np.sqrt(s.control_field.norm_acc[None]))

    def run(self, grad_F_final, grad_x_final, iters: int, gradient_ready: bool, learning_rate: float) -> dict:
        """Per iteration dFc <- dFc - alpha g / rms(g), alpha starting at learning_rate and halved
        until the objective decreases (at most line_search_iters tries; else the step is undone
        and the frame's optimisation stops)."""
        s, cfg = self.solver, self.solver.cfg
        losses = []
        obj = self.objective(grad_F_final, grad_x_final, run_forward=not gradient_ready)
        loss_initial = s.physics_loss.last_loss
        alpha = learning_rate  # optimize_control resolved it (cfg.learning_rate unless given)
        accepted = 0
        volume_mode = STEP_VOLUME_MODES.index(cfg.step_volume)
        for j in range(iters):
            losses.append(s.physics_loss.last_loss)
            if not (j == 0 and gradient_ready):
                s.backward(grad_F_final, grad_x_final)
            # the norm was accumulated in float64 by the kernel; the step is taken in place
            # (ControlSteps.normalized_step), from the control saved at the iteration's start (saved first:
            # the step's change of volume is taken at the iteration's control)
            s.control_field.save_base()
            s.control_field.step_volume_share[None] = cfg.step_volume_share
            # the last step with frame_end last_forward acts from the next frame, which starts at
            # this rollout's end: its change of volume is taken there
            untried = j == iters - 1 and cfg.frame_end == "last_forward"
            start = cfg.substeps if untried else 0
            rms = self.step_norm(volume_mode, start) / np.sqrt(cfg.n_control_slots * s.n * 9)
            if not rms > 0:
                break
            if untried:  # the step for the next frame: this frame ends where its rollout did
                s.control_steps.normalized_step(s.control_field.ctrl_grad, alpha, 1.0 / rms, cfg.step_clip, volume_mode,
                                                start)
                s.current.stale()
                self.last_step = alpha
                return frame_summary(loss_initial, s.physics_loss.last_loss, losses, s.grad_norm, accepted + 1,
                                     step=alpha)
            found, obj, alpha = self.line_search(grad_F_final, grad_x_final, volume_mode, obj, alpha, rms)
            if not found:
                s.control_field.restore_base()
                s.current.stale()
                s.forward()
                break
            accepted += 1
        if not s.current.trajectory_current:
            s.forward()
        self.last_step = alpha
        return frame_summary(loss_initial, s.physics_loss.last_loss, losses, s.grad_norm, accepted, step=alpha)

    def line_search(self, grad_F_final, grad_x_final, volume_mode: int, obj: float, alpha: float,
                    rms: float) -> tuple[bool, float, float]:
        """Steps of length alpha, halved until the objective falls below obj: (found, objective, alpha)."""
        s, cfg = self.solver, self.solver.cfg
        for _ in range(cfg.line_search_iters):
            s.control_steps.normalized_step(s.control_field.ctrl_grad, alpha, 1.0 / rms, cfg.step_clip, volume_mode, 0)
            s.current.stale()
            try:
                trial = self.objective(grad_F_final, grad_x_final)
            except MPMDivergenceError:  # a step so large the rollout blows up: shorten it
                trial = float("inf")
            if trial < obj:
                return True, trial, alpha
            alpha *= 0.5
        return False, obj, alpha


# The frame-level entry points of the solver, its methods (MPMSolver.optimize_control, ...; the
# solver is their first argument): the optimisers and the injection calibration drive its steps.

def optimize_control(solver, grad_F_final: np.ndarray | None = None,  # [N, 3, 3]
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
    if not solver.current.has_target:
        raise RuntimeError("optimize_control needs set_target_grid_mass first")
    J = solver.cfg.grad_iters if iters is None else int(iters)
    if J < 1:
        raise ValueError(f"iters must be >= 1, got {J}")
    now = solver.current
    if gradient_ready and not (now.trajectory_current and now.combined_for == now.rollout):
        raise RuntimeError("gradient_ready needs calibration_gradients and combine_calibration on a "
                           "forward() of the current state and dFc")
    lr = solver.cfg.step_size if learning_rate is None else float(learning_rate)
    if not (np.isfinite(lr) and lr > 0):
        raise ValueError(f"learning_rate must be finite and > 0, got {learning_rate!r}")
    optimiser = solver.normalized_gd if solver.cfg.optimizer == "normalized_gd" else solver.adam
    return optimiser.run(grad_F_final, grad_x_final, J, gradient_ready, lr)


def calibration_gradients(solver, grad_F_final: np.ndarray | None = None,  # [N, 3, 3]
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
        pair = solver.n * solver.cfg.substeps >= PAIR_MIN_PARTICLE_STEPS
    solver.forward()
    if pair:
        n_mass, n_inj = solver.backward_pair(grad_F_final, grad_x_final)
    else:
        solver.backward(None, None)
        n_mass = solver.grad_norm
        solver.control_field.copy_gradient_to_base()
        solver.backward(grad_F_final, grad_x_final, include_mass_loss=False)
        n_inj = solver.grad_norm
    solver.current.calibrated_for = solver.current.rollout
    return n_mass, n_inj


def combine_calibration(solver, scale: float) -> None:
    """The dFc gradient of mass loss + scale <g, final state> from calibration_gradients' two
    (the backward is linear in the injected adjoint), in place, as the last backward's
    gradient: optimize_control(gradient_ready=True) starts from it."""
    if not (solver.current.trajectory_current and solver.current.calibrated_for == solver.current.rollout):
        raise RuntimeError("combine_calibration needs calibration_gradients on the current rollout")
    if not np.isfinite(scale):
        raise ValueError(f"scale must be finite, got {scale!r}")
    solver.control_field.combine_gradients(float(scale))
    solver.current.calibrated_for = -1  # the mass gradient's copy is consumed (the line search reuses its field)
    solver.current.combined_for = solver.current.rollout
    solver.control_field.gradient_norm_sq()
    solver.grad_norm = float(np.sqrt(solver.control_field.norm_acc[None]))
