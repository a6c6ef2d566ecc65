"""Tests of the differentiable MPM solver (physmorph.mpm): the config and state checks, and the stress model: P(Fe) against a torch reference, its hand-written differential against central differences, the energy density it derives from."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
import torch

from physmorph.base.grid import Grid, splat_mass
from physmorph.settings.mpm import CFLWarning, MPMConfig, MPMConfigError, MPMDivergenceError, MPMStateError
from physmorph.mpm.solver import MPMSolver, solver_for
from physmorph.mpm.state import ParticleState, elastic_energy, fixed_corotated_energy_density, total_volume
from physmorph.mpm import reference as ref
from physmorph.mpm.stress import evaluate_stress
from mpm_cases import (RES, autograd_check, ball_state, cfg64, fd_check, make, random_control,  # noqa: F401
                        stretched_target)


# ----------------------------------------------------------------------------- config, state
def test_config_rejects_bad_values_naming_them():
    for kw, word in [(dict(grid_res=4), "grid_res"), (dict(dt=-1.0), "dt"), (dict(substeps=0), "substeps"),
                     (dict(youngs_modulus=0.0), "youngs_modulus"), (dict(poisson_ratio=0.5), "poisson_ratio"),
                     (dict(density=-1.0), "density"), (dict(drag=1000.0), "drag"),
                     (dict(smoothing=1.0), "smoothing"), (dict(control="x"), "control"),
                     (dict(mass_loss="l1"), "mass_loss"), (dict(precision="float16"), "precision")]:
        with pytest.raises(MPMConfigError, match=word):
            MPMConfig(**kw)


def test_cfl_refuses_and_warns():
    cfg = MPMConfig()
    # the paper defaults are accepted, at ~76 % of the stable step (c dt / dx = 0.38)
    assert cfg.dt < cfg.stable_dt
    e_at_limit = cfg.density * (cfg.cfl * cfg.dx / cfg.dt) ** 2 * (1 + 0.2) * (1 - 0.4) / (1 - 0.2)
    with pytest.raises(MPMConfigError, match="dt=.*exceeds the stable step.*E="):
        MPMConfig(youngs_modulus=1.05 * e_at_limit)
    with pytest.warns(CFLWarning):
        MPMConfig(youngs_modulus=0.95 * e_at_limit)


def test_load_state_rejects_nan_and_out_of_domain(solver3, state):
    bad = state.copy()
    bad.F[4, 1, 1] = np.nan
    with pytest.raises(MPMStateError, match="F is not finite.*particle 4"):
        solver3.load_state(bad)
    bad = state.copy()
    bad.x[2, 0] = 15.9
    with pytest.raises(MPMStateError, match="x of particle 2"):
        solver3.load_state(bad)
    with pytest.raises(MPMStateError, match="particles"):
        solver3.load_state(ball_state(radius=2.0))
    solver3.load_state(state)


def test_energy_and_volume_helpers():
    st = ball_state(perturb=False)
    cfg = MPMConfig()
    assert elastic_energy(st, cfg) == pytest.approx(0.0, abs=1e-9)
    assert total_volume(st) == pytest.approx(st.volume.sum())
    st.F = st.F * 1.1  # uniform stretch: J = 1.331, R = I
    psi = cfg.mu * 3 * 0.1 ** 2 + 0.5 * cfg.lam * (1.331 - 1) ** 2
    assert elastic_energy(st, cfg) == pytest.approx(psi * st.volume.sum(), rel=1e-10)
    assert total_volume(st) == pytest.approx(1.331 * st.volume.sum())
    st.Fp = st.F.copy()  # plastic flow absorbs the stretch: no elastic energy
    assert elastic_energy(st, cfg) == pytest.approx(0.0, abs=1e-6)


# ----------------------------------------------------------------------------- stress
def _stress_inputs():
    rng = np.random.default_rng(7)
    F = np.eye(3) + 0.4 * rng.normal(size=(12, 3, 3))
    F[0] = np.diag([1.0, 1.0, 1e-4])  # near-singular
    F[1] = np.diag([1.2, 0.8, -0.5])  # inverted
    F[2] = np.diag([0.37, 0.37, 0.37])  # J -> 0.05
    F[3] = np.diag([3.0, 0.6, 0.2]) @ np.linalg.qr(rng.normal(size=(3, 3)))[0]
    F[4] = -F[4]  # inverted generic
    return F, rng.normal(size=(12, 3, 3))


def test_stress_matches_torch_reference():
    F, _ = _stress_inputs()
    mu, lam = 5.8e4, 3.9e4
    P, _ = evaluate_stress(F, np.zeros_like(F), mu, lam)
    P_ref = ref.stress_torch(torch.tensor(F), mu, lam).numpy()
    np.testing.assert_allclose(P, P_ref, rtol=1e-8, atol=1e-8 * mu)


def test_stress_differential_matches_central_fd():
    F, dF = _stress_inputs()
    mu, lam = 5.8e4, 3.9e4
    _, dP = evaluate_stress(F, dF, mu, lam)
    h = 1e-6
    Pp, _ = evaluate_stress(F + h * dF, dF, mu, lam)
    Pm, _ = evaluate_stress(F - h * dF, dF, mu, lam)
    fd = (Pp - Pm) / (2 * h)
    scale = np.abs(dP).max(axis=(1, 2), keepdims=True)
    assert (np.abs(fd - dP) / scale).max() < 1e-6
    # self-adjointness <dP[a], b> = <a, dP[b]> (dP is a Hessian action), used by the reverse pass
    b = np.random.default_rng(8).normal(size=F.shape)
    _, dPb = evaluate_stress(F, b, mu, lam)
    np.testing.assert_allclose((dP * b).sum(axis=(1, 2)), (dF * dPb).sum(axis=(1, 2)), rtol=1e-8,
                               atol=1e-10 * np.abs(dP).max())


def test_stress_is_the_gradient_of_the_energy_density():
    """P(Fe) = dPsi/dFe by central differences of the energy density the diagnostics use, on
    generic, compressed (J ~ 0.05) and stretched Fe; the paper's pressure lam (1 - J) J falls
    under compression past J = 1/2."""
    F, dF = _stress_inputs()
    keep = np.linalg.det(F) > 0
    F, dF = F[keep], dF[keep]
    F = np.concatenate([F, np.diag([0.3, 0.3, 0.3])[None] * np.array([[[1.0]], [[0.9]]])])
    dF = np.concatenate([dF, np.random.default_rng(9).normal(size=(2, 3, 3))])
    mu, lam = 5.8e4, 3.9e4
    P, _ = evaluate_stress(F, dF, mu, lam)
    h = 1e-6
    fd = (fixed_corotated_energy_density(F + h * dF, mu, lam)
          - fixed_corotated_energy_density(F - h * dF, mu, lam)) / (2 * h)
    np.testing.assert_allclose((P * dF).sum(axis=(1, 2)), fd, rtol=1e-6, atol=1e-9 * lam)
    J = np.array([0.2, 0.4, 0.6])
    Fj = J[:, None, None] ** (1 / 3) * np.eye(3)
    pressure = -(evaluate_stress(Fj, np.zeros_like(Fj), 0.0, lam)[0] @ Fj.transpose(0, 2, 1))[:, 0, 0]
    np.testing.assert_allclose(pressure, lam * (1 - J) * J, rtol=1e-10)
    assert pressure[0] < pressure[1]  # the paper's law: less resistance at J = 0.2 than 0.4


def test_stress_differential_finite_at_degenerate_singular_values():
    # equal singular values of an inverted F make s_i + s_j = 0: the guard keeps dP finite
    F = np.array([np.diag([1.0, 0.5, -0.5]), np.diag([1.0, 1.0, 1e-4]), np.zeros((3, 3))])
    dF = np.random.default_rng(0).normal(size=(3, 3, 3))
    P, dP = evaluate_stress(F, dF, 5.8e4, 3.9e4)
    assert np.isfinite(P).all() and np.isfinite(dP).all()
