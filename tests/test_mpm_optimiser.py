"""Tests of the differentiable MPM solver (physmorph.mpm): the optimisers of dFc: normalised gradient descent with its line search, clip, per-volume weights, step smoothing and volume projections, Adam, and the injection calibration's first gradient."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
import torch

from physmorph.grid import Grid, splat_mass
from physmorph.mpm import (CFLWarning, MPMConfig, MPMConfigError, MPMDivergenceError, MPMSolver,
                           MPMStateError, ParticleState, elastic_energy, fixed_corotated_energy_density, solver_for,
                           total_volume)
from physmorph.mpm import reference as ref
from physmorph.mpm.solver import evaluate_stress
from mpm_cases import (RES, autograd_check, ball_state, cfg64, fd_check, make, random_control, solver3, solver20, state,  # noqa: F401
                        stretched_target)


# ----------------------------------------------------------------------------- normalised GD
def test_normalized_gd_line_search_decreases_the_objective_monotonically(state):
    """Each accepted step lowers mass loss + <gF, F_T>; a step size too large for any decrease
    within line_search_iters halvings is undone (the control is left unchanged)."""
    cfg = cfg64(substeps=5, optimizer="normalized_gd", learning_rate=0.01, line_search_iters=10)
    st = ball_state(perturb=False)
    s = make(cfg, st, reuse=True)
    s.set_target_grid_mass(stretched_target(st, cfg, stretch=(1.06, 0.97, 0.97)))
    gF = 10.0 * np.random.default_rng(2).normal(size=(st.n, 3, 3))
    s.reset_control()
    s.load_state(st)
    objs = []
    for _ in range(6):
        s.optimize_control(grad_F_final=gF, iters=1)
        objs.append(s.mass_loss() + float((gF * s.state_at(cfg.substeps).F).sum()))
    assert all(b <= a for a, b in zip(objs, objs[1:])) and objs[-1] < objs[0]
    # line search exhausted (one try at a huge step): nothing changes
    big = MPMConfig(**{**cfg.__dict__, "learning_rate": 1e3, "line_search_iters": 1})
    s2 = make(big, st, reuse=True)  # s, reset and given the new driver settings
    s2.set_target_grid_mass(stretched_target(st, cfg, stretch=(1.06, 0.97, 0.97)))
    s2.reset_control()
    s2.load_state(st)
    stats = s2.optimize_control(iters=1)
    assert stats["iters"] == 0 and np.abs(s2.control()).max() == 0.0
    assert stats["loss_final"] == pytest.approx(stats["loss_initial"], rel=1e-12)


def _gradient_and_one_step(cfg, st):
    """The dFc gradient of one forward/backward from zero control, and the control after one
    optimiser iteration from there."""
    s = make(cfg, st, reuse=True)
    s.reset_control()
    s.load_state(st)
    s.forward()
    s.backward()
    g = s.control_gradient()
    s.optimize_control(iters=1)
    return g, s.control()


@pytest.mark.parametrize("scaled", [True, False])
def test_normalized_gd_keeps_relative_gradient_sizes(state, scaled):
    """The step is -alpha g / rms(g): proportional to the gradient (unlike Adam's per-entry sign-like
    step), alpha = learning_rate x dx with step_scales_with_dx (dx = 2 on the tests' 16^3 grid), else
    learning_rate."""
    cfg = cfg64(substeps=3, optimizer="normalized_gd", learning_rate=1e-4, step_scales_with_dx=scaled)
    alpha = 2e-4 if scaled else 1e-4
    assert cfg.dx == 2.0 and cfg.step_size == pytest.approx(alpha, rel=1e-12)
    g, step = _gradient_and_one_step(cfg, state)
    rms = np.sqrt(np.mean(g * g))
    np.testing.assert_allclose(step, -alpha * g / rms, rtol=1e-9, atol=1e-15)


def test_normalized_gd_step_clip_bounds_each_entry(state):
    """With step_clip c the step is -alpha clip(g / rms(g), -c, c): entries under c are the plain
    normalised step, larger ones are cut to c alpha."""
    cfg = cfg64(substeps=3, optimizer="normalized_gd", learning_rate=1e-4, step_clip=1.5)
    g, step = _gradient_and_one_step(cfg, state)
    rms = np.sqrt(np.mean(g * g))
    assert np.abs(g / rms).max() > 1.5  # the clip is active somewhere
    np.testing.assert_allclose(step, -cfg.step_size * np.clip(g / rms, -1.5, 1.5), rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize("clip", [0.0, 1.5])
def test_step_per_volume_is_the_gradient_per_unit_volume_normalised(state, clip):
    """With step_per_volume the step is -alpha clip(w g / rms(w g)), w_p = V_max / V_p: a particle of
    a tenth of the volume (a denser sampling's) moves as far as a large one under the same stress;
    with equal volumes it is the plain step, bit for bit."""
    vol = state.volume * np.where(np.arange(state.n) % 3 == 0, 1.0, 0.1)  # two samplings' particles
    st = dataclasses.replace(state, volume=vol, mass=state.mass * vol / state.volume)
    steps = {}
    for per_volume, s_state in ((True, st), (False, st), (True, state), (False, state)):
        cfg = cfg64(substeps=3, optimizer="normalized_gd", learning_rate=1e-4, step_clip=clip,
                    step_per_volume=per_volume)
        g, step = _gradient_and_one_step(cfg, s_state)
        steps[per_volume, s_state is st] = (step, g)
    step, g = steps[True, True]
    wg = g * (vol.max() / vol)[None, :, None, None]
    d = wg / np.sqrt(np.mean(wg * wg))
    np.testing.assert_allclose(step, -1e-4 * 2.0 * (np.clip(d, -clip, clip) if clip else d), rtol=1e-9, atol=1e-15)
    plain, g = steps[False, True]
    assert np.abs(plain - step).max() > 1e-6  # the weights change the step
    np.testing.assert_array_equal(steps[True, False][0], steps[False, False][0])  # equal volumes: no change


def test_step_volume_power_weights_by_a_power_of_the_volume_ratio(state):
    """step_volume_power p: the step is -alpha w g / rms(w g) with w_p = (V_max / V_p)^p; p = 1 is
    the step per unit volume and p = 0 the plain step, bit for bit."""
    vol = state.volume * np.where(np.arange(state.n) % 3 == 0, 1.0, 0.1)
    st = dataclasses.replace(state, volume=vol, mass=state.mass * vol / state.volume)
    steps = {}
    for per_volume, power in ((True, 0.5), (True, 1.0), (True, 0.0), (False, 0.5)):
        cfg = cfg64(substeps=3, optimizer="normalized_gd", learning_rate=1e-4, step_clip=0.0,
                    step_per_volume=per_volume, step_volume_power=power)
        steps[per_volume, power] = _gradient_and_one_step(cfg, st)
    g, step = steps[True, 0.5]
    wg = g * ((vol.max() / vol) ** 0.5)[None, :, None, None]
    np.testing.assert_allclose(step, -1e-4 * 2.0 * wg / np.sqrt(np.mean(wg * wg)), rtol=1e-9, atol=1e-15)
    assert np.abs(step - steps[True, 1.0][1]).max() > 1e-6  # the power changes the step
    np.testing.assert_array_equal(steps[True, 0.0][1], steps[False, 0.5][1])  # power 0: the plain step
    with pytest.raises(ValueError, match="step_volume_power"):
        cfg64(step_volume_power=1.5)


@pytest.mark.parametrize("per_volume", [True, False])
def test_step_rms_by_volume_counts_each_particle_by_its_volume(state, per_volume):
    """step_rms "volume": the step is -alpha clip(w g / rms_V(w g)) with rms_V^2 = sum_p (V_p / mean V)
    |w_p g_p|^2 / (T n 9), each particle counted by its volume; with equal volumes it is the
    particle count's RMS, the default's step."""
    vol = state.volume * np.where(np.arange(state.n) % 3 == 0, 1.0, 0.1)
    st = dataclasses.replace(state, volume=vol, mass=state.mass * vol / state.volume)
    steps = {}
    for rms, s_state in (("volume", st), ("particles", st), ("volume", state), ("particles", state)):
        cfg = cfg64(substeps=3, optimizer="normalized_gd", learning_rate=1e-4, step_clip=1.5,
                    step_per_volume=per_volume, step_rms=rms)
        steps[rms, s_state is st] = _gradient_and_one_step(cfg, s_state)
    g, step = steps["volume", True]
    w = (vol.max() / vol) if per_volume else np.ones(state.n)
    wg = g * w[None, :, None, None]
    rms_v = np.sqrt(np.mean(wg * wg * (vol / vol.mean())[None, :, None, None]))
    np.testing.assert_allclose(step, -1e-4 * 2.0 * np.clip(wg / rms_v, -1.5, 1.5), rtol=1e-9, atol=1e-15)
    assert np.abs(step - steps["particles", True][1]).max() > 1e-6  # the volumes change the step
    np.testing.assert_allclose(steps["volume", False][1], steps["particles", False][1], rtol=1e-12, atol=1e-18)
    with pytest.raises(ValueError, match="step_rms"):
        cfg64(step_rms="mass")


def _grid_share(x, vol, wg, grid):  # x [N, 3], vol [N], wg [T, N, 3, 3] -> [T, N, 3, 3]
    """The NumPy reference of MPMSolver._smooth_step_slot: volume-weighted P2G of wg on the
    B-spline stencils, each node's mean, and G2P back over the nodes that hold material."""
    from physmorph.grid import bspline_weights, scatter_add
    base, w = bspline_weights(x, grid)
    w27 = w[:, 0, :, None, None] * w[:, 1, None, :, None] * w[:, 2, None, None, :]  # [N, 3, 3, 3]
    off = np.stack(np.meshgrid(*(np.arange(3),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    nodes = base[:, None, :] + off[None]  # [N, 27, 3]
    wsum = np.zeros((grid.res,) * 3)
    scatter_add(wsum, base, w27 * vol[:, None, None, None])
    out = np.empty_like(wg)
    for t in range(len(wg)):
        G = np.zeros((grid.res,) * 3 + (9,))
        for c in range(9):
            g = np.zeros((grid.res,) * 3)
            scatter_add(g, base, w27 * (vol * wg[t].reshape(-1, 9)[:, c])[:, None, None, None])
            G[..., c] = np.divide(g, wsum, out=np.zeros_like(g), where=wsum > 0)
        Gn = G[nodes[..., 0], nodes[..., 1], nodes[..., 2]]  # [N, 27, 9]
        out[t] = np.einsum("nk,nkc->nc", w27.reshape(len(x), 27), Gn).reshape(-1, 3, 3)
    return out


@pytest.mark.parametrize("per_volume", [True, False])
def test_step_smoothing_steps_along_the_grids_share_of_the_direction(state, per_volume):
    """step_smoothing "grid": the step is -alpha clip(d / rms(d)) with d the weighted gradient w g
    carried to the grid (volume-weighted B-spline P2G, each node's mean) and back (G2P): the NumPy
    reference. A direction that is already the same for every particle of a node's stencils is
    kept; the smoothed step differs from the particles' own."""
    vol = state.volume * np.where(np.arange(state.n) % 3 == 0, 1.0, 0.1)
    st = dataclasses.replace(state, volume=vol, mass=state.mass * vol / state.volume)
    cfg = cfg64(substeps=3, optimizer="normalized_gd", learning_rate=1e-4, step_clip=1.5,
                step_per_volume=per_volume, step_smoothing="grid")
    g, step = _gradient_and_one_step(cfg, st)
    w = (vol.max() / vol) if per_volume else np.ones(st.n)
    d = _grid_share(st.x, vol, g * w[None, :, None, None], Grid(cfg.grid_res, cfg.domain_lo, cfg.domain_hi))
    rms = np.sqrt(np.mean(d * d))
    np.testing.assert_allclose(step, -1e-4 * 2.0 * np.clip(d / rms, -1.5, 1.5), rtol=1e-8, atol=1e-14)
    _, plain = _gradient_and_one_step(dataclasses.replace(cfg, step_smoothing="none"), st)
    assert np.abs(plain - step).max() > 1e-6
    # the reference itself: a uniform direction comes back unchanged
    u = np.broadcast_to(np.arange(9.0).reshape(1, 1, 3, 3), (1, st.n, 3, 3)).copy()
    np.testing.assert_allclose(_grid_share(st.x, vol, u, Grid(cfg.grid_res, cfg.domain_lo, cfg.domain_hi)), u,
                               rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="step_smoothing"):
        cfg64(step_smoothing="particles")


def _volume_projection(d, F, C, vol, mode):  # d [T, N, 3, 3], F [N, 3, 3], C [T, N, 3, 3], vol [N]
    """The NumPy reference of the step's volume projection (MPMSolver._step_direction): with
    A = F + C and n = A^-T, "particle" removes each particle's component along n, "body" each
    slot's component along N = V det(A) n over all particles together."""
    A = F[None] + C
    n = np.linalg.inv(A).transpose(0, 1, 3, 2)
    if mode == "particle":
        return d - ((d * n).sum(axis=(-2, -1), keepdims=True) / (n * n).sum(axis=(-2, -1), keepdims=True)) * n
    N = (vol * np.linalg.det(A))[..., None, None] * n
    lam = (d * N).sum(axis=(1, 2, 3)) / (N * N).sum(axis=(1, 2, 3))  # [T]
    return d - lam[:, None, None, None] * N


@pytest.mark.parametrize("smoothing", ["none", "grid"])
@pytest.mark.parametrize("mode", ["particle", "body"])
def test_step_volume_removes_the_steps_first_order_volume_change(state, smoothing, mode):
    """step_volume: the step is -alpha clip(d / rms(d)) with d the weighted (and, where asked,
    smoothed) gradient less its first-order change of volume, each particle's ("particle") or the
    body's ("body"): the NumPy projection. Unclipped, the step leaves each particle's det(F_0 + dFc),
    or sum_p V_p det(F_0 + dFc)_p, unchanged to first order; the projected step differs from the full one."""
    vol = state.volume * np.where(np.arange(state.n) % 3 == 0, 1.0, 0.1)
    st = dataclasses.replace(state, volume=vol, mass=state.mass * vol / state.volume)
    w = vol.max() / vol
    C = np.zeros((3, st.n, 3, 3))  # the control the direction is taken at (zero: from rest)
    # the stretched ball's gradient is mostly a change of volume: what is left of it after the
    # smoothing and the body's projection, clipped, is no descent direction, and the line search
    # rightly takes no step, so that case is checked unclipped only
    for clip in (0.0,) if (smoothing, mode) == ("grid", "body") else (1.5, 0.0):
        cfg = cfg64(substeps=3, optimizer="normalized_gd", learning_rate=1e-4, step_clip=clip,
                    step_per_volume=True, step_smoothing=smoothing, step_volume=mode, step_volume_share=1.0)
        g, step = _gradient_and_one_step(cfg, st)
        d = g * w[None, :, None, None]
        if smoothing == "grid":
            d = _grid_share(st.x, vol, d, Grid(cfg.grid_res, cfg.domain_lo, cfg.domain_hi))
        d = _volume_projection(d, st.F, C, vol, mode)
        d = d / np.sqrt(np.mean(d * d))
        np.testing.assert_allclose(step, -1e-4 * 2.0 * (np.clip(d, -clip, clip) if clip else d), rtol=1e-8, atol=1e-14)
    n = np.linalg.inv(st.F).transpose(0, 2, 1)[None]
    change = (step * n).sum(axis=(-2, -1))  # [T, N]: each particle's first-order d(log det)
    if mode == "particle":
        assert np.abs(change).max() < 1e-12 * np.abs(step).max()
    else:
        body = (change * vol * np.linalg.det(st.F)).sum(axis=1)  # [T]: the body's first-order dV
        assert np.abs(body).max() < 1e-12 * np.abs(step).max() * vol.sum()
        assert np.abs(change).max() > 1e-3 * np.abs(step).max()  # particles still trade volume
    _, full = _gradient_and_one_step(dataclasses.replace(cfg, step_volume="full"), st)
    assert np.abs(full - step).max() > 1e-6
    with pytest.raises(ValueError, match="step_volume"):
        cfg64(step_volume="none")
    if mode == "particle" and smoothing == "none":
        # a share beta of the projection: d - beta (<d, n> / <n, n>) n, between the two steps
        cfg = dataclasses.replace(cfg, step_volume_share=0.25)
        g, step = _gradient_and_one_step(cfg, st)
        d = g * w[None, :, None, None]
        d = d - 0.25 * (d - _volume_projection(d, st.F, C, vol, mode))
        np.testing.assert_allclose(step, -1e-4 * 2.0 * d / np.sqrt(np.mean(d * d)), rtol=1e-8, atol=1e-14)
        with pytest.raises(ValueError, match="step_volume_share"):
            cfg64(step_volume_share=1.5)


def test_sufficient_decrease_accepts_only_steps_that_fall_as_promised(state):
    """With the Armijo constant c the accepted step lowers the objective by at least
    c alpha <g, d> (d = clip(g / rms)); a larger c never accepts a longer step than c = 0."""
    alphas = {}
    for c in (0.0, 0.5, 0.9):
        cfg = cfg64(substeps=3, optimizer="normalized_gd", learning_rate=0.05, step_clip=1.5,
                    sufficient_decrease=c)
        st = ball_state(perturb=False)
        s = make(cfg, st, reuse=True)
        s.set_target_grid_mass(stretched_target(st, cfg, stretch=(1.06, 0.97, 0.97)))
        s.reset_control()
        s.load_state(st)
        before = s.forward()
        s.backward()
        g = s.control_gradient()
        rms = np.sqrt(np.mean(g * g))
        rate = float((g * np.clip(g / rms, -1.5, 1.5)).sum())
        stats = s.optimize_control(iters=1)
        alphas[c] = stats["step"] if stats["iters"] else 0.0
        assert stats["loss_final"] <= before - c * alphas[c] * rate + 1e-12 * abs(before)
    assert alphas[0.9] <= alphas[0.5] <= alphas[0.0] and alphas[0.9] < alphas[0.0]


def test_scale_control_is_the_numpy_product(state):
    """The morph loop's leak scales dFc in place: the same numbers as set_control(f x control())."""
    cfg = cfg64(substeps=3)
    s = make(cfg, state, reuse=True)
    s.load_state(state)
    c = random_control(cfg, state.n)
    s.set_control(c)
    s.forward()
    s.scale_control(0.95)
    np.testing.assert_array_equal(s.control(), 0.95 * c)
    assert not s.current.trajectory_current  # the stored rollout belongs to the old control
    with pytest.raises(ValueError, match="finite"):
        s.scale_control(float("nan"))


@pytest.mark.parametrize("optimizer", ["normalized_gd", "adam"])
def test_first_gradient_from_the_injection_calibration_skips_nothing_it_should_not(state, optimizer):
    """The morph loop hands the optimiser the calibration's two gradients, mass + c x injected
    (physmorph.injection, combined in place by MPMSolver.combine_calibration), instead of a forward
    and backward of its own: the two gradients equal separate backwards', their combination is
    their NumPy sum, the controls and losses after two iterations equal the plain path's, and a
    gradient for a stale rollout is refused."""
    from physmorph.injection import calibrate_injection

    cfg = cfg64(substeps=4, optimizer=optimizer, learning_rate=1e-3)
    st = ball_state(perturb=False)
    target = stretched_target(st, cfg, stretch=(1.06, 0.97, 0.97))
    gF = np.random.default_rng(5).normal(size=(st.n, 3, 3))
    runs = []
    # the plain path, then the calibration's gradients handed over, from two backwards and from backward_pair
    for use_first, pair in ((False, None), (True, False), (True, True)):
        s = make(cfg, st, reuse=True)
        s.set_target_grid_mass(target)
        s.reset_control()
        s.load_state(st)
        s.forward()
        s.backward(None, None)
        g_mass = s.control_gradient()
        s.backward(gF, None, include_mass_loss=False)
        g_inj = s.control_gradient()
        cal = calibrate_injection(s, 0.1, gF, None, pair=pair)
        assert cal.scale == pytest.approx(0.1 * np.linalg.norm(g_mass) / np.linalg.norm(g_inj), rel=1e-9)
        pair_inj, pair_mass = s.control_gradient(), s.ctrl_base.to_numpy()
        np.testing.assert_allclose(pair_inj, g_inj, rtol=1e-10, atol=1e-14 * np.abs(g_inj).max())
        np.testing.assert_allclose(pair_mass, g_mass, rtol=1e-10, atol=1e-14 * np.abs(g_mass).max())
        if use_first:
            s.combine_calibration(cal.scale)
            np.testing.assert_allclose(s.control_gradient(), pair_mass + cal.scale * pair_inj, rtol=1e-14, atol=1e-300)
            assert s.grad_norm == pytest.approx(np.linalg.norm(g_mass + cal.scale * g_inj), rel=1e-12)
        stats = s.optimize_control(grad_F_final=cal.scale * gF, iters=2, gradient_ready=use_first)
        runs.append((s.control(), stats["losses"], stats["loss_final"]))
    (c_plain, l_plain, f_plain) = runs[0]
    assert np.abs(c_plain).max() > 0
    for c_first, l_first, f_first in runs[1:]:
        np.testing.assert_allclose(c_first, c_plain, rtol=1e-9, atol=1e-12 * np.abs(c_plain).max())
        np.testing.assert_allclose(l_first, l_plain, rtol=1e-10)
        assert f_first == pytest.approx(f_plain, rel=1e-10)
    with pytest.raises(RuntimeError, match="calibration"):  # consumed: the line search reused its field
        s.combine_calibration(1.0)
    with pytest.raises(RuntimeError, match="forward"):  # the control changed since the rollout
        s.set_control(c_first)
        s.optimize_control(iters=1, gradient_ready=True)
    s.load_state(st)
    calibrate_injection(s, 0.1, gF, None)
    s.backward(None, None)  # a later backward overwrites the injected gradient
    with pytest.raises(RuntimeError, match="calibration"):
        s.combine_calibration(1.0)


def test_control_mean_and_rebase_in_place_equal_their_numpy_formulas(state):
    """MPMSolver.control_mean is mean_t dFc_t and MPMSolver.rebase_control is
    physmorph.plasticity.rebase_control, in place, for a per-substep control."""
    from physmorph.plasticity import rebase_control

    cfg = cfg64(substeps=3)
    st = ball_state(perturb=False)
    s = make(cfg, st, reuse=True)
    rng = np.random.default_rng(7)
    c = 0.05 * rng.standard_normal((cfg.n_control_slots, st.n, 3, 3))
    s.set_control(c)
    np.testing.assert_allclose(s.control_mean(), c.mean(axis=0), rtol=1e-13, atol=1e-16)
    F = np.eye(3) + 0.1 * rng.standard_normal((st.n, 3, 3))
    Fp_old = np.eye(3) + 0.05 * rng.standard_normal((st.n, 3, 3))
    Fp_new = np.eye(3) + 0.05 * rng.standard_normal((st.n, 3, 3))
    s.rebase_control(F, np.linalg.solve(Fp_old, Fp_new))
    np.testing.assert_allclose(s.control(), rebase_control(F, c, Fp_old, Fp_new), rtol=1e-12, atol=1e-14)
    with pytest.raises(MPMStateError, match="shape"):
        s.rebase_control(F[:-1], Fp_new)


def test_optimizer_config_is_checked():
    with pytest.raises(MPMConfigError, match="step_clip"):
        cfg64(step_clip=-1.0)
    with pytest.raises(MPMConfigError, match="optimizer"):
        cfg64(optimizer="sgd")
    with pytest.raises(MPMConfigError, match="line_search_iters"):
        cfg64(line_search_iters=0)


def test_normalized_gd_keeps_no_adam_moments_and_resumes_from_its_state(state):
    """The default optimiser allocates no Adam moments (their fields and checkpoint would be
    0.7 GB each at the paper's scale); its saved state restores the next step exactly."""
    cfg = cfg64(substeps=2, optimizer="normalized_gd", learning_rate=1e-3)
    target = stretched_target(ball_state(perturb=False), cfg)
    s = MPMSolver(cfg, state.n)
    s.set_target_grid_mass(target)
    s.load_state(state)
    s.optimize_control(iters=1)
    saved = s.optimizer_state()
    assert s.adam_m is None and set(saved) == {"control", "adam_step"}
    assert saved["control"].dtype == s.np_dtype
    ctrl_a = (s.optimize_control(iters=1), s.control())[1]
    s.reset_control()
    s.set_optimizer_state(saved)
    s.load_state(state)
    s.optimize_control(iters=1)
    np.testing.assert_array_equal(s.control(), ctrl_a)
