"""The render injection's gain (paper section 3.3, eq. 3): gamma relative to the mass gradient."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from physmorph.mpm import MPMSolver


@dataclass(frozen=True)
class InjectionCalibration:
    """The gain c and the two dFc gradients it was measured from (one rollout, one state)."""

    scale: float
    mass_gradient: np.ndarray  # [Tc, N, 3, 3] d(mass loss)/d(dFc)
    injected_gradient: np.ndarray  # [Tc, N, 3, 3] d<g, final state>/d(dFc) of the unscaled adjoint

    def objective_gradient(self, scale: float) -> np.ndarray:  # [Tc, N, 3, 3]
        """d(mass loss + scale <g, final state>)/d(dFc): the backward is linear in the injected
        adjoint, so this is what a backward with the scaled adjoint returns (up to round-off)."""
        return self.mass_gradient + scale * self.injected_gradient


def calibrate_injection(solver: MPMSolver, gamma: float, g_F: np.ndarray | None,
                        g_x: np.ndarray | None) -> InjectionCalibration:
    """Scale c such that the injected adjoint's dFc gradient has norm gamma x the mass loss's.

    The paper injects gamma * dL_render/dF with gamma = 0.1 in its own code's loss units, which
    we do not share (our mass loss is in kg^2, our DT loss is per pixel and per image height).
    To make gamma mean the same thing at every resolution both adjoints are pulled back to dFc
    through the same rollout (backward is linear in the injected adjoint) and c = gamma
    |grad_mass| / |grad_inject|. The two gradients are returned too: the optimiser's first
    iteration needs exactly their sum, on the rollout this leaves current.
    """
    solver.forward()
    solver.backward(None, None)
    # in the solver's precision (the norms are the solver's, accumulated in float64)
    g_mass, n_mass = solver.control_gradient(native=True), solver.grad_norm
    # The injected part alone (a difference of the two would drown in float32 round-off).
    solver.backward(g_F, g_x, include_mass_loss=False)
    g_inj, n_inj = solver.control_gradient(native=True), solver.grad_norm
    ok = n_inj > 0 and np.isfinite(n_inj) and np.isfinite(n_mass)
    return InjectionCalibration(gamma * n_mass / n_inj if ok else 0.0, g_mass, g_inj)
