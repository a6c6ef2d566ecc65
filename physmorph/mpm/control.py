"""The control field dFc (paper section 4: the per-particle actuation the optimiser steps, one
slot per substep) with its gradient, the line search's base copy, Adam's moments and the
its in-place operations: zero, scale, mean, rebase, copy, without [Tc, N, 3, 3] NumPy copies
(the accepted frame's kept copy: physmorph.mpm.kept_control).
"""

import numpy as np
import taichi as ti

from physmorph.base import taichi_runtime  # noqa: F401  (Taichi's fast class test, before the kernels below)
from physmorph.records.runfile import ArrayBySlots
from physmorph.settings.mpm import MPMStateError

from .currency import Currency
from .model import MPMModel


@ti.data_oriented
class ControlField:
    """dFc [Tc, N], its gradient and the optimiser's state; ``current`` is the solver's record of
    what its stored results belong to (every change of dFc makes the stored rollout stale)."""

    def __init__(self, model: MPMModel, current: Currency):
        self.model, self.current = model, current
        self.n, self.dtype, self.np_dtype = model.n, model.dtype, model.np_dtype
        mat = ti.types.matrix(3, 3, model.dtype)
        shape = (model.cfg.n_control_slots, model.n)
        self.ctrl = mat.field(shape=shape)
        self.ctrl_grad = mat.field(shape=shape)
        # the line search's starting control: the trial steps are taken from it in place, so a
        # trial costs no NumPy copy of the [Tc, N, 3, 3] control (0.34 GB each at 471K x 20 slots).
        # Before the line search it holds the injection calibration's mass gradient
        # (calibration_gradients), which the first iteration's gradient is combined from.
        self.ctrl_base = mat.field(shape=shape)
        # Adam's moments are allocated at Adam's first use (ensure_adam): the default optimiser
        # (normalised GD) has none, which at 471K particles x 20 slots saves 0.7 GB and their checkpoint
        self.adam_m = None
        self.adam_v = None
        self.adam_steps = 0  # Adam's step count (its bias correction)
        self.step_volume_share = ti.field(ti.f64, shape=())  # MPMConfig.step_volume_share, set per step
        self.norm_acc = ti.field(ti.f64, shape=())

    def ensure_adam(self) -> None:
        """Allocate Adam's moments (zero) on first use."""
        if self.adam_m is None:
            mat = ti.types.matrix(3, 3, self.dtype)
            shape = (self.model.cfg.n_control_slots, self.n)
            self.adam_m = mat.field(shape=shape)
            self.adam_v = mat.field(shape=shape)
            self.adam_m.fill(0.0)
            self.adam_v.fill(0.0)

    @ti.kernel
    def zero(self, g: ti.template()):
        for s, p in g:
            g[s, p] = ti.Matrix.zero(self.dtype, 3, 3)

    @ti.kernel
    def norm_sq(self, g: ti.template()):
        self.norm_acc[None] = 0.0
        for s, p in g:
            self.norm_acc[None] += ti.cast((g[s, p] * g[s, p]).sum(), ti.f64)

    def gradient_norm_sq(self) -> None:
        self.norm_sq(self.ctrl_grad)

    @ti.kernel
    def _scale_ctrl(self, factor: ti.f64):
        for s, p in self.ctrl:
            self.ctrl[s, p] = ti.cast(factor, self.dtype) * self.ctrl[s, p]

    @ti.kernel
    def save_base(self):
        for s, p in self.ctrl:
            self.ctrl_base[s, p] = self.ctrl[s, p]

    @ti.kernel
    def restore_base(self):
        for s, p in self.ctrl:
            self.ctrl[s, p] = self.ctrl_base[s, p]

    @ti.kernel
    def copy_gradient_to_base(self):
        for s, p in self.ctrl_grad:
            self.ctrl_base[s, p] = self.ctrl_grad[s, p]

    @ti.kernel
    def combine_gradients(self, scale: ti.f64):
        """g = g_mass + scale g_inj: ctrl_base holds g_mass, ctrl_grad g_inj (calibration_gradients)."""
        for s, p in self.ctrl_grad:
            self.ctrl_grad[s, p] = self.ctrl_base[s, p] + ti.cast(scale, self.dtype) * self.ctrl_grad[s, p]

    @ti.kernel
    def _control_mean(self, out: ti.types.ndarray()):
        """out_p = (1 / Tc) sum_t dFc_t,p, in float64."""
        for p in range(self.n):
            acc = ti.Matrix.zero(ti.f64, 3, 3)
            for s in range(ti.static(self.model.cfg.n_control_slots)):
                acc += ti.cast(self.ctrl[s, p], ti.f64)
            for a, b in ti.static(ti.ndrange(3, 3)):
                out[p, a, b] = acc[a, b] / ti.static(self.model.cfg.n_control_slots)

    @ti.kernel
    def _rebase_ctrl(self, F: ti.types.ndarray(), M: ti.types.ndarray()):
        """dFc_t <- (F + dFc_t) M - F for every slot t (physmorph.plasticity.step.rebase_control), in
        float64 as the NumPy formula, stored in the solver's precision."""
        for s, p in self.ctrl:
            Fp = ti.Matrix.zero(ti.f64, 3, 3)
            Mp = ti.Matrix.zero(ti.f64, 3, 3)
            for a, b in ti.static(ti.ndrange(3, 3)):
                Fp[a, b] = F[p, a, b]
                Mp[a, b] = M[p, a, b]
            self.ctrl[s, p] = ti.cast((Fp + ti.cast(self.ctrl[s, p], ti.f64)) @ Mp - Fp, self.dtype)

    def reset(self) -> None:
        """Zero dFc and the Adam moments (and the Adam step counter)."""
        self.ctrl.fill(0.0)
        self.ctrl_grad.fill(0.0)
        if self.adam_m is not None:
            self.adam_m.fill(0.0)
            self.adam_v.fill(0.0)
        self.adam_steps = 0
        self.current.stale()

    def values(self, native: bool = False) -> np.ndarray:  # [Tc, N, 3, 3]
        """dFc, float64 (native: in the solver's precision, no conversion)."""
        c = self.ctrl.to_numpy()
        return c if native else c.astype(np.float64)

    def set_values(self, dFc: np.ndarray) -> None:  # [Tc, N, 3, 3]
        dFc = np.asarray(dFc)
        if not np.issubdtype(dFc.dtype, np.floating):
            dFc = dFc.astype(np.float64)
        shape = (self.model.cfg.n_control_slots, self.n, 3, 3)
        if dFc.shape != shape or not np.isfinite(dFc).all():
            raise MPMStateError(f"dFc must be finite with shape {shape}, got {dFc.shape}")
        self.ctrl.from_numpy(np.ascontiguousarray(dFc, dtype=self.np_dtype))
        self.current.stale()

    def scale(self, factor: float) -> None:
        """dFc <- factor dFc, in place (the morph loop's leak and restart; no copy of the control)."""
        if not np.isfinite(factor):
            raise ValueError(f"factor must be finite, got {factor!r}")
        self._scale_ctrl(float(factor))
        self.current.stale()

    def mean(self) -> np.ndarray:  # [N, 3, 3]
        """mean_t dFc_t, float64 (no [Tc, N, 3, 3] copy of the control)."""
        out = np.empty((self.n, 3, 3))
        self._control_mean(out)
        return out

    def rebase(self, F: np.ndarray,  # [N, 3, 3]
                       M: np.ndarray) -> None:  # [N, 3, 3]
        """dFc_t <- (F + dFc_t) M - F for every slot, in place (physmorph.plasticity.step.rebase_control
        with M = Fp_old^-1 Fp_new; no [Tc, N, 3, 3] copy of the control)."""
        F = np.ascontiguousarray(F, dtype=np.float64)
        M = np.ascontiguousarray(M, dtype=np.float64)
        if F.shape != (self.n, 3, 3) or M.shape != (self.n, 3, 3):
            raise MPMStateError(f"F and M must have shape {(self.n, 3, 3)}, got {F.shape} and {M.shape}")
        if not (np.isfinite(F).all() and np.isfinite(M).all()):
            raise MPMStateError("F and M must be finite")
        self._rebase_ctrl(F, M)
        self.current.stale()

    def gradient(self, native: bool = False) -> np.ndarray:  # [Tc, N, 3, 3]
        """The last backward's dFc gradient, float64 (native: in the solver's precision)."""
        g = self.ctrl_grad.to_numpy()
        return g if native else g.astype(np.float64)

    @ti.kernel
    def slot_to_array(self, src: ti.template(), s: ti.i32, out: ti.types.ndarray()):
        """out = slot s of the [Tc, N] field src, [N, 3, 3]."""
        for p in range(self.n):
            for a, b in ti.static(ti.ndrange(3, 3)):
                out[p, a, b] = src[s, p][a, b]

    def _by_slots(self, field) -> ArrayBySlots:
        def slot(s: int) -> np.ndarray:  # [N, 3, 3]
            out = np.empty((self.n, 3, 3), dtype=self.np_dtype)
            self.slot_to_array(field, s, out)
            return out

        return ArrayBySlots((self.model.cfg.n_control_slots, self.n, 3, 3), np.dtype(self.np_dtype), slot)

    def optimizer_state(self, by_slots: bool = False) -> dict:
        """dFc (in the solver's precision: exact), the Adam moments where Adam has run, and the
        step count: everything needed to resume the optimization. ``by_slots``: the arrays as
        ArrayBySlots, which a checkpoint writes a slot at a time (no [Tc, N, 3, 3] copy in memory)."""
        names = ("ctrl", "adam_m", "adam_v") if self.adam_m is not None else ("ctrl",)
        arrays = {name: self._by_slots(getattr(self, name)) if by_slots else getattr(self, name).to_numpy()
                  for name in names}
        out = {"control": arrays.pop("ctrl"), "adam_step": int(self.adam_steps)}
        out.update(arrays)
        return out

    def set_optimizer_state(self, state: dict) -> None:
        """Restore what :meth:`optimizer_state` returned (moments absent: zero)."""
        self.set_values(state["control"])
        shape = (self.model.cfg.n_control_slots, self.n, 3, 3)
        has_moments = "adam_m" in state or "adam_v" in state
        if has_moments:
            for key in ("adam_m", "adam_v"):
                arr = np.asarray(state[key])
                if arr.shape != shape or not np.isfinite(arr).all():
                    raise MPMStateError(f"{key} must be finite with shape {shape}, got {arr.shape}")
            self.ensure_adam()
            self.adam_m.from_numpy(np.asarray(state["adam_m"]).astype(self.np_dtype, copy=False))
            self.adam_v.from_numpy(np.asarray(state["adam_v"]).astype(self.np_dtype, copy=False))
        elif self.adam_m is not None:
            self.adam_m.fill(0.0)
            self.adam_v.fill(0.0)
        self.adam_steps = int(state["adam_step"])
        self.current.stale()
