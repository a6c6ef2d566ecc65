"""Spray put back into the body between frames (MorphConfig.reabsorb_strays, physmorph.morph.reabsorb)."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import h5py
import numpy as np

import physmorph.morph.reabsorb as reabsorb
from physmorph.base.grid import Grid
from physmorph.morph.loop import morph_config, run_morph
from physmorph.morph.reabsorb import SPRAY_PIECE_SHARE, detached_pieces, reabsorb_spray
from physmorph.morph.targets import load_target
from physmorph.mpm.state import ParticleState
from physmorph.records.runfile import read_metrics


def _lattice(lo, hi, h):  # [M, 3] points of a lattice of spacing h in the box [lo, hi]
    axes = [np.arange(a, b + 1e-9, h) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def _scene():
    """A block body (inside a box target), a two-particle spray cluster far outside the target, a
    detached particle inside the target, and a detached slab outside holding > SPRAY_PIECE_SHARE."""
    grid = Grid(32)  # domain [0, 16], dx 0.5
    dx = grid.dx
    body = _lattice((5.0, 5.0, 5.0), (9.0, 9.0, 9.0), 0.25)
    spray = np.array([[13.0, 7.0, 7.0], [13.2, 7.0, 7.0]])
    inside = np.array([[7.0, 7.0, 11.0]])  # detached, but in the target
    slab = _lattice((7.0, 12.0, 5.0), (8.0, 12.5, 9.0), 0.25)  # detached, outside, but a piece of the body
    x = np.concatenate([body, spray, inside, slab])
    n = len(x)
    grid_mass = np.zeros((grid.res,) * 3)
    node = np.rint((_lattice((4.0, 4.0, 4.0), (10.0, 10.0, 12.0), dx) - grid.lo) / dx).astype(int)
    grid_mass[tuple(node.T)] = 1.0  # the target: the box [4, 10] x [4, 10] x [4, 12]
    faces = _lattice((4.0, 4.0, 4.0), (10.0, 10.0, 12.0), 0.25)
    on_face = np.isclose(faces, [4.0, 4.0, 4.0]).any(axis=1) | np.isclose(faces, [10.0, 10.0, 12.0]).any(axis=1)
    target = SimpleNamespace(grid=grid, grid_mass=grid_mass, surface_points=faces[on_face])
    rng = np.random.default_rng(0)
    st = ParticleState(x=x, v=rng.normal(size=(n, 3)), F=np.eye(3) + 0.1 * rng.normal(size=(n, 3, 3)),
                       C=rng.normal(size=(n, 3, 3)), Fp=np.eye(3) + 0.05 * rng.normal(size=(n, 3, 3)),
                       mass=rng.uniform(0.5, 1.5, n), volume=rng.uniform(0.5, 1.5, n))
    from scipy.spatial import cKDTree

    d, i = cKDTree(target.surface_points).query(x)
    parts = {"body": np.arange(len(body)), "spray": len(body) + np.arange(2), "inside": np.array([len(body) + 2]),
             "slab": len(body) + 3 + np.arange(len(slab))}
    return st, d, i, target, parts


def test_only_small_detached_pieces_count_as_spray():
    st, _, _, target, parts = _scene()
    assert st.mass[parts["slab"]].sum() > SPRAY_PIECE_SHARE * st.mass.sum()
    for links in ("corners", "faces"):  # the scene's pieces are apart by more than a cell either way
        detached = detached_pieces(st.x, st.mass, target.grid.dx, links)
        assert np.flatnonzero(detached).tolist() == sorted(parts["spray"].tolist() + parts["inside"].tolist())


def test_a_bead_hanging_on_by_a_corner_is_spray_only_when_cells_link_through_faces():
    """spray_links "faces": a bead whose cell touches the body's only at a corner (and one touching it
    by an edge) is a piece of its own and, outside the target, is put back; "corners" (26-connected)
    keeps both on the body."""
    st, _, _, target, parts = _scene()
    dx = target.grid.dx
    top = st.x[parts["body"]].max(axis=0)  # 9.0: the body's last cells are [9, 9.5)
    corner_bead = top + 1.5 * dx  # in the next cell along the diagonal
    edge_bead = np.array([top[0] + 1.5 * dx, 7.0, top[2] + 1.5 * dx])  # across an edge
    x = np.concatenate([st.x, [corner_bead, edge_bead]])
    beads = [len(st.x), len(st.x) + 1]
    cells = np.floor((x - x.min(axis=0)) / dx)
    for c in cells[beads]:  # neither bead shares a cell or a face with the body; each touches it by a corner or an edge
        off = np.abs(cells[parts["body"]] - c)
        assert off.max(axis=1).min() == 1 and (off.sum(axis=1)[off.max(axis=1) == 1] >= 2).all()
    n = len(x)
    grown = ParticleState(x=x, v=np.zeros((n, 3)), F=np.tile(np.eye(3), (n, 1, 1)), C=np.zeros((n, 3, 3)),
                          Fp=np.tile(np.eye(3), (n, 1, 1)), mass=np.concatenate([st.mass, [1.0, 1.0]]),
                          volume=np.concatenate([st.volume, [1.0, 1.0]]))
    assert not detached_pieces(x, grown.mass, dx, "corners")[beads].any()
    assert detached_pieces(x, grown.mass, dx, links="faces")[beads].all()
    # a target the body fills ([5, 9]^3), so the beads lie outside it
    grid = target.grid
    node = np.rint((_lattice((5.0, 5.0, 5.0), (9.0, 9.0, 9.0), dx) - grid.lo) / dx).astype(int)
    grid_mass = np.zeros((grid.res,) * 3)
    grid_mass[tuple(node.T)] = 1.0
    box = st.x[parts["body"]]
    faces = box[np.isclose(box, 5.0).any(axis=1) | np.isclose(box, 9.0).any(axis=1)]
    tight = SimpleNamespace(grid=grid, grid_mass=grid_mass, surface_points=faces)
    from scipy.spatial import cKDTree

    d, i = cKDTree(faces).query(x)
    spray = sorted(parts["spray"].tolist() + parts["inside"].tolist())  # the detached particles outside this target
    assert reabsorb_spray(grown, d, i, tight, onset_cells=0.0, links="corners").moved.tolist() == spray
    assert reabsorb_spray(grown, d, i, tight, onset_cells=0.0, links="faces").moved.tolist() == spray + beads


def test_the_spray_joins_the_body_with_its_state_and_keeps_its_mass():
    """Only the detached particles outside the target move: next to the body particle nearest their
    target surface point (half a cell from it, toward that point), taking its v, C, F, Fp; mass and
    volume unchanged; afterwards no detached piece is left outside the target."""
    st, d, i, target, parts = _scene()
    r = reabsorb_spray(st, d, i, target, onset_cells=1.0, links="faces")
    assert r.moved.tolist() == parts["spray"].tolist()
    np.testing.assert_allclose(r.mass_share, st.mass[parts["spray"]].sum() / st.mass.sum(), rtol=1e-15)
    still = np.setdiff1d(np.arange(st.n), r.moved)
    for k in ("x", "v", "F", "C", "Fp"):
        np.testing.assert_array_equal(getattr(r.state, k)[still], getattr(st, k)[still])
    np.testing.assert_array_equal(r.state.mass, st.mass)
    np.testing.assert_array_equal(r.state.volume, st.volume)
    body = parts["body"]
    aim = target.surface_points[i[r.moved]]
    for p, s in zip(r.moved, aim):
        b = body[np.argmin(np.linalg.norm(st.x[body] - s, axis=1))]
        expected = st.x[b] + min(0.5 * target.grid.dx, np.linalg.norm(s - st.x[b])) * (s - st.x[b]) / np.linalg.norm(s - st.x[b])
        np.testing.assert_allclose(r.state.x[p], expected, atol=1e-12)
        for k in ("v", "F", "C", "Fp"):
            np.testing.assert_array_equal(getattr(r.state, k)[p], getattr(st, k)[b])
    after = detached_pieces(r.state.x, r.state.mass, target.grid.dx, "faces")
    assert not after[parts["spray"]].any()
    # the spray sat 3 cells outside: an onset past that leaves it where it is
    none = reabsorb_spray(st, d, i, target, onset_cells=8.0, links="faces")
    assert len(none.moved) == 0 and none.mass_share == 0.0 and none.state is st


def test_a_run_puts_a_torn_off_particle_back_and_records_its_share(tiny, monkeypatch):
    """In a tiny full morph with reabsorb_strays a particle thrown far outside the target after each
    frame's plasticity is back within half a cell of a body particle in the committed state, and each
    frame records at least its mass share. Slow (~3 s): a tiny full morph of 2 frames."""
    from scipy.spatial import cKDTree

    cfg, d = tiny
    real = reabsorb.reabsorb_spray
    dx = load_target(d / "t_bunny.h5").grid.dx
    corner = {}

    def throw_then_reabsorb(st, nearest_d, nearest_i, target, onset_cells, links):
        x = st.x.copy()
        x[0] = np.asarray(target.grid.lo) + 2.5 * target.grid.dx  # near the domain's corner: far off the target
        corner["x"] = x[0].copy()
        corner["links"] = links  # the run's own setting reaches the spray test
        nd, ni = nearest_d.copy(), nearest_i.copy()
        nd[0], ni[0] = (v[0] for v in cKDTree(target.surface_points).query(x[:1]))
        return real(dataclasses.replace(st, x=x), nd, ni, target, onset_cells, links)

    monkeypatch.setattr(reabsorb, "reabsorb_spray", throw_then_reabsorb)
    base = dataclasses.replace(morph_config(cfg, "iso_bunny_full"), progress=False, release_frames=0, frames=2,
                               save_every=1)
    out = d / "reabsorb_on.h5"
    run_morph(d / "p_iso.h5", d / "t_bunny.h5", out, dataclasses.replace(base, reabsorb_strays=True, spray_links="corners"),
              name=out.stem)
    assert corner["links"] == "corners"
    m = read_metrics(out)
    with h5py.File(out, "r") as f:
        x_last = f["states"][sorted(f["states"])[-1]]["x"][()].astype(np.float64)
    with h5py.File(d / "p_iso.h5", "r") as f:
        mass = f["mass"][()].astype(np.float64)
    assert np.isnan(m["reabsorbed"][0])
    assert np.all(m["reabsorbed"][1:] >= mass[0] / mass.sum() * (1 - 1e-9))
    assert np.linalg.norm(x_last[1:] - x_last[0], axis=1).min() <= 0.5 * dx + 1e-5
    assert np.linalg.norm(x_last[0] - corner["x"]) > 5 * dx


def test_off_or_outside_the_full_method_nothing_moves_and_the_share_is_nan():
    st, d, i, target, _ = _scene()
    fs = SimpleNamespace(state=st)
    inputs = SimpleNamespace(target=target)
    for cfg in (SimpleNamespace(reabsorb_strays=False, method="full", stray_pull_onset=1.0),
                SimpleNamespace(reabsorb_strays=True, method="f_inject", stray_pull_onset=1.0)):
        assert np.isnan(reabsorb.reabsorb_frame(fs, d, i, inputs, cfg))
        assert fs.state is st
