"""Optimal-transport correspondences between a source's particles and a target's mass (not in the
paper; plasticity.correspondence = "transport", docs/study/log.md part 15).

The paper's plasticity (section 3.4) moves each particle's rest state toward its nearest target
surface point. From a far source that map is many-to-one: a cow's legs and head all project onto
the bunny's nearest surface, none onto its ears, and the projection of a volume onto a surface is
a compression. An entropic optimal transport plan between the source's mass (the particles at
rest) and the target's (its grid mass) gives every material point a destination instead, with each
destination region receiving its own mass:

    P = argmin_P <P, C> - eps H(P),  P 1 = a,  P^T 1 = b,  C_ij = |x_i - y_j|^2 / 2,

a_i the particle masses and b_j the target node masses (both normalised to 1), solved by
log-domain Sinkhorn iterations with eps decreasing geometrically from the squared diameter to
blur^2 (eps scaling); each particle's destination is the barycentric projection
T_i = sum_j P_ij y_j / a_i.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from physmorph.grid import Grid, bspline_weights, splat_mass


# Rows of the cost matrix handled at once, and the matrix size up to which its blocks are kept
# between iterations (float32: 2^25 entries = 128 MB) rather than recomputed: the plan never holds
# an N x M array, so a 64^3 grid (~25K x 25K nodes) needs ~100 MB, not 2.5 GB.
BLOCK_ENTRIES = 1 << 22
CACHE_ENTRIES = 1 << 25


def _cost_blocks(X: torch.Tensor, Y: torch.Tensor):  # X [N, 3], Y [M, 3] -> iterator of (rows, C [n, M])
    """C_ij = |x_i - y_j|^2 / 2 by blocks of rows (cached when the whole matrix is small)."""
    rows = max(1, BLOCK_ENTRIES // max(len(Y), 1))
    spans = [slice(k, min(k + rows, len(X))) for k in range(0, len(X), rows)]
    cache = [None] * len(spans) if len(X) * len(Y) <= CACHE_ENTRIES else None

    def blocks():
        for b, sl in enumerate(spans):
            C = cache[b] if cache is not None else None
            if C is None:
                C = 0.5 * torch.cdist(X[sl], Y) ** 2
                if cache is not None:
                    cache[b] = C
            yield sl, C
    return blocks


def sinkhorn_potentials(X: torch.Tensor,  # [N, 3]
                        Y: torch.Tensor,  # [M, 3]
                        log_a: torch.Tensor,  # [N]
                        log_b: torch.Tensor,  # [M]
                        eps_schedule: list[float]) -> tuple[torch.Tensor, torch.Tensor, object]:
    """Log-domain Sinkhorn: for each eps of the schedule one pair of updates
    f_i = -eps logsumexp_j(log b_j + (g_j - C_ij) / eps), g_j = -eps logsumexp_i(log a_i + (f_i - C_ij) / eps),
    the cost taken by blocks of rows (the column sums merged with logaddexp). Returns f, g and the
    cost's block iterator."""
    blocks = _cost_blocks(X, Y)
    f = torch.zeros_like(log_a)
    g = torch.zeros_like(log_b)
    for eps in eps_schedule:
        for sl, C in blocks():
            f[sl] = -eps * torch.logsumexp(log_b[None, :] + (g[None, :] - C) / eps, dim=1)
        acc = torch.full_like(log_b, -float("inf"))
        for sl, C in blocks():
            acc = torch.logaddexp(acc, torch.logsumexp(log_a[sl, None] + (f[sl, None] - C) / eps, dim=0))
        g = -eps * acc
    return f, g, blocks


def transport_destinations(x: np.ndarray,  # [N, 3] source particles
                           a: np.ndarray,  # [N] their masses (> 0)
                           y: np.ndarray,  # [M, 3] target samples (e.g. grid nodes)
                           b: np.ndarray,  # [M] their masses (>= 0; zero entries are dropped)
                           blur: float,
                           iters: int = 40,
                           extra_iters: int = 10,
                           dtype: torch.dtype = torch.float32) -> np.ndarray:  # [N, 3]
    """T_i = sum_j P_ij y_j / a_i for the entropic plan of the module docstring, eps going from the
    squared diameter of the two clouds to blur^2 over ``iters`` Sinkhorn steps, then ``extra_iters``
    more at blur^2. On the CPU in ``dtype`` (float32: the log-domain potentials need ~1e-4 of
    relative precision); the cost matrix is handled by blocks of rows (BLOCK_ENTRIES)."""
    x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
    y = np.asarray(y, dtype=np.float64).reshape(-1, 3)
    a = np.asarray(a, dtype=np.float64).reshape(-1)
    b = np.asarray(b, dtype=np.float64).reshape(-1)
    if len(a) != len(x) or len(b) != len(y):
        raise ValueError(f"transport_destinations: {len(x)} points with {len(a)} masses, {len(y)} targets with {len(b)} masses")
    if not (a > 0).all() or not (b >= 0).all() or not b.sum() > 0 or not blur > 0:
        raise ValueError("transport_destinations needs positive source masses, non-negative target masses "
                         f"with a positive sum, and blur > 0 (got blur={blur})")
    keep = b > 0
    y, b = y[keep], b[keep]
    X, Y = torch.from_numpy(x).to(dtype), torch.from_numpy(y).to(dtype)
    log_a = torch.log(torch.from_numpy(a / a.sum())).to(dtype)
    log_b = torch.log(torch.from_numpy(b / b.sum())).to(dtype)
    lo = np.minimum(x.min(0), y.min(0))
    hi = np.maximum(x.max(0), y.max(0))
    eps0 = max(float(((hi - lo) ** 2).sum()), blur ** 2)
    eps1 = blur ** 2
    schedule = [math.exp(math.log(eps0) + (math.log(eps1) - math.log(eps0)) * k / max(iters - 1, 1)) for k in range(iters)]
    schedule += [eps1] * extra_iters
    f, g, blocks = sinkhorn_potentials(X, Y, log_a, log_b, schedule)
    T = torch.empty_like(X)
    for sl, C in blocks():  # P_ij = a_i b_j exp((f_i + g_j - C_ij) / eps), row by row
        P = torch.exp(log_a[sl, None] + log_b[None, :] + (f[sl, None] + g[None, :] - C) / eps1)
        T[sl] = (P @ Y) / P.sum(dim=1, keepdim=True)
    return T.numpy().astype(np.float64)


def destinations_in_grid_mass(x: np.ndarray,  # [N, 3] source particles at rest
                              mass: np.ndarray,  # [N]
                              grid_mass: np.ndarray,  # [R, R, R] the target's grid mass
                              grid: Grid) -> np.ndarray:  # [N, 3]
    """Each particle's destination in the target's grid mass, from the plan between the two grid
    masses (the source's splatted: m_I = sum_p w_Ip m_p): transport_destinations from the source's
    non-empty nodes y_I to the target's, blur = one grid cell, gives node displacements
    D_I = T_I - y_I, and a particle moves by their B-spline interpolation,
    T_p = x_p + sum_I w_Ip D_I m_I / sum_I w_Ip m_I (its stencil's nodes all hold mass).
    Node to node, the plan is ~(N / nodes)^2 times cheaper than particle to node."""
    R = grid.res
    if grid_mass.shape != (R, R, R):
        raise ValueError(f"target grid mass has shape {grid_mass.shape}, expected {(R, R, R)}")
    x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
    src = splat_mass(x, mass, grid)
    src_idx = np.argwhere(src > 0)
    tgt_idx = np.argwhere(grid_mass > 0)
    y = grid.lo + grid.dx * src_idx
    T = transport_destinations(y, src[src > 0], grid.lo + grid.dx * tgt_idx, grid_mass[grid_mass > 0], blur=grid.dx)
    D = np.zeros((R, R, R, 3))
    D[tuple(src_idx.T)] = (T - y) * src[src > 0][:, None]  # mass-weighted, divided out below
    base, w = bspline_weights(x, grid)
    num = np.zeros((len(x), 3))
    den = np.zeros(len(x))
    for a in range(3):
        for b in range(3):
            for c in range(3):
                idx = np.clip(base + np.array([a, b, c]), 0, R - 1)
                wt = w[:, 0, a] * w[:, 1, b] * w[:, 2, c]
                num += wt[:, None] * D[idx[:, 0], idx[:, 1], idx[:, 2]]
                den += wt * src[idx[:, 0], idx[:, 1], idx[:, 2]]
    return x + num / den[:, None]
