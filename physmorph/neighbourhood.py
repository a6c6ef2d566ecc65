"""The plasticity's neighbourhood sums (paper section 3.4, eq. 4) in one Taichi pass each.

Steps 2 and 3 of physmorph.plasticity, over each particle's k neighbours j in K_i (the KD tree's
query, the particle itself included with r2 = 0):

- :func:`smooth_displacement`: ``iters`` passes of d_i <- mean_{j in K_i} d_j; with ``sources``
  (the neighbour pool, the only particles any K_i holds) every pass but the last updates those
  rows alone, the others keeping their d (what plasticity.knn_smooth_sparse computes).
- :func:`displacement_jacobian_pairs`: J_i = sum_j w_ij (d_j - d_i)(x_j - x_i)^T / n_i with
  w_ij = 1 / r2_ij (0 for the particle itself or a coincident neighbour) and n_i the count of
  nonzero weights (at least 1); ``mode="least_squares"`` right-multiplies by M_i^-1, M_i the same
  sum with x in place of d, regularised by 1e-9 tr(M_i) + 1e-12 on its diagonal.

At the paper's scale (471K particles, k = 64) the sparse-matrix forms took ~1.4 s of a frame. The
pair sums here are summed directly (no expansion of the products, so no cancellation); the
references are plasticity.knn_smooth and plasticity.displacement_jacobian.
"""

# No "from __future__ import annotations": Taichi needs the kernel annotations as objects.

import numpy as np
import taichi as ti

from physmorph.taichi_runtime import ensure_taichi


@ti.kernel
def _mean_rows(d: ti.types.ndarray(dtype=ti.f64, ndim=2),  # [N, 3]
               neighbors: ti.types.ndarray(ndim=2),  # [N, k] int
               rows: ti.types.ndarray(ndim=1),  # [R] the rows to update
               out: ti.types.ndarray(dtype=ti.f64, ndim=2)):  # [N, 3], rows written
    k = neighbors.shape[1]
    for r in range(rows.shape[0]):
        i = rows[r]
        acc = ti.Vector([0.0, 0.0, 0.0], ti.f64)
        for a in range(k):
            j = neighbors[i, a]
            acc += ti.Vector([d[j, 0], d[j, 1], d[j, 2]])
        acc /= ti.cast(k, ti.f64)
        for c in ti.static(range(3)):
            out[i, c] = acc[c]


@ti.kernel
def _jacobian(x: ti.types.ndarray(dtype=ti.f64, ndim=2),  # [N, 3]
              d: ti.types.ndarray(dtype=ti.f64, ndim=2),  # [N, 3]
              neighbors: ti.types.ndarray(ndim=2),  # [N, k] int
              r2: ti.types.ndarray(dtype=ti.f64, ndim=2),  # [N, k]
              out: ti.types.ndarray(dtype=ti.f64, ndim=3),  # [N, 3, 3]
              least_squares: ti.template()):
    k = neighbors.shape[1]
    for i in range(x.shape[0]):
        xi = ti.Vector([x[i, 0], x[i, 1], x[i, 2]])
        di = ti.Vector([d[i, 0], d[i, 1], d[i, 2]])
        J = ti.Matrix.zero(ti.f64, 3, 3)
        M = ti.Matrix.zero(ti.f64, 3, 3)
        count = 0
        for a in range(k):
            if r2[i, a] > 0.0:
                j = neighbors[i, a]
                w = 1.0 / r2[i, a]
                e = ti.Vector([x[j, 0], x[j, 1], x[j, 2]]) - xi
                J += w * (ti.Vector([d[j, 0], d[j, 1], d[j, 2]]) - di).outer_product(e)
                if ti.static(least_squares):
                    M += w * e.outer_product(e)
                count += 1
        n = ti.cast(ti.max(count, 1), ti.f64)
        J /= n
        if ti.static(least_squares):
            M /= n
            M += (1e-9 * M.trace() + 1e-12) * ti.Matrix.identity(ti.f64, 3)
            J = J @ M.inverse()
        for a, b in ti.static(ti.ndrange(3, 3)):
            out[i, a, b] = J[a, b]


def _as_index(neighbors: np.ndarray) -> np.ndarray:
    nb = np.asarray(neighbors)
    return np.ascontiguousarray(nb if nb.dtype in (np.int32, np.int64) else nb.astype(np.int64))


def smooth_displacement(d: np.ndarray,  # [N, 3]
                        neighbors: np.ndarray,  # [N, k] indices
                        iters: int,
                        sources: np.ndarray | None = None) -> np.ndarray:  # [P] the neighbour pool -> [N, 3]
    """``iters`` passes of the neighbourhood mean (module docstring)."""
    ensure_taichi()
    d = np.ascontiguousarray(d, dtype=np.float64)
    nb = _as_index(neighbors)
    n = len(d)
    every = np.arange(n, dtype=nb.dtype)
    pool = None if sources is None or len(sources) == n else np.ascontiguousarray(sources, dtype=nb.dtype)
    for it in range(iters):
        rows = pool if it + 1 < iters and pool is not None else every
        out = d.copy() if rows is pool else np.empty_like(d)
        if n:
            _mean_rows(d, nb, rows, out)
        d = out
    return d


def displacement_jacobian_pairs(x: np.ndarray,  # [N, 3]
                                d: np.ndarray,  # [N, 3]
                                neighbors: np.ndarray,  # [N, k] indices
                                r2: np.ndarray,  # [N, k] squared neighbour distances (0: the particle itself)
                                mode: str = "paper") -> np.ndarray:  # -> [N, 3, 3]
    """The displacement Jacobian of eq. 4 from the pair sums (module docstring)."""
    if mode not in ("paper", "least_squares"):
        raise ValueError(f"jacobian mode must be paper or least_squares, got {mode!r}")
    ensure_taichi()
    x = np.ascontiguousarray(x, dtype=np.float64)
    d = np.ascontiguousarray(d, dtype=np.float64)
    r2 = np.ascontiguousarray(r2, dtype=np.float64)
    nb = _as_index(neighbors)
    if not (len(x) == len(d) == len(nb) == len(r2)) or nb.shape != r2.shape:
        raise ValueError(f"x {x.shape}, d {d.shape}, neighbors {nb.shape} and r2 {r2.shape} must agree")
    out = np.empty((len(x), 3, 3))
    if len(x):
        _jacobian(x, d, nb, r2, out, mode == "least_squares")
    return out
