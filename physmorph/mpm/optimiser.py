"""The optimisers of the control dFc (paper section 4, "Physics rollout": J iterations of forward,
mass loss, backward and a step on dFc per frame), as small objects acting on a solver's control.

NormalizedGD (the default, DiffMPMLib3D's): dFc <- dFc - alpha g / rms(g), alpha halved until the
objective decreases (MPMConfig.line_search_iters tries), with the step-volume projection and
per-volume weights of the step (physmorph.mpm.step_kernels). Adam (the paper's): bias-corrected moments warm-started across
frames. Both end with a forward of the updated dFc, so the solver's rollout() returns it.
"""

import numpy as np

from physmorph.settings.mpm import STEP_VOLUME_MODES, MPMDivergenceError


def frame_summary(loss_initial: float, loss_final: float, losses: list, grad_norm: float, iters: int,
                  **extra) -> dict:
    """What optimize_control returns: the losses, the last |g|, the accepted iterations and
    Delta E % = 100 (L_0 - L_J) / L_0."""
    return {"loss_initial": loss_initial, "loss_final": loss_final, "losses": losses, "grad_norm": grad_norm,
            "iters": iters, **extra,
            "delta_E_percent": 100.0 * (loss_initial - loss_final) / loss_initial if loss_initial > 0 else 0.0}


class Adam:
    """Adam on dFc; its moments are the solver's fields (allocated on first use), its step count here."""

    def __init__(self, solver):
        self.solver = solver
        self.steps = 0

    def step(self, learning_rate: float | None = None) -> None:
        """One Adam step on dFc with the gradient of the last backward (cfg.step_size unless given)."""
        s = self.solver
        self.steps += 1
        k = self.steps
        b1, b2 = s.cfg.adam_beta1, s.cfg.adam_beta2
        lr = s.cfg.step_size if learning_rate is None else learning_rate
        # folded bias correction: lr_t = lr sqrt(1 - b2^k) / (1 - b1^k), eps_hat = eps sqrt(1 - b2^k)
        lr_t = lr * np.sqrt(1.0 - b2 ** k) / (1.0 - b1 ** k)
        s._ensure_adam()
        s._adam(lr_t)
        s.current.stale()

    def run(self, grad_F_final, grad_x_final, iters: int, gradient_ready: bool, learning_rate: float) -> dict:
        """``iters`` x (forward, backward, step), then the forward of the updated dFc."""
        s = self.solver
        losses = []
        for j in range(iters):
            if j == 0 and gradient_ready:
                losses.append(s._last_loss)
            else:
                losses.append(s.forward())
                s.backward(grad_F_final, grad_x_final)
            self.step(learning_rate)
        loss_final = s.forward()
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
        J = s.forward() if run_forward or not s.current.trajectory_current else s._last_loss
        if grad_F_final is not None or grad_x_final is not None:
            x, _, F, _ = s._export_raw(s.cfg.substeps)
            if grad_F_final is not None:
                J += float((np.asarray(grad_F_final) * F).sum())
            if grad_x_final is not None:
                J += float((np.asarray(grad_x_final) * x).sum())
        return J

    def step_norm(self, volume_mode: int) -> float:
        """|d| of the step's direction (_step_direction: the weighted gradient, less a share of its
        change of volume where asked)."""
        s = self.solver
        if not (s._weighted_step or volume_mode):
            return s.grad_norm  # the backward's own |g|
        s._direction_norm_sq(s.ctrl_grad, volume_mode)
        return float(np.sqrt(s.norm_acc[None]))

    def run(self, grad_F_final, grad_x_final, iters: int, gradient_ready: bool, learning_rate: float) -> dict:
        """Per iteration dFc <- dFc - alpha g / rms(g), alpha starting at learning_rate and halved
        until the objective decreases (at most line_search_iters tries; else the step is undone
        and the frame's optimisation stops)."""
        s, cfg = self.solver, self.solver.cfg
        losses = []
        obj = self.objective(grad_F_final, grad_x_final, run_forward=not gradient_ready)
        loss_initial = s._last_loss
        alpha = learning_rate  # optimize_control resolved it (cfg.learning_rate unless given)
        accepted = 0
        volume_mode = STEP_VOLUME_MODES.index(cfg.step_volume)
        for j in range(iters):
            losses.append(s._last_loss)
            if not (j == 0 and gradient_ready):
                s.backward(grad_F_final, grad_x_final)
            # the norm was accumulated in float64 by the kernel; the step is taken in place
            # (_normalized_step), from the control saved at the iteration's start (saved first:
            # the step's change of volume is taken at the iteration's control)
            s._save_ctrl_base()
            s.step_volume_share[None] = cfg.step_volume_share
            rms = self.step_norm(volume_mode) / np.sqrt(cfg.n_control_slots * s.n * 9)
            if not rms > 0:
                break
            found, obj, alpha = self.line_search(grad_F_final, grad_x_final, volume_mode, obj, alpha, rms)
            if not found:
                s._restore_ctrl_base()
                s.current.stale()
                s.forward()
                break
            accepted += 1
        if not s.current.trajectory_current:
            s.forward()
        self.last_step = alpha
        return frame_summary(loss_initial, s._last_loss, losses, s.grad_norm, accepted, step=alpha)

    def line_search(self, grad_F_final, grad_x_final, volume_mode: int, obj: float, alpha: float,
                    rms: float) -> tuple[bool, float, float]:
        """Steps of length alpha, halved until the objective falls below obj: (found, objective, alpha)."""
        s, cfg = self.solver, self.solver.cfg
        for _ in range(cfg.line_search_iters):
            s._normalized_step(s.ctrl_grad, alpha, 1.0 / rms, cfg.step_clip, volume_mode)
            s.current.stale()
            try:
                trial = self.objective(grad_F_final, grad_x_final)
            except MPMDivergenceError:  # a step so large the rollout blows up: shorten it
                trial = float("inf")
            if trial < obj:
                return True, trial, alpha
            alpha *= 0.5
        return False, obj, alpha
