"""The solver tests' shared fixtures (their helpers: mpm_cases.py beside this file): a small ball
of particles and two float64 solvers on the 16^3 grid, made once per test
module (solver3 once per worker: mpm_cases.module_solver)."""

import pytest

from mpm_cases import ball_state, cfg64, make, module_solver


@pytest.fixture(scope="module")
def state():
    return ball_state()


@pytest.fixture(scope="module")
def solver3(state):
    """float64, T = 3, per-substep control, paper drag/smoothing, squared loss (one solver for every
    module's solver3, reset and loaded again for each)."""
    return module_solver("solver3", cfg64(), state)


@pytest.fixture(scope="module")
def solver20():
    """float64, T = 20, paper defaults on the small grid (extremes, optimization)."""
    st = ball_state(perturb=False)
    return make(cfg64(substeps=20), st)
