"""The physics loss's volume term (not in the paper: the "global volume penalty" its limits name as
future work; MPMConfig.volume_weight, 0 = off).

    L_vol = w u (V_T / V* - 1)^2,   V_T = sum_p V0_p det F_T,p,   V* = sum_p V0_p det Fp_p

V_T is the body's volume at the rollout's end, V* the loaded frame's rest volume (with
plasticity.volume "target" the plasticity has already moved it toward the target's), and u the
term's unit: the number of grid nodes the target fills (log mass loss) or sum_I m*_I^2 (squared),
so a body whose volume is off by a share delta pays what a target whose every node is off by that
share would. Its adjoint on the end state's F, d det F / dF = cof F:

    F_bar_T,p += 2 w u (V_T / V* - 1) / V* V0_p cof(F_T,p)
"""

import numpy as np
import taichi as ti

from physmorph.base import taichi_runtime  # noqa: F401  (Taichi's fast class test, before the kernels below)
from physmorph.base.linalg3 import det3

from .model import MPMModel
from .state import ParticleState
from .stress import cofactor
from .trajectory import Trajectory


@ti.data_oriented
class VolumeTerm:
    """The volume term of the physics loss: its rest volume and unit, set with the frame and the
    target, and the body's volume of the last evaluation."""

    def __init__(self, model: MPMModel, trajectory: Trajectory):
        self.model, self.trajectory = model, trajectory
        self.n, self.dtype = model.n, model.dtype
        self.volume_acc = ti.field(ti.f64, shape=())
        self.rest_volume = float("nan")  # V* of the loaded frame
        self.unit = 0.0  # u of the target
        self.ratio = float("nan")  # V_T / V* of the last evaluation

    @property
    def active(self) -> bool:
        """The term is on (a weight > 0) and has a target to be weighed against."""
        return self.model.cfg.volume_weight > 0 and self.unit > 0

    def set_rest_volume(self, st: ParticleState) -> None:
        """V* = sum_p V0_p det Fp_p of the frame being loaded."""
        self.rest_volume = float((st.volume * det3(st.Fp)).sum())

    def set_unit(self, target_m: np.ndarray) -> None:  # [res, res, res]
        """u of the target grid mass: the nodes it fills (log form) or the sum of their squares (squared)."""
        filled = target_m[target_m > 0]
        self.unit = float(filled.size if self.model.cfg.mass_loss == "log" else (filled ** 2).sum())

    @ti.kernel
    def _sum_volume(self):
        """volume_acc = sum_p V0_p det F_T,p (accumulated in float64)."""
        T = self.model.cfg.substeps
        self.volume_acc[None] = 0.0
        for p in range(self.n):
            self.volume_acc[None] += ti.cast(self.model.vol[p] * self.trajectory.F[T, p].determinant(), ti.f64)

    def _measure(self) -> float:
        """V_T / V* of the stored end state (kept as ``ratio``)."""
        self._sum_volume()
        self.ratio = float(self.volume_acc[None]) / self.rest_volume
        return self.ratio

    def loss(self) -> float:
        """w u (V_T / V* - 1)^2 of the stored end state."""
        return self.model.cfg.volume_weight * self.unit * (self._measure() - 1.0) ** 2

    @ti.kernel
    def _add_adjoint(self, Fa: ti.template(), c: ti.f64):
        """F_bar_T,p += c V0_p cof(F_T,p)."""
        T = self.model.cfg.substeps
        for p in range(self.n):
            Fa[p] += ti.cast(c, self.dtype) * self.model.vol[p] * cofactor(self.trajectory.F[T, p])

    def backward(self, Fa) -> None:
        """The term's adjoint into the F adjoint set ``Fa``."""
        c = 2.0 * self.model.cfg.volume_weight * self.unit * (self._measure() - 1.0) / self.rest_volume
        self._add_adjoint(Fa, c)
