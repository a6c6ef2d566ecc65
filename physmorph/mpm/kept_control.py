"""The accepted frame's kept copy of the control (the settle phase's undo: MorphConfig.settle):
dFc and, where Adam has run, its moments and step count, kept in fields of their own or spilled
to a file a slot at a time, and put back, without [Tc, N, 3, 3] NumPy copies.
"""

import os

import numpy as np
import taichi as ti

from physmorph.base import taichi_runtime  # noqa: F401  (Taichi's fast class test, before the kernels below)
from physmorph.settings.mpm import MPMStateError

from .control import ControlField


@ti.data_oriented
class KeptControl:
    """A copy of a ControlField's dFc (and Adam's state) to restore."""

    def __init__(self, control: ControlField):
        self.control = control
        self.n, self.dtype, self.np_dtype = control.n, control.dtype, control.np_dtype
        self.clear()

    def clear(self) -> None:
        """Nothing kept."""
        self.kept = None  # keep: its fields (allocated on first use) or its file
        self.adam_step = (0, False)

    @ti.kernel
    def _copy_slots(self, dst: ti.template(), src: ti.template()):
        for s, p in src:
            dst[s, p] = src[s, p]

    @ti.kernel
    def _array_to_slot(self, dst: ti.template(), s: ti.i32, arr: ti.types.ndarray()):
        for p in range(self.n):
            for a, b in ti.static(ti.ndrange(3, 3)):
                dst[s, p][a, b] = arr[p, a, b]

    def _names(self) -> tuple[str, ...]:
        return ("ctrl", "adam_m", "adam_v") if self.control.adam_m is not None else ("ctrl",)

    def keep(self, spill: str | os.PathLike | None = None) -> None:
        """Keep the control (and the Adam moments where Adam has run) for :meth:`restore`,
        the settle phase's undo: in fields of their own (``spill`` None: on the device), or written to
        the file ``spill`` a slot at a time, so that on the CPU the kept copy does not stay resident
        (at 471K particles x 20 slots it is 340 MB, and the page cache holds the file instead)."""
        names = self._names()
        if spill is None:
            if self.kept is None or isinstance(self.kept, (str, os.PathLike)):
                self.kept = {}
            for name in names:
                src = getattr(self.control, name)
                if name not in self.kept:
                    self.kept[name] = ti.types.matrix(3, 3, self.dtype).field(shape=src.shape)
                self._copy_slots(self.kept[name], src)
        else:
            slot = np.empty((self.n, 3, 3), dtype=self.np_dtype)
            with open(spill, "wb") as f:
                for name in names:
                    for s in range(self.control.model.cfg.n_control_slots):
                        self.control.slot_to_array(getattr(self.control, name), s, slot)
                        slot.tofile(f)
            self.kept = spill
        self.adam_step = (int(self.control.adam_steps), self.control.adam_m is not None)

    def _restore_spilled(self, path, names: tuple[str, ...]) -> None:
        count = self.n * 9
        with open(path, "rb") as f:
            for name in names:
                for s in range(self.control.model.cfg.n_control_slots):
                    slot = np.fromfile(f, dtype=self.np_dtype, count=count)
                    if slot.size != count:
                        raise MPMStateError(f"{path}: the kept control ends early (slot {s} of {name})")
                    self._array_to_slot(getattr(self.control, name), s, slot.reshape(self.n, 3, 3))

    def restore(self) -> None:
        """Put back what :meth:`keep` kept (moments Adam made since then: zero)."""
        if self.kept is None:
            raise MPMStateError("restore_kept_control before keep_control")
        step, had_moments = self.adam_step
        names = ("ctrl", "adam_m", "adam_v") if had_moments and self.control.adam_m is not None else ("ctrl",)
        if isinstance(self.kept, dict):
            for name in names:
                self._copy_slots(getattr(self.control, name), self.kept[name])
        else:
            self._restore_spilled(self.kept, names)
        if self.control.adam_m is not None and not had_moments:
            self.control.adam_m.fill(0.0)
            self.control.adam_v.fill(0.0)
        self.control.adam_steps = step
        self.control.current.stale()
