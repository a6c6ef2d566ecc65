"""The render injection's gain (paper section 3.3, eq. 3): gamma relative to the mass gradient."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from physmorph.mpm.solver import MPMSolver


@dataclass(frozen=True)
class InjectionCalibration:
    """The gain c and the norms of the two dFc gradients it was measured from (one rollout, one
    state); the gradients themselves stay in the solver (MPMSolver.calibration_gradients)."""

    scale: float
    mass_gradient_norm: float  # |d(mass loss)/d(dFc)|
    injected_gradient_norm: float  # |d<g, final state>/d(dFc)| of the unscaled adjoint


def calibrate_injection(solver: MPMSolver, gamma: float, g_F: np.ndarray | None,
                        g_x: np.ndarray | None, pair: bool | None = None) -> InjectionCalibration:
    """Scale c such that the injected adjoint's dFc gradient has norm gamma x the mass loss's.

    The paper injects gamma * dL_render/dF with gamma = 0.1 in its own code's loss units, which
    we do not share (our mass loss is in kg^2, our DT loss is per pixel and per image height).
    To make gamma mean the same thing at every resolution both adjoints are pulled back to dFc
    through the same rollout (backward is linear in the injected adjoint) and c = gamma
    |grad_mass| / |grad_inject|. The solver keeps the two gradients: the optimiser's first
    iteration needs exactly mass + c x injected on the rollout this leaves current
    (MPMSolver.combine_calibration, then optimize_control(gradient_ready=True)). pair: see
    MPMSolver.calibration_gradients (by default chosen by the solver's size).
    """
    n_mass, n_inj = solver.calibration_gradients(g_F, g_x, pair)
    ok = n_inj > 0 and np.isfinite(n_inj) and np.isfinite(n_mass)
    return InjectionCalibration(gamma * n_mass / n_inj if ok else 0.0, n_mass, n_inj)
