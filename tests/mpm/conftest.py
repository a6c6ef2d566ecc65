"""The solver tests' shared fixtures (their helpers: mpm_cases.py beside this file): a small ball
of particles and two float64 solvers on the 16^3 grid, built once per test module."""

import pytest

from mpm_cases import ball_state, cfg64, make


@pytest.fixture(scope="module")
def state():
    return ball_state()


@pytest.fixture(scope="module")
def solver3(state):
    """float64, T = 3, per-substep control, paper drag/smoothing, squared loss."""
    return make(cfg64(), state)


@pytest.fixture(scope="module")
def solver20():
    """float64, T = 20, paper defaults on the small grid (extremes, optimization)."""
    st = ball_state(perturb=False)
    return make(cfg64(substeps=20), st)
