"""Stage 3: shell-biased volumetric sampling, particle HDF5 and preview."""

import h5py
import numpy as np
import pytest
import trimesh
from scipy.spatial.distance import cdist

from physmorph.base.grid import Grid, splat_mass
from physmorph.records.h5io import StageInputError, stamp_checksum
from physmorph.meshes.errors import MeshError
from physmorph.meshes.shapes import ShapeSpec
from physmorph.meshes.prepare import prepare_mesh
from physmorph.meshes.particles import (load_particles, mean_nn_distance, sample_particles, sample_volume,
                                 stored_particle_count)


@pytest.fixture(scope="module")
def iso_h5(tmp_path_factory):
    path = tmp_path_factory.mktemp("mesh") / "iso.h5"
    prepare_mesh(ShapeSpec("iso", "isosphere", size=14.0), None, path)
    return path


def _round_sphere(radius):
    return trimesh.creation.icosphere(subdivisions=4, radius=radius)  # volume within 0.3 % of the ball


def test_sphere_sampled_volume_matches_ball():
    r = 6.0
    x, vol, is_surface = sample_volume(_round_sphere(r), Grid(32), ppc_surface=2, ppc_interior=1, seed=0)
    ball = 4.0 / 3.0 * np.pi * r ** 3
    assert abs(vol.sum() - ball) < 0.01 * ball
    assert np.all(np.linalg.norm(x, axis=1) <= r + 1e-9)
    assert is_surface.any() and (~is_surface).any()


def test_particle_volumes_and_shell_classification():
    grid, r = Grid(32), 6.0
    mesh = _round_sphere(r)
    x, vol, is_surface = sample_volume(mesh, grid, ppc_surface=3, ppc_interior=1, seed=1, shell_cells=2.0)
    np.testing.assert_allclose(vol[is_surface], grid.dx ** 3 / 27)
    np.testing.assert_allclose(vol[~is_surface], grid.dx ** 3 / 1)
    depth = r - np.linalg.norm(x, axis=1)  # distance below the (near-spherical) surface
    # Shell particles come from cells whose centre is within 2 dx of the surface; interior ones
    # from cells farther away (a particle is at most half a cell diagonal from its cell centre).
    half_diag = 0.5 * np.sqrt(3.0) * grid.dx
    assert depth[is_surface].max() < 2.0 * grid.dx + half_diag + 0.05
    assert depth[~is_surface].min() > 2.0 * grid.dx - half_diag - 0.05
    # Number density: dx^-3 ppc^3 in each region (checked with the shell's mean particle volume).
    assert mean_nn_distance(x[is_surface]) < mean_nn_distance(x[~is_surface])


def test_particles_stay_inside_mesh_and_grid_interior(iso_h5):
    from physmorph.meshes.prepare import load_mesh

    mesh = load_mesh(iso_h5)
    grid = Grid(16)
    x, vol, _ = sample_volume(mesh, grid, 2, 1, seed=0)
    assert mesh.contains(x).all()
    lo, hi = grid.interior_bounds()
    assert x.min() >= lo and x.max() <= hi
    # Inside the interior bounds the B-spline stencil never leaves the grid: P2G conserves mass.
    np.testing.assert_allclose(splat_mass(x, vol, grid).sum(), vol.sum(), rtol=1e-12)


def test_sampling_is_deterministic_for_a_seed():
    mesh, grid = _round_sphere(5.0), Grid(24)
    a = sample_volume(mesh, grid, 2, 1, seed=7)
    b = sample_volume(mesh, grid, 2, 1, seed=7)
    c = sample_volume(mesh, grid, 2, 1, seed=8)
    for u, v in zip(a, b):
        np.testing.assert_array_equal(u, v)
    assert len(a[0]) != len(c[0]) or not np.array_equal(a[0], c[0])


def test_mean_nn_distance_matches_brute_force():
    x = np.random.default_rng(0).normal(size=(300, 3))
    d = cdist(x, x)
    np.fill_diagonal(d, np.inf)
    np.testing.assert_allclose(mean_nn_distance(x), d.min(axis=1).mean(), rtol=1e-12)


def test_sample_particles_writes_consistent_file_and_preview(tmp_path, iso_h5):
    out, png = tmp_path / "iso_16.h5", tmp_path / "iso_16.png"
    summary = sample_particles(iso_h5, out, grid_res=16, ppc_surface=2, ppc_interior=1, density=75.0,
                               sigma_scale=0.7, seed=3, preview_png=png)
    p = load_particles(out)
    assert p.count == summary["count"] > 0
    np.testing.assert_allclose(p.mass, 75.0 * p.volume)
    d = cdist(p.x, p.x)
    np.fill_diagonal(d, np.inf)
    np.testing.assert_allclose(p.sigma0, 0.7 * d.min(axis=1).mean(), rtol=1e-12)
    assert p.grid == Grid(16, -16.0, 16.0)
    with h5py.File(out) as f:
        assert f.attrs["count"] == p.count and f.attrs["n_surface"] == p.is_surface.sum()
        assert f.attrs["shape"] == "iso" and f.attrs["seed"] == 3 and f.attrs["ppc_surface"] == 2
        assert "package_versions" in f.attrs and "wall_time_s" in f.attrs
    np.testing.assert_allclose(summary["sampled_volume"], summary["mesh_volume"], rtol=0.03)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(q.name for q in tmp_path.iterdir()) == ["iso_16.h5", "iso_16.png"]
    assert stored_particle_count(out) == p.count and stored_particle_count(tmp_path / "none.h5") is None


def test_mesh_not_fitting_the_grid_is_named_and_leaves_nothing(tmp_path, iso_h5):
    # res 10: the particle region is [-6.4, 6.4]^3, the isosphere has radius 7.
    with pytest.raises(MeshError, match="iso: mesh bounds .* do not fit"):
        sample_particles(iso_h5, tmp_path / "p.h5", 10, 2, 1, 75.0, preview_png=tmp_path / "p.png")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("kwargs, match", [
    (dict(ppc_surface=0), "ppc_surface"),
    (dict(ppc_interior=1.5), "ppc_interior"),
    (dict(density=-1.0), "density"),
    (dict(sigma_scale=0.0), "sigma_scale"),
    (dict(grid_res=0), "grid_res"),
])
def test_bad_parameters_are_named(tmp_path, iso_h5, kwargs, match):
    args = dict(grid_res=16, ppc_surface=2, ppc_interior=1, density=75.0) | kwargs
    with pytest.raises(ValueError, match=match):
        sample_particles(iso_h5, tmp_path / "p.h5", **args)
    assert list(tmp_path.iterdir()) == []


def test_corrupt_inputs_give_stage_input_error(tmp_path):
    with pytest.raises(StageInputError, match="not found"):
        sample_particles(tmp_path / "absent.h5", tmp_path / "p.h5", 16, 2, 1, 75.0)
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"\x89HDF\r\n\x1a\n truncated")
    with pytest.raises(StageInputError):
        sample_particles(bad, tmp_path / "p.h5", 16, 2, 1, 75.0)
    assert not (tmp_path / "p.h5").exists()
    with h5py.File(tmp_path / "nomass.h5", "w") as f:
        f["x"] = np.zeros((4, 3))
        f["volume"] = np.ones(4)
        f["is_surface"] = np.ones(4, bool)
        stamp_checksum(f)
    with pytest.raises(StageInputError, match="'mass'"):
        load_particles(tmp_path / "nomass.h5")


def test_scatter_add_is_np_add_at():
    """grid.scatter_add (the splats' bincount) against np.add.at, the obviously-correct reference:
    repeated indices summed, indices outside the grid dropped."""
    from physmorph.base.grid import scatter_add

    rng = np.random.default_rng(3)
    shape = (5, 6, 7)
    for lo, hi in ((-3, 8), (0, 3)):  # stencils leaving the grid on every side; all inside
        base = rng.integers(lo, hi, size=(3000, 3))  # many repeated nodes
        w = rng.standard_normal((3000, 3, 3, 3))
        fast, ref = np.zeros(shape), np.zeros(shape)
        scatter_add(fast, base, w)
        dropped = 0
        for a in range(3):
            for b in range(3):
                for c in range(3):
                    idx = base + np.array([a, b, c])
                    ok = np.all((idx >= 0) & (idx < np.array(shape)), axis=1)
                    dropped += (~ok).sum()
                    np.add.at(ref, tuple(idx[ok].T), w[ok, a, b, c])
        assert (dropped > 0) == (lo < 0)
        np.testing.assert_allclose(fast, ref, rtol=1e-12, atol=1e-12)
