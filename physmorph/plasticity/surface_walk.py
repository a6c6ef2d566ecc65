"""Each particle's nearest target surface point, found from its nearest of the frame before by a
walk on the surface points' Delaunay graph (the d_i = NN_T(x_i) - x_i of paper section 3.4, eq. 4,
and the mask's and the Chamfer metric's distances).

A point p of a set S is the nearest to x exactly when x lies in p's Voronoi cell, and that cell is
bounded by the bisector planes of p and its Delaunay neighbours alone: p is the nearest when none of
its neighbours is nearer. So a walk that moves to the nearest neighbour while one is strictly nearer
ends at the nearest point, from any start. The particles move a little each frame, so starting
from last frame's answer the paper profile's walks take about 6 steps of ~16 neighbours (511K
particles against 200K points: 0.1 s, against the KD tree's 0.8 s on 2 threads). The distance is
then computed as scipy's KD tree computes it (numpy.linalg.norm of the difference).

The graph is Qhull's Delaunay tetrahedralisation (scipy.spatial.Delaunay) of the points joggled
(Qhull's "QJ": each coordinate moved by ~1e-10 of the extent, the same way on every build). A
letter's flat faces put thousands of points on one plane, a degenerate set whose facets Qhull would
otherwise merge slowly (40K points of the paper's A: 28 s against 1.5 s, and five times longer with
each doubling); joggled, 200K points take 7-11 s on one core, once per run, and ~0.6 GB while built.
The walk then ends at the nearest point of the joggled set, which is the nearest of the points
themselves unless two lie within the joggle of the same distance: at such a near-tie either is a
nearest point, as with the device's search (physmorph.plasticity.nearest). On every paper-scale
target and the default profile's letters, 800K queries each, the walk and a KD-tree query agree bit
for bit; tests/plasticity/test_surface_walk.py holds it to the KD tree, its reference, on curved
and flat-faced surfaces.

The graph pays back where a query costs the KD tree much more than a walk: from WALK_MIN_QUERIES
particles (MorphInputs). :meth:`SurfaceWalk.build` returns None, and the caller keeps the KD tree,
where there are fewer than five points or Qhull fails, where two points lie within SEPARATION_MIN
of the extent (the joggle alone would tell them apart), or where the new walk's audit against the
KD tree finds one other distance.
"""

# No "from __future__ import annotations": Taichi needs the kernel annotations as objects.

from typing import Callable

import numpy as np
import taichi as ti

from physmorph.base.taichi_runtime import ensure_taichi

# Particles from which a run walks instead of querying the KD tree: the paper profile (~0.5M
# particles, 200K surface points) saves ~0.7 s a frame for 7-13 s of Qhull once (beside frame 0);
# the mid profile (35K particles, 20K points) would save 29 ms a frame for 0.7 s, little over a run.
WALK_MIN_QUERIES = 100_000
# The nearest two points may lie no nearer than this share of the set's extent (~1000 times the
# joggle; the paper-scale targets' 200K samples lie 1.5e-6 to 1e-5 of it apart)
SEPARATION_MIN = 1e-8
# Queries a built walk answers against the KD tree before it is used (AUDIT_SCALES of the extent
# from random surface points, from random starts): any other distance and the walk is not used
AUDIT_QUERIES = 20_000
AUDIT_SCALES = (1e-3, 1e-2, 1e-1)


@ti.kernel
def _walk(x: ti.types.ndarray(dtype=ti.f64, ndim=2),  # [N, 3] the queries
          points: ti.types.ndarray(dtype=ti.f64, ndim=2),  # [M, 3]
          first: ti.types.ndarray(ndim=1),  # [M + 1] each point's first neighbour in ``neighbours``
          neighbours: ti.types.ndarray(ndim=1),  # [E] the Delaunay neighbours, point by point
          start: ti.types.ndarray(ndim=1),  # [N] each walk's first point
          nearest: ti.types.ndarray(ndim=1)):  # [N] out: each query's nearest point
    """Steepest descent on the Delaunay graph: from start_i, move to the neighbour q minimising
    |x_i - q|^2 while it is strictly below |x_i - p|^2; the point where none is, is x_i's nearest."""
    for i in range(x.shape[0]):
        xi = ti.Vector([x[i, 0], x[i, 1], x[i, 2]])
        p = start[i]
        e = ti.Vector([points[p, 0], points[p, 1], points[p, 2]]) - xi
        dp = e.dot(e)
        moved = True
        while moved:
            best = p
            for a in range(first[p], first[p + 1]):
                q = neighbours[a]
                f = ti.Vector([points[q, 0], points[q, 1], points[q, 2]]) - xi
                dq = f.dot(f)
                if dq < dp:
                    dp = dq
                    best = q
            moved = best != p
            p = best
        nearest[i] = p


class SurfaceWalk:
    """A fixed point set and its Delaunay graph, for nearest-point queries from known starts."""

    def __init__(self, points: np.ndarray,  # [M, 3]
                 first: np.ndarray,  # [M + 1] int32
                 neighbours: np.ndarray):  # [E] int32
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        self.first = first
        self.neighbours = neighbours

    @classmethod
    def build(cls, points: np.ndarray,  # [M, 3]
              audit: bool = True) -> "SurfaceWalk | None":
        """The walk over ``points``, or None where it cannot be trusted (module docstring). Without
        ``audit`` no Taichi kernel runs (the caller audits with :meth:`passes_audit`)."""
        from scipy.spatial import Delaunay, QhullError, cKDTree

        points = np.ascontiguousarray(points, dtype=np.float64)
        if len(points) < 5:
            return None
        # Two points nearer each other than SEPARATION_MIN of the extent would be told apart by the
        # joggle alone: a walk could stop at one whose twin's side holds the nearest point.
        extent = float(np.ptp(points, axis=0).max())
        tree = cKDTree(points)
        if not tree.query(points, k=2)[0][:, 1].min() > SEPARATION_MIN * extent:
            return None
        try:
            tri = Delaunay(points, qhull_options="QJ")
        except (QhullError, ValueError):
            return None
        if len(tri.coplanar):  # a point left out of every tetrahedron: no walk would reach it
            return None
        first, neighbours = tri.vertex_neighbor_vertices
        del tri
        if np.any(first[1:] == first[:-1]):
            return None
        walk = cls(points, first.astype(np.int32), neighbours.astype(np.int32))
        return walk if not audit or walk.passes_audit() else None

    def passes_audit(self) -> bool:
        """A new walk's audit: AUDIT_QUERIES queries near and around the surface, walked from random
        starts, at the KD tree's distances (the same seed on every build)."""
        from scipy.spatial import cKDTree

        extent = float(np.ptp(self.points, axis=0).max())
        rng = np.random.default_rng(0)
        n = AUDIT_QUERIES // len(AUDIT_SCALES)
        x = np.concatenate([self.points[rng.integers(0, len(self.points), n)] + rng.normal(scale=s * extent, size=(n, 3))
                            for s in AUDIT_SCALES])
        d, _ = self.query(x, rng.integers(0, len(self.points), len(x)))
        return bool(np.array_equal(d, cKDTree(self.points).query(x, k=1)[0]))

    def query(self, x: np.ndarray,  # [N, 3]
              start: np.ndarray,  # [N] each query's first point (last frame's nearest)
              ) -> tuple[np.ndarray, np.ndarray]:  # [N] float64 distances, [N] int64 indices
        """Each x_i's nearest point and its distance, walking from start_i (module docstring)."""
        ensure_taichi()
        x = np.ascontiguousarray(x, dtype=np.float64).reshape(-1, 3)
        start = np.ascontiguousarray(start, dtype=np.int64)
        if start.shape != (len(x),) or (len(start) and (start.min() < 0 or start.max() >= len(self.points))):
            raise ValueError(f"start must hold one index into the {len(self.points)} points per query, got {start.shape}")
        nearest = np.empty(len(x), dtype=np.int64)
        if len(x):
            _walk(x, self.points, self.first, self.neighbours, start, nearest)
        return np.linalg.norm(self.points[nearest] - x, axis=1), nearest


def build_in_background(points: np.ndarray,  # [M, 3]
                        ) -> Callable[[], "SurfaceWalk | None"]:
    """SurfaceWalk.build(points) started on a thread of its own (Qhull lets go of the interpreter,
    so it runs beside the caller's work); returns the call that waits for it and then audits the
    walk in the caller's thread (Taichi's kernels are launched from one thread only)."""
    from concurrent.futures import ThreadPoolExecutor

    pool = ThreadPoolExecutor(1, thread_name_prefix="surface-walk")
    future = pool.submit(SurfaceWalk.build, points, False)
    pool.shutdown(wait=False)

    def result() -> "SurfaceWalk | None":
        walk = future.result()
        return walk if walk is not None and walk.passes_audit() else None

    return result
