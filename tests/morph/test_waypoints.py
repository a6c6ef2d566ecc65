"""Each frame's physics aimed at a waypoint along the transport plan (MorphConfig.waypoint_cells,
physmorph.morph.waypoints)."""

from __future__ import annotations

import dataclasses

import numpy as np

import physmorph.morph.waypoints as waypoints
from physmorph.base.grid import Grid, splat_mass
from physmorph.morph.loop import morph_config, run_morph
from physmorph.morph.steering import MomentumRestart
from physmorph.morph.waypoints import TO_TARGET, plan_distance, plan_push, waypoint_grid_mass, waypoint_positions, waypoints_on
from physmorph.records.runfile import read_metrics


def test_the_plan_distance_is_the_mass_weighted_mean_in_cells():
    x = np.zeros((2, 3))
    d = np.array([[2.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    assert plan_distance(x, np.array([3.0, 1.0]), d, dx=0.5) == 3.0  # (3 x 4 cells + 1 x 0) / 4


def test_far_particles_step_toward_their_destination_and_near_ones_stay():
    x = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [2.0, 0.0, 0.0]])
    d = np.array([[10.0, 0.0, 0.0], [0.0, 0.0, 1.5], [1.0, 1.0, 1.2], [0.0, 0.0, 0.0]])
    y = waypoint_positions(x, d, step=2.0, onset=0.5)
    np.testing.assert_allclose(y[0], [2.0, 0.0, 0.0])  # 2 along a 10-long way
    np.testing.assert_allclose(y[1], [0.0, 0.0, 1.5])  # 1.5 < 2: onto the destination, not past it
    np.testing.assert_array_equal(y[2], x[2])  # within the onset: where it is
    np.testing.assert_allclose(y[3], [0.0, 0.0, 0.0])


def test_the_waypoint_target_is_the_target_plus_the_moving_particles_flux():
    """m* = max(0, target + m(y) - m(x)) over the particles that move; where none moves, the target
    itself; the flux keeps the total mass where nothing is clipped."""
    grid = Grid(32)  # domain [-16, 16], dx 1
    rng = np.random.default_rng(0)
    x = rng.uniform(-2.0, 2.0, size=(200, 3))
    mass = rng.uniform(0.5, 1.5, 200)
    d = x.copy()
    d[:50, 0] += 6.0  # 6 cells to go
    target = splat_mass(d, mass, grid)
    m = waypoint_grid_mass(x, mass, d, target, grid, step_cells=2.0, onset_cells=2.0)
    y = x.copy()
    y[:50, 0] += 2.0  # 2 cells
    expected = np.maximum(0.0, target + splat_mass(y[:50], mass[:50], grid) - splat_mass(x[:50], mass[:50], grid))
    np.testing.assert_allclose(m, expected, atol=1e-12)
    assert (m >= 0).all()
    # every particle within the onset: the target, unchanged
    np.testing.assert_array_equal(waypoint_grid_mass(x, mass, d, target, grid, 2.0, onset_cells=7.0), target)
    # a target the flux never drives below zero keeps its total
    roomy = target + 10.0
    np.testing.assert_allclose(waypoint_grid_mass(x, mass, d, roomy, grid, 2.0, 2.0).sum(), roomy.sum(), rtol=1e-12)


def test_the_restart_reads_the_loss_against_the_target_where_waypoints_are_on(tiny):
    cfg, _ = tiny
    base = morph_config(cfg, "iso_bunny_full")
    on = dataclasses.replace(base, waypoint_cells=1.0)
    assert not waypoints_on(base) and waypoints_on(on)
    assert MomentumRestart(base).rise_on == "physics_loss" and MomentumRestart(on).rise_on == TO_TARGET
    assert not waypoints_on(dataclasses.replace(on, method="f_inject"))


def test_a_run_aims_each_frame_at_its_waypoints_and_judges_against_the_target(tiny, monkeypatch):
    """A tiny full morph with waypoints: each frame's physics is given the waypoint target of its
    start state (moved off the target by the plan), then the target itself, whose end-state loss
    the frame records beside the waypoint's physics loss. Slow (~3 s): a tiny full morph of 2 frames."""
    cfg, d = tiny
    base = dataclasses.replace(morph_config(cfg, "iso_bunny_full"), progress=False, release_frames=0, frames=2,
                               waypoint_cells=2.0)
    aims, real = [], waypoints.waypoint_grid_mass

    def recorded(x, mass, destination, target_mass, grid, step, onset):
        m = real(x, mass, destination, target_mass, grid, step, onset)
        aims.append(np.abs(m - target_mass).sum() / target_mass.sum())
        return m

    monkeypatch.setattr(waypoints, "waypoint_grid_mass", recorded)
    out = d / "waypoints_on.h5"
    run_morph(d / "p_iso.h5", d / "t_bunny.h5", out, base, name=out.stem)
    on = read_metrics(out)
    assert len(aims) == 2 and min(aims) > 1e-3  # the plan moved each frame's aim
    assert np.isnan(on[TO_TARGET][0]) and np.isfinite(on[TO_TARGET][1:]).all()
    # the physics loss is the waypoint's, the recorded to-target loss the target's
    assert not np.allclose(on["physics_loss"][1:], on[TO_TARGET][1:], rtol=1e-6)


def test_the_push_carries_far_particles_their_step_over_the_frame():
    x = np.zeros((3, 3))
    d = np.array([[8.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.5]])
    v = plan_push(x, d, length=1.0, onset=0.5, frame_time=0.25)
    np.testing.assert_allclose(v[0], [4.0, 0.0, 0.0])  # 1 unit in 0.25 s
    np.testing.assert_allclose(v[1], [0.0, 4.0, 0.0])  # 1.0 away: onto it, no farther
    np.testing.assert_array_equal(v[2], 0.0)  # within the onset


def test_the_push_backs_off_with_the_settle_phase_step(tiny):
    """FramePlan.pushed(st, share): share of the push (the settle phase's back-off), none at 0."""
    from types import SimpleNamespace

    from physmorph.mpm.state import ParticleState

    cfg, _ = tiny
    full = dataclasses.replace(morph_config(cfg, "iso_bunny_full"), plan_push_speed=1.0, plan_push_onset=1.0)
    grid = SimpleNamespace(dx=0.5)
    plan = waypoints.FramePlan(full, SimpleNamespace(target=SimpleNamespace(grid=grid)))
    # one far, one within the onset (1 cell: 0.5), one just beyond it
    plan._destination = np.array([[8.0, 0.0, 0.0], [0.0, 0.0, 0.4], [0.0, 0.6, 0.0]])
    eye = np.tile(np.eye(3), (3, 1, 1))
    st = ParticleState(x=np.zeros((3, 3)), v=np.ones((3, 3)), F=eye, C=0 * eye, Fp=eye, mass=np.ones(3), volume=np.ones(3))
    frame_time = full.mpm.substeps * full.mpm.dt
    whole, half, none = plan.pushed(st).v, plan.pushed(st, share=0.5).v, plan.pushed(st, share=0.0).v
    np.testing.assert_allclose(whole[0] - 1.0, [1.0 / frame_time, 0.0, 0.0])  # 1 unit over the frame
    np.testing.assert_allclose(half[0] - 1.0, 0.5 * (whole[0] - 1.0))
    np.testing.assert_array_equal(none, st.v)
    np.testing.assert_array_equal(whole[1], st.v[1])  # within the onset: no push
    np.testing.assert_allclose(whole[2] - 1.0, [0.0, 0.6 / frame_time, 0.0])  # beyond it: onto its destination


def test_the_push_outside_the_target_is_its_multiple(tiny):
    """MorphConfig.plan_push_outside: a particle whose nearest grid node holds no target mass is
    pushed that multiple of plan_push_speed; one inside the target's mass the plain speed."""
    from types import SimpleNamespace

    from physmorph.mpm.state import ParticleState

    cfg, _ = tiny
    full = dataclasses.replace(morph_config(cfg, "iso_bunny_full"), plan_push_speed=0.5, plan_push_onset=1.0,
                               plan_push_outside=3.0)
    grid = Grid(32)  # domain [-16, 16], dx 1
    target_mass = np.zeros((32, 32, 32))
    target_mass[16, 16, 16] = 1.0  # the node at the origin
    plan = waypoints.FramePlan(full, SimpleNamespace(target=SimpleNamespace(grid=grid, grid_mass=target_mass)))
    plan._destination = np.array([[8.0, 0.0, 0.0], [8.0, 5.0, 0.0]])
    eye = np.tile(np.eye(3), (2, 1, 1))
    x = np.array([[0.2, 0.0, 0.0], [0.0, 5.0, 0.0]])  # inside the target's node, outside
    st = ParticleState(x=x, v=np.zeros((2, 3)), F=eye, C=0 * eye, Fp=eye, mass=np.ones(2), volume=np.ones(2))
    frame_time = full.mpm.substeps * full.mpm.dt
    v = plan.pushed(st).v
    np.testing.assert_allclose(v[0], [0.5 / frame_time, 0.0, 0.0])
    np.testing.assert_allclose(v[1], [1.5 / frame_time, 0.0, 0.0])
    np.testing.assert_array_equal(waypoints.outside_target(x, target_mass, grid), [False, True])


def test_a_run_with_the_push_starts_each_frame_with_it(tiny, monkeypatch):
    """The physics of each frame is loaded with the frame's start state plus the plan's push (the
    state committed at the frame's end is the solver's). Slow (~3 s): a tiny full morph of 2 frames."""
    cfg, d = tiny
    base = dataclasses.replace(morph_config(cfg, "iso_bunny_full"), progress=False, release_frames=0, frames=2,
                               plan_push_speed=0.5)
    from physmorph.mpm.solver import MPMSolver

    loaded, real_load = [], MPMSolver.load_state
    monkeypatch.setattr(MPMSolver, "load_state", lambda self, st: (loaded.append(st.v.copy()), real_load(self, st))[1])
    pushes, real_push = [], waypoints.plan_push

    def recorded(*a, **k):
        pushes.append(real_push(*a, **k))
        return pushes[-1]

    monkeypatch.setattr(waypoints, "plan_push", recorded)
    out = d / "push_on.h5"
    run_morph(d / "p_iso.h5", d / "t_bunny.h5", out, base, name=out.stem)
    assert len(pushes) == 2 and np.abs(pushes[0]).max() > 0
    m = read_metrics(out)
    assert np.isnan(m["plan_distance"][0]) and (m["plan_distance"][1:] > 0).all()
    # frame 1 starts at rest: the solver's first state's velocity is the push itself
    np.testing.assert_array_equal(loaded[0], pushes[0])
