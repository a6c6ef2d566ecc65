"""The render injection's gain (paper section 3.3, eq. 3): gamma relative to the mass gradient."""

from __future__ import annotations

import numpy as np

from physmorph.mpm import MPMSolver


def calibrate_injection(solver: MPMSolver, gamma: float, g_F: np.ndarray | None, g_x: np.ndarray | None) -> float:
    """Scale c such that the injected adjoint's dFc gradient has norm gamma x the mass loss's.

    The paper injects gamma * dL_render/dF with gamma = 0.1 in its own code's loss units, which
    we do not share (our mass loss is in kg^2, our DT loss is per pixel and per image height).
    To make gamma mean the same thing at every resolution we calibrate once, at the first frame
    that has a render gradient: both adjoints are pulled back to dFc through the same rollout
    (backward is linear in the injected adjoint) and c = gamma |grad_mass| / |grad_inject|.
    The run then injects c * g for every later frame (c is stored in the run file).
    """
    solver.forward()
    solver.backward(None, None)
    g_mass = solver.control_gradient()
    # The injected part alone (a difference of the two would drown in float32 round-off).
    solver.backward(g_F, g_x, include_mass_loss=False)
    g_inj = solver.control_gradient()
    n_mass, n_inj = float(np.linalg.norm(g_mass)), float(np.linalg.norm(g_inj))
    if not (n_inj > 0 and np.isfinite(n_inj) and np.isfinite(n_mass)):
        return 0.0
    return gamma * n_mass / n_inj
