"""Tests of the differentiable MPM solver (physmorph.mpm): the transfers and their adjoints: the forward against a dense torch reference, conservation, float32 against float64, the control gradient against central differences (float64) and torch autograd, at the simple settings and at the shipped defaults; isochoric smoothing, the volume floor, the polar decomposition and its quaternion."""

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


# ----------------------------------------------------------------------------- forward
def test_grid_mass_matches_splat_mass(solver3, state):
    solver3.load_state(state)
    solver3.set_control(random_control(solver3.cfg, state.n))
    solver3.forward()
    end = solver3.state_at(3)
    np.testing.assert_allclose(solver3.grid_mass(), splat_mass(end.x, end.mass, solver3.grid),
                               rtol=1e-12, atol=1e-10)
    assert solver3.mass_loss() == pytest.approx(
        ((solver3.grid_mass() - solver3.model.target_m.to_numpy()) ** 2).sum(), rel=1e-12)


def test_rollout_matches_torch_reference(solver3, state):
    cfg = solver3.cfg
    ctrl = random_control(cfg, state.n)
    solver3.load_state(state)
    solver3.set_control(ctrl)
    solver3.forward()
    T = [ref.as_torch(a) for a in (state.x, state.v, state.C, state.F)]
    states = ref.rollout_torch(*T, ref.as_torch(ctrl), ref.as_torch(state.Fp), ref.as_torch(state.mass),
                               ref.as_torch(state.volume), cfg)
    for t in (1, 3):
        got = solver3.state_at(t)
        for name, want in zip(("x", "v", "C", "F"), states[t]):
            np.testing.assert_allclose(getattr(got, name), want.numpy(), rtol=1e-7, atol=1e-9,
                                       err_msg=f"{name} at substep {t}")


def test_momentum_and_mass_conserved_without_drag():
    cfg = cfg64(substeps=20, drag=0.0, smoothing=0.0)
    st = ball_state(radius=2.5)
    s = make(cfg, st)
    s.set_control(random_control(cfg, st.n, scale=0.02))
    s.forward()
    p0 = (st.mass[:, None] * st.v).sum(0)
    for t in (1, 10, 20):
        e = s.state_at(t)
        assert np.abs(e.x).max() < 10.0  # no boundary contact
        np.testing.assert_allclose((e.mass[:, None] * e.v).sum(0), p0, atol=1e-9 * np.abs(st.mass * np.abs(st.v).max(1)).sum())
    assert s.grid_mass().sum() == pytest.approx(st.mass.sum(), rel=1e-12)
    # drag = 0, s = 0 is also an extreme: forward and backward stay finite
    s.backward()
    assert np.isfinite(s.control_gradient()).all()


def test_float32_matches_float64_over_20_substeps():
    st = ball_state(seed=5)
    trajs = {}
    for prec in ("float32", "float64"):
        cfg = MPMConfig(grid_res=RES, precision=prec, substeps=20)
        s = make(cfg, st, target=False)
        s.set_control(random_control(cfg, st.n, scale=0.02))
        s.forward()
        trajs[prec] = s.state_at(20)
    a, b = trajs["float32"], trajs["float64"]
    # stated tolerance: 1e-4 of a cell in position, 1e-4 in F, 1e-3 relative in velocity
    assert np.abs(a.x - b.x).max() < 1e-4 * RES / 16 * 2
    assert np.abs(a.F - b.F).max() < 1e-4
    assert np.abs(a.v - b.v).max() < 1e-3 * np.abs(b.v).max()


# ----------------------------------------------------------------------------- gradients


def test_one_substep_gradients_match_fd(state):
    s = make(cfg64(substeps=1), state, reuse=True)
    s.set_control(random_control(s.cfg, state.n))
    fd_check(s, state, n_checks=8)
    gF = 50.0 * np.random.default_rng(12).normal(size=(state.n, 3, 3))
    fd_check(s, state, gF=gF, n_checks=6, seed=7)


def test_three_substep_gradients_match_fd(solver3, state):
    solver3.set_control(random_control(solver3.cfg, state.n))
    fd_check(solver3, state, n_checks=8, seed=1)


def test_injected_adjoints_match_fd(solver3, state):
    rng = np.random.default_rng(11)
    gF = 50.0 * rng.normal(size=(state.n, 3, 3))
    gx = 5.0 * rng.normal(size=(state.n, 3))
    solver3.set_control(random_control(solver3.cfg, state.n))
    fd_check(solver3, state, gF=gF, n_checks=6, seed=2)
    fd_check(solver3, state, gx=gx, n_checks=6, seed=3)




def test_gradients_match_torch_autograd(solver3, state):
    ctrl = random_control(solver3.cfg, state.n)
    gF = np.random.default_rng(4).normal(size=(state.n, 3, 3))
    autograd_check(solver3, state, ctrl, gF)


@pytest.fixture(scope="module")
def solver3_log(state):
    """As solver3, with the log mass loss."""
    return make(cfg64(mass_loss="log"), state)


def test_log_loss_gradients_match_fd(solver3_log, state):
    solver3_log.set_control(random_control(solver3_log.cfg, state.n))
    fd_check(solver3_log, state, n_checks=6, seed=5)


def test_log_loss_value_matches_reference(solver3_log, state):
    # the documented formula on the reference grid mass
    s = solver3_log
    cfg = s.cfg
    s.load_state(state)
    s.set_control(np.zeros((3, state.n, 3, 3)))
    L = s.forward()
    end = s.state_at(3)
    m = splat_mass(end.x, end.mass, s.grid)
    eps = cfg.log_mass_eps * state.mass.mean()
    want = ((np.log(m + eps) - np.log(s.model.target_m.to_numpy() + eps)) ** 2).sum()
    assert L == pytest.approx(want, rel=1e-10)


# ----------------------------------------------------------------------------- isochoric smoothing
def test_isochoric_smoothing_keeps_the_volume_and_matches_reference_and_fd(state):
    """smoothing_mode "isochoric": det F follows the motion exactly (det F_{t+1} = det(I + dt C_{t+1})
    det F_t) while the smoothing still damps the shape; the rollout equals the torch reference's and
    the gradients match central finite differences (control and initial state) and torch autograd."""
    cfg = cfg64(substeps=3, smoothing_mode="isochoric")
    s = make(cfg, state)
    ctrl = random_control(cfg, state.n)
    s.set_control(ctrl)
    s.forward()
    for t in range(cfg.substeps):
        a, b = s.state_at(t), s.state_at(t + 1)
        want = np.linalg.det(np.eye(3) + cfg.dt * b.C) * np.linalg.det(a.F)
        np.testing.assert_allclose(np.linalg.det(b.F), want, rtol=1e-12)
    plain = make(cfg64(substeps=3), state, reuse=True)
    plain.set_control(ctrl)
    plain.forward()
    assert np.abs(np.linalg.det(plain.state_at(3).F) - np.linalg.det(s.state_at(3).F)).max() > 1e-3
    gF = np.random.default_rng(8).normal(size=(state.n, 3, 3))
    fd_check(s, state, gF=gF, n_checks=6, seed=9)
    states = autograd_check(s, state, ctrl, gF)
    np.testing.assert_allclose(s.state_at(3).F, states[-1][3].detach().numpy(), rtol=1e-9, atol=1e-12)


def test_volume_floor_holds_det_F_and_matches_reference_and_fd(state):
    """min_volume_ratio J_min (isochoric smoothing): det F' = max(det(I + dt C') det F, J_min)
    exactly, so the floored particles stop at J_min and the others follow the motion; the rollout
    equals the torch reference's and the gradients match central finite differences and autograd
    (the floored particles pass no gradient through det F_new)."""
    J0 = np.linalg.det(state.F)
    floor = float(np.quantile(J0, 0.3))  # about a third of the ball starts below the floor
    cfg = cfg64(substeps=3, smoothing_mode="isochoric", min_volume_ratio=floor)
    s = make(cfg, state)
    ctrl = random_control(cfg, state.n)
    s.set_control(ctrl)
    s.forward()
    floored = 0
    for t in range(cfg.substeps):
        a, b = s.state_at(t), s.state_at(t + 1)
        moved = np.linalg.det(np.eye(3) + cfg.dt * b.C) * np.linalg.det(a.F)
        np.testing.assert_allclose(np.linalg.det(b.F), np.maximum(moved, floor), rtol=1e-12)
        floored += int((moved < floor).sum())
    assert 0 < floored < cfg.substeps * state.n
    gF = np.random.default_rng(11).normal(size=(state.n, 3, 3))
    fd_check(s, state, gF=gF, n_checks=6, seed=12)
    states = autograd_check(s, state, ctrl, gF)
    np.testing.assert_allclose(s.state_at(3).F, states[-1][3].detach().numpy(), rtol=1e-9, atol=1e-12)


def test_gradients_at_the_shipped_defaults_match_fd(state):
    """The gradients the morph loop steps along, at the shipped solver: MPMConfig() with only the
    precision (float64), the grid (16^3) and the substeps (3) changed, every method setting at its
    default (log mass loss with eps 0.1 x mean mass, the blurred level at 2 cells, the overfill term
    at weight 1 and ratio 0.001, isochoric smoothing with the volume floor J_min = 0.25, fixed
    corotated stress, drag 0.9, smoothing 0.955, the control in the stress only; the step_* and
    optimiser fields are driver-only and change no gradient). The loss's gradient and that of
    L + <gF, F_T> + <gx, x_T> (the injected render adjoints) w.r.t. the control and the initial x,
    v, F against central finite differences, at the existing checks' tolerance. The floor is a
    clamp, max(det F_new, J_min), not differentiable where det F_new = J_min: a quarter of the
    ball starts compressed to det F ~ 0.17 so that branch is exercised (floored in the first
    substep, free after), and the test asserts no particle's det F_new lies within 1e-4 of the
    kink (2e-4 at the nearest here), so a central difference of step 1e-5 stays on one branch:
    the check is where the clamp is smooth. The overfill term max(0, r)^2 is C^1 (its nodes on
    both sides of the cap here); the volume term at its shipped weight (mpm.volume_weight) is in
    it. Then the same with the volume term weighed to about the rest of the loss."""
    cfg = dataclasses.replace(MPMConfig(), precision="float64", grid_res=RES, substeps=3)
    default = MPMConfig()
    changed = {f.name for f in dataclasses.fields(MPMConfig) if getattr(cfg, f.name) != getattr(default, f.name)}
    assert changed == {"precision", "grid_res", "substeps"}
    assert cfg.mass_loss == "log" and cfg.mass_loss_blur > 0 and cfg.overfill_weight > 0
    assert cfg.smoothing_mode == "isochoric" and cfg.min_volume_ratio > 0 and cfg.volume_weight > 0
    st = state.copy()
    squeezed = np.arange(st.n) % 4 == 0
    st.F[squeezed] *= 0.55  # det F ~ 0.55^3 = 0.17 < J_min: these particles sit on the floor
    s = make(cfg, st, reuse=True)
    s.set_control(random_control(cfg, st.n, scale=0.02))
    s.forward()
    m, t = splat_mass(s.state_at(cfg.substeps).x, st.mass, s.grid), s.model.target_m.to_numpy()
    cap = np.maximum(cfg.overfill_ratio * cfg.density * cfg.dx ** 3, t)
    assert (m > cap).sum() > 5  # the overfill term acts on some nodes ...
    assert ((m > 0) & (m <= cap)).sum() > 5  # ... and not on others
    floored = free = 0
    for k in range(cfg.substeps):
        a, b = s.state_at(k), s.state_at(k + 1)
        moved = np.linalg.det(np.eye(3) + cfg.dt * b.C) * np.linalg.det(a.F)
        assert np.abs(moved - cfg.min_volume_ratio).min() > 1e-4  # no particle at the clamp's kink
        floored += int((moved < cfg.min_volume_ratio).sum())
        free += int((moved > cfg.min_volume_ratio).sum())
    assert floored > 0 and free > 0  # both branches of the floor
    rng = np.random.default_rng(21)
    fd_check(s, st, n_checks=8, seed=22, h=1e-5)
    fd_check(s, st, gF=50.0 * rng.normal(size=(st.n, 3, 3)), gx=5.0 * rng.normal(size=(st.n, 3)), n_checks=6,
              seed=23, h=1e-5)
    # the volume term on the same solver, weighed so it is about the rest of the loss
    s.configure(dataclasses.replace(cfg, volume_weight=0.0))
    plain, ratio, unit = volume_term_parts(s, st)
    s.configure(dataclasses.replace(cfg, volume_weight=plain / (unit * (ratio - 1.0) ** 2)))
    fd_check(s, st, n_checks=6, seed=24, h=1e-5)


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_polar_from_a_nearby_rotation_is_the_svd_polar(precision):
    """polar_from (the forward's polar decomposition, warm-started at the particle's rotation one
    substep earlier) equals the SVD's polar factors: to round-off in float64, and in float32 at
    least as close to the exact rotation as the float32 SVD, from starts up to 2 rad away; inverted
    Fe included. Its gap is the SVD's smallest pair sum where it fell back to the SVD, and else a
    lower bound of it no lower than WARM_GAP_MIN |S| (all the rotation's derivative needs). A
    start that is no rotation (before the first forward) takes the SVD itself."""
    from scipy.spatial.transform import Rotation

    from physmorph.mpm.stress import WARM_GAP_MIN, evaluate_polar

    rng = np.random.default_rng(3)
    n = 3000
    S = np.eye(3) + 0.3 * rng.standard_normal((n, 3, 3))
    S = S @ S.transpose(0, 2, 1) + 0.3 * np.eye(3)
    Fe = Rotation.random(n, random_state=4).as_matrix() @ S
    Fe[:40, :, 2] *= -1.0  # inverted
    R64, S64, gap64 = evaluate_polar(Fe, None, "float64")
    R_svd, _, _ = evaluate_polar(Fe, None, precision)
    tol = 1e-13 if precision == "float64" else None
    for angle in (0.01, 0.3, 2.0):
        R0 = R64 @ Rotation.from_rotvec(angle * rng.standard_normal((n, 3)) / np.sqrt(3)).as_matrix()
        R, S_w, gap = evaluate_polar(Fe, R0, precision)
        if tol:
            np.testing.assert_allclose(R, R64, atol=tol)
            np.testing.assert_allclose(S_w, S64, atol=1e-12)
        else:
            assert np.abs(R - R64).max() <= max(np.abs(R_svd - R64).max(), 2e-6)
        slack = 1e-12 if tol else 1e-5 * np.abs(S64).max()
        bound = WARM_GAP_MIN * np.linalg.norm(S_w, axis=(1, 2))
        warm = np.abs(gap - bound) <= slack  # the warm rotations' gap is their bound
        assert 0 < warm.sum() < n  # both branches taken (the inverted Fe fall back to the SVD)
        np.testing.assert_allclose(gap[~warm], gap64[~warm], atol=slack)
        assert (gap[warm] <= gap64[warm] + slack).all()  # a lower bound of the smallest pair sum
    # (the SVD itself: from a zero start the steps would give no rotation; in float32 the two
    # inlined copies of the SVD may round differently when Taichi's IR optimisation is off)
    R, _, _ = evaluate_polar(Fe, np.zeros_like(Fe), precision)
    np.testing.assert_allclose(R, R_svd, atol=1e-14 if precision == "float64" else 2e-6)


def test_forward_rotations_kept_as_quaternions_round_trip(solver3):
    """The forward keeps each substep's polar rotation as a unit quaternion for the backward
    (MPMModel.quaternion_of / rotation_of): back to the same rotation to float64 round-off,
    for random rotations, rotations by pi about an axis (w = 0: every Shepperd branch) and the
    identity."""
    import taichi as ti
    from scipy.spatial.transform import Rotation

    s = solver3
    rng = np.random.default_rng(4)
    axes = rng.normal(size=(60, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    half_turns = Rotation.from_rotvec(np.pi * np.vstack([axes, np.eye(3)])).as_matrix()
    rots = np.concatenate([Rotation.random(400, random_state=3).as_matrix(), half_turns, np.eye(3)[None]])
    r_in = ti.Matrix.field(3, 3, ti.f64, shape=len(rots))
    r_out = ti.Matrix.field(3, 3, ti.f64, shape=len(rots))
    r_in.from_numpy(rots)

    @ti.kernel
    def round_trip():
        for i in r_in:
            r_out[i] = s.model.rotation_of(s.model.quaternion_of(r_in[i]))

    round_trip()
    np.testing.assert_allclose(r_out.to_numpy(), rots, rtol=0, atol=1e-14)
