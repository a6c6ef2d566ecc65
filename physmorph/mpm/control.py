"""The control field dFc (paper section 4: the per-particle actuation the optimiser steps) and
its in-place operations: zero, scale, mean, rebase, the line search's base copy and the
accepted frame's kept copy, without [Tc, N, 3, 3] NumPy copies. A mixin of MPMSolver.
"""

import os

import numpy as np
import taichi as ti

from physmorph.settings.mpm import MPMStateError


class ControlField:
    """dFc and its gradient: in-place kernels and the public control API."""

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
        """dFc_t <- (F + dFc_t) M - F for every slot t (physmorph.plasticity.step.rebase_control), in
        float64 as the NumPy formula, stored in the solver's precision."""
        for s, p in self.ctrl:
            Fp = ti.Matrix.zero(ti.f64, 3, 3)
            Mp = ti.Matrix.zero(ti.f64, 3, 3)
            for a, b in ti.static(ti.ndrange(3, 3)):
                Fp[a, b] = F[p, a, b]
                Mp[a, b] = M[p, a, b]
            self.ctrl[s, p] = ti.cast((Fp + ti.cast(self.ctrl[s, p], ti.f64)) @ Mp - Fp, self.dtype)

    def reset_control(self) -> None:
        """Zero dFc and the Adam moments (and the Adam step counter)."""
        self.ctrl.fill(0.0)
        self.ctrl_grad.fill(0.0)
        if self.adam_m is not None:
            self.adam_m.fill(0.0)
            self.adam_v.fill(0.0)
        self.adam.steps = 0
        self.current.stale()

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
        self.current.stale()

    def scale_control(self, factor: float) -> None:
        """dFc <- factor dFc, in place (the morph loop's leak and restart; no copy of the control)."""
        if not np.isfinite(factor):
            raise ValueError(f"factor must be finite, got {factor!r}")
        self._scale_ctrl(float(factor))
        self.current.stale()

    def control_mean(self) -> np.ndarray:  # [N, 3, 3]
        """mean_t dFc_t, float64 (no [Tc, N, 3, 3] copy of the control)."""
        out = np.empty((self.n, 3, 3))
        self._control_mean(out)
        return out

    def rebase_control(self, F: np.ndarray,  # [N, 3, 3]
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

    def control_gradient(self, native: bool = False) -> np.ndarray:  # [Tc, N, 3, 3]
        """The last backward's dFc gradient, float64 (native: in the solver's precision)."""
        g = self.ctrl_grad.to_numpy()
        return g if native else g.astype(np.float64)

    @ti.kernel
    def _slot_to_array(self, src: ti.template(), s: ti.i32, out: ti.types.ndarray()):
        for p in range(self.n):
            for a, b in ti.static(ti.ndrange(3, 3)):
                out[p, a, b] = src[s, p][a, b]

    @ti.kernel
    def _array_to_slot(self, dst: ti.template(), s: ti.i32, arr: ti.types.ndarray()):
        for p in range(self.n):
            for a, b in ti.static(ti.ndrange(3, 3)):
                dst[s, p][a, b] = arr[p, a, b]

    def _kept_names(self) -> tuple[str, ...]:
        return ("ctrl", "adam_m", "adam_v") if self.adam_m is not None else ("ctrl",)

    def keep_control(self, spill: str | os.PathLike | None = None) -> None:
        """Keep the control (and the Adam moments where Adam has run) for :meth:`restore_kept_control`,
        the settle phase's undo: in fields of their own (``spill`` None: on the device), or written to
        the file ``spill`` a slot at a time, so that on the CPU the kept copy does not stay resident
        (at 471K particles x 20 slots it is 340 MB, and the page cache holds the file instead)."""
        names = self._kept_names()
        if spill is None:
            if self._kept is None or isinstance(self._kept, (str, os.PathLike)):
                self._kept = {}
            for name in names:
                src = getattr(self, name)
                if name not in self._kept:
                    self._kept[name] = ti.types.matrix(3, 3, self.dtype).field(shape=src.shape)
                self._copy_slots(self._kept[name], src)
        else:
            slot = np.empty((self.n, 3, 3), dtype=self.np_dtype)
            with open(spill, "wb") as f:
                for name in names:
                    for s in range(self.cfg.n_control_slots):
                        self._slot_to_array(getattr(self, name), s, slot)
                        slot.tofile(f)
            self._kept = spill
        self._kept_adam_step = (int(self.adam.steps), self.adam_m is not None)

    def _restore_spilled(self, path, names: tuple[str, ...]) -> None:
        count = self.n * 9
        with open(path, "rb") as f:
            for name in names:
                for s in range(self.cfg.n_control_slots):
                    slot = np.fromfile(f, dtype=self.np_dtype, count=count)
                    if slot.size != count:
                        raise MPMStateError(f"{path}: the kept control ends early (slot {s} of {name})")
                    self._array_to_slot(getattr(self, name), s, slot.reshape(self.n, 3, 3))

    def restore_kept_control(self) -> None:
        """Put back what :meth:`keep_control` kept (moments Adam made since then: zero)."""
        if self._kept is None:
            raise MPMStateError("restore_kept_control before keep_control")
        step, had_moments = self._kept_adam_step
        names = ("ctrl", "adam_m", "adam_v") if had_moments and self.adam_m is not None else ("ctrl",)
        if isinstance(self._kept, dict):
            for name in names:
                self._copy_slots(getattr(self, name), self._kept[name])
        else:
            self._restore_spilled(self._kept, names)
        if self.adam_m is not None and not had_moments:
            self.adam_m.fill(0.0)
            self.adam_v.fill(0.0)
        self.adam.steps = step
        self.current.stale()

    def optimizer_state(self) -> dict:
        """dFc (in the solver's precision: exact), the Adam moments where Adam has run, and the
        step count: everything needed to resume the optimization."""
        out = {"control": self.ctrl.to_numpy(), "adam_step": int(self.adam.steps)}
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
        self.adam.steps = int(state["adam_step"])
        self.current.stale()
