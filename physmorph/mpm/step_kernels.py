"""The optimisers' steps on dFc as kernels (paper section 4, "Physics rollout": the control update):
the normalised gradient step with its step-volume projection and per-volume weights, and Adam's
update; steps acting on the model, the frame's start state and the control. The optimisers in
physmorph.mpm.optimiser drive them.
"""

import taichi as ti

from physmorph.base import taichi_runtime  # noqa: F401  (Taichi's fast class test, before the kernels below)
from .control import ControlField
from .model import MPMModel
from .trajectory import Trajectory


@ti.data_oriented
class ControlSteps:
    """Kernels of a step on dFc: direction, projection, norm, Adam."""

    def __init__(self, model: MPMModel, trajectory: Trajectory, control: ControlField):
        self.model, self.trajectory, self.control = model, trajectory, control
        self.dtype = model.dtype

    @ti.func
    def _step_direction(self, direction: ti.template(), s, p, volume_mode: ti.template(), start):
        """w_p d_sp (w the particle's step weight, 1 unless step_per_volume), less a share of its
        first-order change of volume (MPMConfig.step_volume; A = F_start + dFc with dFc the
        iteration's base control and F_start the F the step will act from: substep ``start`` of the
        stored rollout, 0 the frame's start, T its end where the step acts from the next frame
        (MPMConfig.frame_end), n = A^-T). volume_mode 1 ("particle"): the share beta
        (step_volume_share) of each particle's, d - beta (<d, n> / <n, n>) n."""
        d = direction[s, p] * self.model.step_weight[p]
        # volume_mode is a compile-time constant: the full step's kernels carry no 3x3 inverse
        if ti.static(volume_mode != 0):
            A = self.trajectory.F[start, p] + self.control.ctrl_base[s, p]
            n = A.inverse().transpose()
            d -= (ti.cast(self.control.step_volume_share[None], self.dtype) * (d * n).sum() / (n * n).sum()) * n
        return d

    @ti.kernel
    def normalized_step(self, direction: ti.template(), alpha: ti.f64, inv_rms: ti.f64, clip: ti.f64,
                         volume_mode: ti.template(), start: ti.i32):
        """dFc = base - alpha clip(d / rms(d), -clip, clip) (clip <= 0: unclipped), d the step's
        direction (_step_direction: the weighted gradient w g, less a share of its change of volume
        where asked): the normalised gradient step of DiffMPMLib3D's optimiser, in place (tests:
        the NumPy formula, test_mpm_optimiser)."""
        for s, p in self.control.ctrl:
            d = self._step_direction(direction, s, p, volume_mode, start) * ti.cast(inv_rms, self.dtype)
            if clip > 0:
                d = ti.math.clamp(d, -ti.cast(clip, self.dtype), ti.cast(clip, self.dtype))
            self.control.ctrl[s, p] = self.control.ctrl_base[s, p] - ti.cast(alpha, self.dtype) * d

    @ti.kernel
    def direction_norm_sq(self, direction: ti.template(), volume_mode: ti.template(), start: ti.i32):
        """norm_acc = sum_sp |d_sp|^2, d the step's direction (_step_direction)."""
        self.control.norm_acc[None] = 0.0
        for s, p in direction:
            d = self._step_direction(direction, s, p, volume_mode, start)
            self.control.norm_acc[None] += ti.cast((d * d).sum(), ti.f64)

    @ti.kernel
    def adam(self, lr_t: ti.f64):
        """Adam (Kingma & Ba) on dFc; lr_t already carries the bias corrections."""
        b1 = self.dtype(self.model.cfg.adam_beta1)
        b2 = self.dtype(self.model.cfg.adam_beta2)
        for s, p in self.control.ctrl:
            g = self.control.ctrl_grad[s, p]
            m = b1 * self.control.adam_m[s, p] + (1.0 - b1) * g
            v = b2 * self.control.adam_v[s, p] + (1.0 - b2) * g * g
            self.control.adam_m[s, p] = m
            self.control.adam_v[s, p] = v
            step = ti.Matrix.zero(self.dtype, 3, 3)
            for a, b in ti.static(ti.ndrange(3, 3)):
                step[a, b] = m[a, b] / (ti.sqrt(v[a, b]) + self.dtype(self._eps_hat))
            self.control.ctrl[s, p] = self.control.ctrl[s, p] - ti.cast(lr_t, self.dtype) * step

    @property
    def _eps_hat(self) -> float:
        # a compile-time constant of _adam: eps without the step-dependent factor (a tiny
        # difference from textbook Adam, whose eps is added after the bias correction)
        return self.model.cfg.adam_eps
