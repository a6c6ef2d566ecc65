"""MPMSolver.end_loss: the last forward's end state judged against a target set since, without
running the substeps again (the morph loop's waypoint targets, physmorph.morph.waypoints)."""

from __future__ import annotations

import numpy as np
import pytest

from mpm_cases import stretched_target


def test_end_loss_equals_a_forward_against_the_new_target(solver3, state):
    """A forward against target A, then target B set: end_loss equals the loss (and mass loss) of a
    forward run against B from the start, and is not A's."""
    s, cfg = solver3, solver3.cfg
    s.reset()
    a = stretched_target(state, cfg, (1.15, 0.93, 0.93))
    b = stretched_target(state, cfg, (0.9, 1.1, 1.0))
    s.set_target_grid_mass(b)
    s.load_state(state)
    s.set_control(np.zeros((cfg.substeps, state.n, 3, 3)))
    against_b = s.forward()
    s.set_target_grid_mass(a)
    against_a = s.forward()
    assert against_a != pytest.approx(against_b, rel=1e-3)
    s.set_target_grid_mass(b)
    assert s.end_loss() == pytest.approx(against_b, rel=1e-12)
    assert s.mass_loss() == pytest.approx(against_b, rel=1e-12) and s.loss() == s.end_loss()


def test_end_loss_needs_a_forward(solver3, state):
    s = solver3
    s.reset()
    s.set_target_grid_mass(stretched_target(state, s.cfg))
    s.load_state(state)
    with pytest.raises(RuntimeError, match="forward first"):
        s.end_loss()
