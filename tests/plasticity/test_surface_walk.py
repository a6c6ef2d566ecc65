"""The surface walk (physmorph.plasticity.surface_walk) against its reference, the KD tree: the same
nearest points and the same distances, bit for bit, from any start, on a curved surface, on
flat faces and on degenerate sets; no walk where Qhull builds no graph (a morph that walks is the
morph that queries the tree: tests/morph/test_morph.py)."""

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from physmorph.plasticity.surface_walk import SurfaceWalk


def _assert_walks_like_the_tree(points, rng, n_queries=20000):
    walk = SurfaceWalk.build(points)
    assert walk is not None
    tree = cKDTree(points)
    lo, hi = points.min(axis=0), points.max(axis=0)
    pad = 0.3 * (hi - lo)
    x = rng.uniform(lo - pad, hi + pad, size=(n_queries, 3))  # inside, near and outside the surface
    x[:n_queries // 10] = points[rng.integers(0, len(points), n_queries // 10)] + rng.normal(scale=1e-3, size=(n_queries // 10, 3))
    d_ref, i_ref = tree.query(x, k=1)
    far_start = rng.integers(0, len(points), len(x))  # from anywhere: the walk crosses the surface
    near_start = tree.query(x + rng.normal(scale=0.02 * float((hi - lo).max()), size=x.shape))[1]  # last frame's
    for start in (far_start, near_start):
        d, i = walk.query(x, start)
        np.testing.assert_array_equal(i, i_ref)
        np.testing.assert_array_equal(d, d_ref)


def test_the_walk_finds_the_kd_trees_nearest_points_on_a_curved_surface():
    rng = np.random.default_rng(0)
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=2.0)
    mesh.vertices[:, 2] *= 0.6  # an ellipsoid: no symmetric ties
    points, _ = trimesh.sample.sample_surface(mesh, 6000, seed=1)
    _assert_walks_like_the_tree(np.asarray(points), rng)


def test_the_walk_finds_the_kd_trees_nearest_points_on_flat_faces():
    """A box's faces and an extruded letter's: thousands of points on one plane, Qhull's degenerate
    case; the walk still ends at the tree's points."""
    rng = np.random.default_rng(2)
    box = trimesh.creation.box(extents=(3.0, 2.0, 1.0))
    points, _ = trimesh.sample.sample_surface(box, 6000, seed=3)
    _assert_walks_like_the_tree(np.asarray(points), rng)


def test_degenerate_point_sets():
    """All on one plane the walk still ends at the tree's points; too few points, or two points
    (nearly) the same, give no walk (the caller keeps the tree)."""
    rng = np.random.default_rng(4)
    flat = np.column_stack([rng.uniform(size=(500, 2)), np.zeros(500)])
    _assert_walks_like_the_tree(flat, rng)
    pts = rng.uniform(size=(500, 3))
    assert SurfaceWalk.build(pts) is not None
    assert SurfaceWalk.build(pts[:4]) is None
    assert SurfaceWalk.build(np.vstack([pts, pts[:1]])) is None
    assert SurfaceWalk.build(np.vstack([pts, pts[:1] + 1e-12])) is None


def test_a_walk_that_disagrees_with_the_tree_is_not_used(monkeypatch):
    """The audit: a walk whose graph misses edges (every other neighbour dropped) ends short of the
    nearest point somewhere, and build gives no walk, nor does the build beside the caller's work."""
    import physmorph.plasticity.surface_walk as sw

    rng = np.random.default_rng(6)
    pts = rng.uniform(size=(2000, 3))
    real = sw.SurfaceWalk.__init__

    def thinned(self, points, first, neighbours):
        keep = np.arange(len(neighbours)) % 2 == 0
        counts = np.add.reduceat(keep.astype(np.int32), first[:-1])
        real(self, points, np.concatenate([[0], np.cumsum(counts)]).astype(np.int32), neighbours[keep])

    assert sw.SurfaceWalk.build(pts) is not None
    assert sw.build_in_background(pts)() is not None
    monkeypatch.setattr(sw.SurfaceWalk, "__init__", thinned)
    assert sw.SurfaceWalk.build(pts, audit=False) is not None
    assert sw.SurfaceWalk.build(pts) is None
    assert sw.build_in_background(pts)() is None  # built on its thread, audited in this one


def test_a_start_of_the_wrong_size_or_out_of_range_is_refused():
    rng = np.random.default_rng(5)
    walk = SurfaceWalk.build(rng.uniform(size=(200, 3)))
    x = rng.uniform(size=(10, 3))
    with pytest.raises(ValueError, match="start"):
        walk.query(x, np.zeros(9, dtype=np.int64))
    with pytest.raises(ValueError, match="start"):
        walk.query(x, np.full(10, 200))
