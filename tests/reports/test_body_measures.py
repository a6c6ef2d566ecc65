"""The body in 3D (physmorph.reports.export.body): the mass outside the largest connected body, a
closed surface's components and genus, the body's genus in voxels of half a cell, the
95th-percentile surface distance and the roughness, each on shapes whose answer is known."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from physmorph.reports.export.body import (BODY_PITCH_DX, body_genus, components_and_genus,
                                           largest_body_outside_share, roughness_percent, solid_topology,
                                           surface_distance_p95, voxel_topology)


def test_the_mass_outside_the_largest_body_is_the_torn_off_pieces():
    rng = np.random.default_rng(0)
    body = rng.uniform(-3, 3, (4000, 3))  # ~18 particles a cell: one connected body
    piece = rng.uniform(8, 9, (200, 3))  # a torn-off piece well apart from it
    spray = np.array([[20.0, 0, 0], [0, 20.0, 0]])  # two lone particles
    x = np.vstack([body, piece, spray])
    w = np.ones(len(x))
    assert largest_body_outside_share(body, np.ones(len(body)), 1.0) == 0.0
    w_one = np.random.default_rng(3).uniform(0.1, 1.0, len(body))  # a sum that rounds: still exactly 0
    assert largest_body_outside_share(body, w_one, 1.0) == 0.0
    assert largest_body_outside_share(x, w, 1.0) == pytest.approx(202 / len(x))
    w[:len(body)] = 0.01  # by weight: the heavy piece is then the largest body
    assert largest_body_outside_share(x, w, 1.0) == pytest.approx(1 - 200 / (40 + 202))


def test_a_particle_in_a_neighbouring_cell_belongs_to_the_body_and_two_cells_away_does_not():
    x = np.array([[0.5, 0.5, 0.5], [1.5, 1.5, 1.5], [3.5, 1.5, 1.5]])  # diagonal neighbour, then a gap of one cell
    assert largest_body_outside_share(x, np.ones(3), 1.0) == pytest.approx(1 / 3)


def test_genus_and_components_of_closed_surfaces():
    sphere = trimesh.creation.icosphere(3, 5.0)
    torus = trimesh.creation.torus(5.0, 1.5)
    assert components_and_genus(sphere) == (1, 0)
    assert components_and_genus(torus) == (1, 1)
    both = trimesh.util.concatenate([sphere, torus.copy().apply_translation([20.0, 0, 0])])
    assert components_and_genus(both) == (2, 1)
    two_holes = trimesh.util.concatenate([torus, torus.copy().apply_translation([0, 0, 10.0])])
    assert components_and_genus(two_holes) == (2, 2)
    open_sphere = trimesh.Trimesh(sphere.vertices, sphere.faces[1:], process=False)  # a face missing
    assert components_and_genus(open_sphere) == (-1, -1)


def test_pieces_tunnels_and_cavities_of_voxel_solids():
    ring = np.zeros((8, 8, 3), bool)
    ring[1:7, 1:7, :] = True
    ring[3:5, 3:5, :] = False  # a square hole through the block: one tunnel
    assert solid_topology(ring) == (1, 1, 0)
    hollow = np.zeros((7, 7, 7), bool)
    hollow[1:6, 1:6, 1:6] = True
    hollow[3, 3, 3] = False  # a closed void: one cavity, no tunnel
    assert solid_topology(hollow) == (1, 0, 1)
    two = np.zeros((9, 4, 4), bool)
    two[0:3], two[5:9] = True, True
    assert solid_topology(two) == (2, 0, 0)
    # a diagonal contact is a 26-connection: two cubes meeting at an edge are one piece
    edge = np.zeros((4, 4, 2), bool)
    edge[0:2, 0:2], edge[2:4, 2:4] = True, True
    assert solid_topology(edge) == (1, 0, 0)


def _slab_with_hole(hole_tenths: int, offset: int) -> trimesh.Trimesh:
    """A 3.8 x 3.8 x 1 slab with a square hole ``hole_tenths`` tenths wide through it, ``offset`` tenths
    off its middle, drawn by marching cubes on voxels of 0.1."""
    solid = np.zeros((40, 40, 12), bool)
    solid[1:39, 1:39, 1:11] = True
    lo = 20 - hole_tenths // 2 + offset
    solid[lo:lo + hole_tenths, lo:lo + hole_tenths, :] = False
    return trimesh.voxel.VoxelGrid(solid).marching_cubes.apply_scale(0.1)


def test_the_body_counts_a_tunnel_a_cell_wide_and_not_one_narrower_than_half_a_cell():
    assert BODY_PITCH_DX == 0.5
    torus = trimesh.creation.torus(5.0, 1.5)  # a hole 7 across
    assert body_genus(torus, 1.0) == 1 and body_genus(trimesh.creation.icosphere(3, 5.0), 1.0) == 0
    for offset in range(4):  # wherever the voxels fall against the hole
        narrow, wide = _slab_with_hole(5, offset), _slab_with_hole(12, offset)
        assert components_and_genus(narrow) == components_and_genus(wide) == (1, 1)  # the surfaces have both
        assert body_genus(narrow, 1.0) == 0  # half a cell: not the body's
        assert body_genus(wide, 1.0) == 1
        assert body_genus(narrow, 0.5) == 1  # in a grid twice as fine the same hole is a cell wide
    open_sphere = trimesh.creation.icosphere(3, 5.0)
    open_sphere = trimesh.Trimesh(open_sphere.vertices, open_sphere.faces[1:], process=False)
    assert body_genus(open_sphere, 1.0) == -1


def test_the_95th_percentile_distance_sees_a_missing_part_the_mean_hides():
    rng = np.random.default_rng(1)
    target = rng.normal(size=(4000, 3))
    target /= np.linalg.norm(target, axis=1, keepdims=True)  # points on the unit sphere
    assert surface_distance_p95(target, target, 1.0) == 0.0
    assert surface_distance_p95(1.5 * target, target, 0.5) == pytest.approx(1.0, rel=1e-9)  # 0.5 apart: 1 cell
    missing = target[target[:, 2] < 0.6]  # a cap of the target missing from the body
    far = surface_distance_p95(missing, target, 1.0)
    mean_ab = np.mean(np.min(np.linalg.norm(target[:, None] - missing[None, ::4], axis=2), axis=1))
    assert far > 2.5 * mean_ab and far > 0.1


def test_roughness_is_zero_for_a_smooth_body_and_grows_with_lumps():
    rng = np.random.default_rng(2)
    sphere = trimesh.creation.icosphere(4, 5.0)
    assert abs(roughness_percent(sphere)) < 0.1
    lumpy = sphere.copy()
    lumpy.vertices = lumpy.vertices * (1 + 0.03 * rng.normal(size=(len(lumpy.vertices), 1)))
    lumpier = sphere.copy()
    lumpier.vertices = lumpier.vertices * (1 + 0.06 * rng.normal(size=(len(lumpier.vertices), 1)))
    assert 1.0 < roughness_percent(lumpy) < roughness_percent(lumpier)


def _legs(gap_tenths: int) -> trimesh.Trimesh:
    """Two 1 x 1 x 4 legs joined by a 3 x 1 x 1 hip, their feet ``gap_tenths`` tenths apart and the
    slit between them widening to 1.0 above, drawn by marching cubes on voxels of 0.1: no tunnel."""
    solid = np.zeros((34, 14, 54), bool)
    solid[2:32, 2:12, 42:52] = True  # the hip
    solid[2:12, 2:12, 2:42] = True  # the left leg
    solid[12 + gap_tenths:22 + gap_tenths, 2:12, 2:12] = True  # the right foot, close to the left
    solid[22:32, 2:12, 12:42] = True  # the right leg, a slit of 1.0 from the left
    return trimesh.voxel.VoxelGrid(solid).marching_cubes.apply_scale(0.1)


def test_legs_that_nearly_touch_make_no_tunnel_where_the_voxels_close_the_gap_between_them():
    for gap in (2, 3):  # the feet 0.2-0.3 apart: closed in voxels of 0.5, the slit above 1.0 open
        legs = _legs(gap)
        assert components_and_genus(legs) == (1, 0)
        assert voxel_topology(legs, BODY_PITCH_DX * 1.0)[1] == 1  # the solid alone would count the loop ...
        assert body_genus(legs, 1.0) == 0  # ... that the surface does not have
