"""Tests of the differentiable MPM solver (physmorph.mpm): the optimisers of dFc: normalised gradient descent with its line search, clip, per-volume weights and volume projection, Adam, and the injection calibration's first gradient."""

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


@pytest.mark.parametrize("optimizer", ["normalized_gd", "adam"])
def test_frame_end_last_forward_takes_the_same_step_one_forward_sooner(state, optimizer):
    """frame_end "last_forward": the frame's one forward is the rollout its gradient is taken on,
    and its end is the frame's state; the control then holds the same step as with "stepped"
    (where the line search accepts its first try), which then runs a forward of it and ends there."""
    runs = {}
    for frame_end in ("stepped", "last_forward"):
        cfg = cfg64(substeps=3, optimizer=optimizer, learning_rate=1e-4, frame_end=frame_end)
        s = make(cfg, state, reuse=True)
        s.set_target_grid_mass(stretched_target(state, cfg, stretch=(1.06, 0.97, 0.97)))
        s.reset_control()
        s.load_state(state)
        before = s.current.rollout
        stats = s.optimize_control(iters=1)
        runs[frame_end] = (s.current.rollout - before, s.control(), s.state_at(cfg.substeps), stats)
        if frame_end == "last_forward":
            s.reset_control()
            s.load_state(state)
            unstepped = s.rollout()  # the zero control's rollout, which the frame ended at
    forwards, control, end, stats = runs["last_forward"]
    assert forwards == 1 and runs["stepped"][0] >= 2
    np.testing.assert_array_equal(control, runs["stepped"][1])
    assert np.abs(control).max() > 0
    np.testing.assert_array_equal(end.x, unstepped.x)
    np.testing.assert_array_equal(end.F, unstepped.F)
    assert np.abs(runs["stepped"][2].x - end.x).max() > 0  # the stepped frame ends elsewhere
    assert stats["loss_final"] == stats["loss_initial"] and stats["iters"] == 1


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


def _volume_projection(d, F, C):  # d [T, N, 3, 3], F [N, 3, 3], C [T, N, 3, 3]
    """The NumPy reference of the step's volume projection (MPMSolver._step_direction): with
    A = F + C and n = A^-T, each particle's component along n removed."""
    A = F[None] + C
    n = np.linalg.inv(A).transpose(0, 1, 3, 2)
    return d - ((d * n).sum(axis=(-2, -1), keepdims=True) / (n * n).sum(axis=(-2, -1), keepdims=True)) * n


def test_step_volume_removes_the_steps_first_order_volume_change(state):
    """step_volume "particle": the step is -alpha clip(d / rms(d)) with d the weighted gradient less
    each particle's first-order change of volume: the NumPy projection. Unclipped, the step leaves
    each particle's det(F_0 + dFc) unchanged to first order; the projected step differs from the
    full one; a share beta < 1 removes that share of the change."""
    vol = state.volume * np.where(np.arange(state.n) % 3 == 0, 1.0, 0.1)
    st = dataclasses.replace(state, volume=vol, mass=state.mass * vol / state.volume)
    w = vol.max() / vol
    C = np.zeros((3, st.n, 3, 3))  # the control the direction is taken at (zero: from rest)
    for clip in (1.5, 0.0):
        cfg = cfg64(substeps=3, optimizer="normalized_gd", learning_rate=1e-4, step_clip=clip,
                    step_per_volume=True, step_volume="particle", step_volume_share=1.0)
        g, step = _gradient_and_one_step(cfg, st)
        d = _volume_projection(g * w[None, :, None, None], st.F, C)
        d = d / np.sqrt(np.mean(d * d))
        np.testing.assert_allclose(step, -1e-4 * 2.0 * (np.clip(d, -clip, clip) if clip else d), rtol=1e-8, atol=1e-14)
    n = np.linalg.inv(st.F).transpose(0, 2, 1)[None]
    change = (step * n).sum(axis=(-2, -1))  # [T, N]: each particle's first-order d(log det)
    assert np.abs(change).max() < 1e-12 * np.abs(step).max()
    _, full = _gradient_and_one_step(dataclasses.replace(cfg, step_volume="full"), st)
    assert np.abs(full - step).max() > 1e-6
    with pytest.raises(ValueError, match="step_volume"):
        cfg64(step_volume="body")
    # a share beta of the projection: d - beta (<d, n> / <n, n>) n, between the two steps
    cfg = dataclasses.replace(cfg, step_volume_share=0.25)
    g, step = _gradient_and_one_step(cfg, st)
    d = g * w[None, :, None, None]
    d = d - 0.25 * (d - _volume_projection(d, st.F, C))
    np.testing.assert_allclose(step, -1e-4 * 2.0 * d / np.sqrt(np.mean(d * d)), rtol=1e-8, atol=1e-14)
    with pytest.raises(ValueError, match="step_volume_share"):
        cfg64(step_volume_share=1.5)


def test_frame_end_last_forward_takes_the_steps_change_of_volume_where_it_acts(state):
    """With frame_end "last_forward" the step acts from the next frame, which starts at the
    rollout's end: the volume projection is taken at that F (the NumPy projection at F_T), not at
    the frame's start."""
    cfg = cfg64(substeps=3, optimizer="normalized_gd", learning_rate=1e-4, step_clip=0.0, step_per_volume=False,
                step_volume="particle", step_volume_share=1.0, frame_end="last_forward")
    g, control = _gradient_and_one_step(cfg, state)
    s = make(cfg, state, reuse=True)
    s.reset_control()
    s.load_state(state)
    F_end = s.rollout().F  # the zero control's rollout: where the frame ended
    C = np.zeros_like(g)
    steps = {}
    for at, F in (("end", F_end), ("start", state.F)):
        d = _volume_projection(g, F, C)
        steps[at] = -cfg.step_size * d / np.sqrt(np.mean(d * d))
    np.testing.assert_allclose(control, steps["end"], rtol=1e-7, atol=1e-14)
    # three substeps move F a little, but the two projections differ far beyond that tolerance
    assert np.abs(steps["end"] - steps["start"]).max() > 1e-5 * np.abs(steps["end"]).max()


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
    (physmorph.morph.injection, combined in place by MPMSolver.combine_calibration), instead of a forward
    and backward of its own: the two gradients equal separate backwards', their combination is
    their NumPy sum, the controls and losses after two iterations equal the plain path's, and a
    gradient for a stale rollout is refused."""
    from physmorph.morph.injection import calibrate_injection

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
        pair_inj, pair_mass = s.control_gradient(), s.control_field.ctrl_base.to_numpy()
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
    physmorph.plasticity.step.rebase_control, in place, for a per-substep control."""
    from physmorph.plasticity.step import rebase_control

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
    assert s.control_field.adam_m is None and set(saved) == {"control", "adam_step"}
    assert saved["control"].dtype == s.model.np_dtype
    ctrl_a = (s.optimize_control(iters=1), s.control())[1]
    s.reset_control()
    s.set_optimizer_state(saved)
    s.load_state(state)
    s.optimize_control(iters=1)
    np.testing.assert_array_equal(s.control(), ctrl_a)
