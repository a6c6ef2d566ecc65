"""The destination pull (MorphConfig.destination_pull): each particle far from its transport
destination anchored there in the physics loss, strays keeping the stray pull's anchor."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import h5py
import numpy as np

from physmorph.morph.loop import morph_config, run_morph
from physmorph.morph.steering import StrayPull, destination_pull_anchors
from physmorph.morph.targets import load_target
from physmorph.mpm.solver import MPMSolver
from physmorph.plasticity.transport import destinations_in_grid_mass


class _Recorder:
    """Stands in for the solver: keeps what the pulls hand it."""

    def set_position_anchors(self, anchor, weight):
        self.anchor, self.weight = anchor, weight


def test_destination_pull_anchors_the_far_particles_and_leaves_strays_their_own(tiny):
    """A particle more than destination_pull_onset cells from its destination gets it as anchor
    with the weight destination_pull m_p / (rho dx^3) / dx^2; a nearer one none; a stray (outside
    the target, past the stray pull's onset) keeps the stray pull's anchor and weight; with
    destination_pull 0, or outside the full method or the transport map, the pull is off."""
    cfg, d = tiny
    target = load_target(d / "t_bunny.h5")
    g = target.grid
    filled = np.argwhere(target.grid_mass > 0)
    inside = (g.lo + filled[len(filled) // 2] * g.dx).astype(float)
    empty = (g.lo + np.argwhere(target.grid_mass == 0)[0] * g.dx).astype(float)
    x = np.stack([inside, inside, empty])  # far from its destination, near it, a stray
    destination = x + np.array([[3.0, 0, 0], [0, 1.0, 0], [0, 0, 4.0]]) * g.dx
    mc = dataclasses.replace(morph_config(cfg, "iso_bunny_full"), stray_pull=2.0, stray_pull_onset=1.0,
                             destination_pull=0.5, destination_pull_onset=2.0)
    mass = np.full(3, 0.25)
    unit = 0.25 / (mc.mpm.density * g.dx ** 3) / g.dx ** 2
    anchor, w = destination_pull_anchors(x, mass, destination, g, mc)
    np.testing.assert_allclose(w, [0.5 * unit, 0.0, 0.5 * unit])
    np.testing.assert_array_equal(anchor, destination)

    pulls, solver = StrayPull(mc), _Recorder()
    assert pulls.on and pulls.to_destination
    st = SimpleNamespace(x=x, mass=mass)  # what the pulls read of the state
    near_d = np.array([0.0, 0.0, 5.0]) * g.dx
    pulls.anchor(solver, st, near_d, np.zeros(3, int), target, destination)
    np.testing.assert_allclose(solver.weight, [0.5 * unit, 0.0, 2.0 * unit])
    np.testing.assert_array_equal(solver.anchor[0], destination[0])
    np.testing.assert_array_equal(solver.anchor[2], target.surface_points[0])

    for off in (dataclasses.replace(mc, destination_pull=0.0), dataclasses.replace(mc, method="f_inject"),
                dataclasses.replace(mc, plasticity=dataclasses.replace(mc.plasticity, correspondence="nearest"))):
        assert not StrayPull(off).to_destination


def test_a_run_with_the_destination_pull_anchors_the_plans_destinations_and_nears_them(tiny, monkeypatch):
    """In a run the anchors are the plasticity's transport destinations of the source at rest
    (the plan the plasticity uses), and a strong pull brings the body nearer them than the run
    without it (the mean distance falls by more in its 3 frames). Slow (~10 s): two tiny full morphs of 3 frames."""
    cfg, d = tiny
    handed = []
    real = MPMSolver.set_position_anchors

    def recording(self, anchor, weight=None):
        handed.append((None if anchor is None else np.array(anchor), None if weight is None else np.array(weight)))
        return real(self, anchor, weight)

    monkeypatch.setattr(MPMSolver, "set_position_anchors", recording)
    # without the push along the plan, which carries both runs onto the same destinations
    base = dataclasses.replace(morph_config(cfg, "iso_bunny_full"), progress=False, release_frames=0, frames=3,
                               stray_pull=0.0, plan_push_speed=0.0)
    with h5py.File(d / "p_iso.h5", "r") as f:
        x0, mass = f["x"][()].astype(np.float64), f["mass"][()].astype(np.float64)
    target = load_target(d / "t_bunny.h5")
    T = destinations_in_grid_mass(x0, mass, target.grid_mass, target.grid, base.plasticity.transport_blur,
                                  projection=base.plasticity.transport_projection)
    distance = {}
    for name, pull in (("without", 0.0), ("with", 50.0)):
        handed.clear()
        out = d / f"destination_pull_{name}.h5"
        run_morph(d / "p_iso.h5", d / "t_bunny.h5", out,
                  dataclasses.replace(base, destination_pull=pull, destination_pull_onset=0.0), name=out.stem)
        with h5py.File(out, "r") as f:
            x = f["states"][sorted(f["states"])[-1]]["x"][()].astype(np.float64)
        distance[name] = float(np.sum(mass * np.linalg.norm(x - T, axis=1)) / mass.sum())
        if pull:
            assert handed, "the pull set no anchors"
            anchor, weight = handed[-1]
            moved = weight > 0
            assert moved.mean() > 0.9  # onset 0: every particle not at its destination
            np.testing.assert_allclose(anchor[moved], T[moved], rtol=0, atol=1e-9)
        else:
            assert all(a is None or not np.any(w) for a, w in handed)
    start = float(np.sum(mass * np.linalg.norm(x0 - T, axis=1)) / mass.sum())
    assert start - distance["with"] > 1.3 * (start - distance["without"]), (start, distance)
