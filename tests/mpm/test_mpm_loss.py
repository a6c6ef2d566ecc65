"""Tests of the differentiable MPM solver (physmorph.mpm): the physics loss: its terms (blurred level, position anchors, overfill) against their formulas, a reference and central differences."""

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
                        stretched_target, volume_term_parts)


def _loss_control_gradient_matches_autograd(s: MPMSolver, state: ParticleState, ctrl, target, eps: float,
                                            cfg: MPMConfig | None = None) -> None:
    """The solver's dFc gradient of its mass loss (with log eps) against torch autograd through the
    reference rollout and reference loss (of cfg, the solver's own by default)."""
    cfg = s.cfg if cfg is None else cfg
    s.load_state(state)
    s.set_control(ctrl)
    s.forward()
    s.backward()
    c = ref.as_torch(ctrl, True)
    states = ref.rollout_torch(ref.as_torch(state.x), ref.as_torch(state.v), ref.as_torch(state.C), ref.as_torch(state.F), c,
                               ref.as_torch(state.Fp), ref.as_torch(state.mass), ref.as_torch(state.volume), cfg)
    ref.mass_loss_torch(states[-1][0], ref.as_torch(state.mass), ref.as_torch(target), cfg, log_eps=eps).backward()
    np.testing.assert_allclose(s.control_gradient(), c.grad.numpy(), rtol=1e-6, atol=1e-8 * c.grad.abs().max().item())


def _loss_at_zero_control(s: MPMSolver, cfg: MPMConfig, state: ParticleState):
    """The solver's loss with dFc = 0, the reference grid masses it compares (end state, target)
    and eps in mass units."""
    s.set_control(np.zeros((cfg.substeps, state.n, 3, 3)))
    L = s.forward()
    end = s.state_at(cfg.substeps)
    return L, splat_mass(end.x, end.mass, s.grid), s.model.target_m.to_numpy(), cfg.log_mass_eps * state.mass.mean()


def _a_term_of_the_physics_loss(s: MPMSolver, state: ParticleState, L: float, plain: float, seed: int) -> None:
    """A term added to the loss L (plain without it) is the physics loss's: loss() reports it whole
    and mass_loss() without (the run's physics_loss and mass_loss), the gradients of control and
    initial state match central finite differences, and backward_pair's mass-loss gradient
    carries it (it belongs to the physics objective, not to the injected adjoints)."""
    assert s.loss() == L and s.mass_loss() == pytest.approx(plain, rel=1e-12)
    fd_check(s, state, n_checks=6, seed=seed)
    s.forward()
    s.backward()
    whole = s.control_gradient()
    s.forward()
    n_mass, n_inj = s.backward_pair(None, None)
    assert n_mass == pytest.approx(np.linalg.norm(whole), rel=1e-10) and n_inj == 0.0


def test_blurred_mass_loss_level_matches_a_dense_convolution_and_fd(state):
    """mass_loss_blur sigma > 0 adds weight x sum_I (log((B m)_I + e) - log((B m*)_I + e))^2, B the
    Gaussian blur truncated at 3 sigma, zero outside the grid: the loss against the formula with B
    as one dense 3D convolution (scipy, not the solver's separable passes), and the control gradient
    against central finite differences and torch autograd (the reference's conv3d). Slow: it
    compiles a solver of its own settings (the blurred level's kernels) and runs some 30 rollouts
    for the finite differences."""
    from scipy.ndimage import convolve

    cfg = cfg64(substeps=2, mass_loss="log", mass_loss_blur=1.2, mass_loss_blur_weight=2.0)
    s = make(cfg, state)
    L, m, t, eps = _loss_at_zero_control(s, cfg, state)
    r = int(np.ceil(3 * 1.2))
    k = np.exp(-np.arange(-r, r + 1) ** 2 / (2 * 1.2 ** 2))
    kernel = np.einsum("i,j,k->ijk", k, k, k) / k.sum() ** 3
    Bm, Bt = (convolve(a, kernel, mode="constant", cval=0.0) for a in (m, t))
    grid_level = ((np.log(m + eps) - np.log(t + eps)) ** 2).sum()
    blurred = ((np.log(Bm + eps) - np.log(Bt + eps)) ** 2).sum()
    assert blurred > 0.05 * grid_level  # the level is not negligible in the test's ball
    assert L == pytest.approx(grid_level + 2.0 * blurred, rel=1e-10)
    ctrl = random_control(cfg, state.n)
    s.set_control(ctrl)
    fd_check(s, state, n_checks=6, seed=5)
    _loss_control_gradient_matches_autograd(s, state, ctrl, t, eps)
    for bad in ({"mass_loss_blur": -1.0}, {"mass_loss_blur": 17.0}, {"mass_loss_blur_weight": -1.0}):
        with pytest.raises(MPMConfigError, match="mass_loss_blur"):
            cfg64(**bad)


def test_position_anchors_add_their_term_and_match_fd(state):
    """set_position_anchors(a, w) adds sum_p w_p |x_T,p - a_p|^2 to the loss (the morph loop's stray
    pull): the loss is the plain one plus that sum at the rollout's end, the gradients of control and
    initial state match central finite differences, backward_pair's mass-loss gradient carries the
    term (it belongs to the physics objective, not to the injected adjoints), mass_loss() reports
    the loss without it, and None removes it. Slow: it compiles a solver of its own settings (the
    anchors' kernels) and runs some 30 rollouts for the finite differences."""
    cfg = cfg64(substeps=2, mass_loss="log")
    s = make(cfg, state, reuse=True)
    s.set_control(random_control(cfg, state.n))
    plain = s.forward()
    rng = np.random.default_rng(4)
    anchor = state.x + rng.normal(0.0, 0.3, state.x.shape)
    weight = np.where(rng.random(state.n) < 0.5, 0.0, rng.uniform(0.5, 2.0, state.n))
    s.set_position_anchors(anchor, weight)
    L = s.forward()
    end = s.state_at(cfg.substeps).x
    pull = (weight * ((end - anchor) ** 2).sum(axis=1)).sum()
    assert pull > 0.05 * plain
    assert L == pytest.approx(plain + pull, rel=1e-10)
    _a_term_of_the_physics_loss(s, state, L, plain, seed=12)
    s.backward(None, None, include_mass_loss=False)  # the injected adjoints alone: none here
    assert not s.control_gradient().any()
    s.set_position_anchors(None)
    assert s.forward() == pytest.approx(plain, rel=1e-12) and s.mass_loss() == s.loss()
    with pytest.raises(MPMStateError, match="anchor weights"):
        s.set_position_anchors(anchor, -weight - 1.0)


def test_overfill_term_matches_its_formula_reference_and_fd(state):
    """overfill_weight > 0 adds w sum_I max(0, log(m_I + e) - log(c_I + e))^2, c_I = max(ratio x
    density x dx^3, m*_I), to the log loss: the documented formula on the reference grid mass (the
    test's ball has nodes on both sides of the cap), and the control gradient against central
    finite differences and torch autograd. A weight w' set at run time (set_overfill_weight, what
    MorphConfig.overfill_onset does) gives the same with w': 0 leaves the plain log loss, and the
    gradient at w' matches finite differences and the reference built with w'. A solver built
    without the term refuses a weight. Slow: it compiles a solver of its own settings (the overfill
    kernels) and runs two finite-difference checks and two reference rollouts through torch."""
    cfg = cfg64(substeps=2, mass_loss="log", overfill_weight=3.0, overfill_ratio=0.4)
    s = make(cfg, state)
    assert s.overfill_weight == 3.0
    L, m, t, eps = _loss_at_zero_control(s, cfg, state)
    cap = np.maximum(cfg.overfill_ratio * cfg.density * cfg.dx ** 3, t)
    over = np.maximum(np.log(m + eps) - np.log(cap + eps), 0.0)
    assert (over > 0).sum() > 5 and ((m > 0) & (over == 0)).sum() > 5
    log_loss = ((np.log(m + eps) - np.log(t + eps)) ** 2).sum()
    assert L == pytest.approx(log_loss + 3.0 * (over ** 2).sum(), rel=1e-10)
    for w in (0.0, 1.5):
        s.set_overfill_weight(w)
        assert s.overfill_weight == w
        assert s.forward() == pytest.approx(log_loss + w * (over ** 2).sum(), rel=1e-10)
    ctrl = random_control(cfg, state.n)
    for w in (3.0, 1.5):
        s.set_overfill_weight(w)
        s.set_control(ctrl)
        fd_check(s, state, n_checks=6 if w == 3.0 else 3, seed=11)
        _loss_control_gradient_matches_autograd(s, state, ctrl, t, eps, cfg=dataclasses.replace(cfg, overfill_weight=w))
    with pytest.raises(MPMConfigError, match="overfill_weight"):
        cfg64(overfill_weight=-1.0)
    with pytest.raises(ValueError, match="overfill weight"):
        s.set_overfill_weight(-1.0)
    plain = MPMSolver(cfg64(substeps=2, mass_loss="log"), state.n)  # no kernel runs: none compiles
    plain.set_overfill_weight(0.0)
    with pytest.raises(MPMConfigError, match="overfill_weight > 0"):
        plain.set_overfill_weight(1.0)



def test_volume_term_adds_its_formula_and_matches_fd(state):
    """volume_weight w > 0 adds w u (V_T / V* - 1)^2 to the loss, V_T = sum_p V0 det F_T the body's
    volume at the end, V* = sum_p V0 det Fp the rest volume, u the target's filled nodes (log form):
    the loss is the plain one plus that term, mass_loss() reports it without, the control's and the
    initial state's gradients match central finite differences (float64; at the shipped solver in
    test_mpm_transfers.py), backward_pair's mass-loss gradient carries the term, and weight 0
    removes it. The weight is chosen so the term is about the plain loss (a test of a negligible
    term would pass with a wrong gradient)."""
    base = cfg64(substeps=2, mass_loss="log")
    s = make(base, state, reuse=True)
    s.set_control(random_control(base, state.n))
    plain, ratio, unit = volume_term_parts(s, state)
    assert abs(ratio - 1.0) > 1e-3  # the perturbed ball's volume is off its rest volume
    w = plain / (unit * (ratio - 1.0) ** 2)
    s.configure(dataclasses.replace(base, volume_weight=w))
    L = s.forward()
    assert L == pytest.approx(plain + w * unit * (ratio - 1.0) ** 2, rel=1e-10)
    _a_term_of_the_physics_loss(s, state, L, plain, seed=31)
    s.configure(base)
    assert s.forward() == pytest.approx(plain, rel=1e-12)
    with pytest.raises(MPMConfigError, match="volume_weight"):
        dataclasses.replace(base, volume_weight=-1.0)
