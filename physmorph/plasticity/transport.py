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

The iterations run coarse to fine (multiscale Sinkhorn): while the blur sqrt(eps) is several times
a cell of side 2^L blur, both clouds are replaced by their mass-weighted cell centroids, which
changes the plan by far less than its blur and makes an iteration ~64^L times cheaper; at each
switch to a finer level the dual potential g is carried over by one half-update against the
coarser measure. The last iterations, at eps = blur^2, run on the clouds themselves.
"""

from __future__ import annotations

import hashlib
import math

import numpy as np
import torch

from physmorph.base.grid import Grid, bspline_weights, splat_mass


# Rows handled at once: each block of the kernel is a [rows, M] float32 matrix (2^22 entries,
# 16 MB); the plan never holds an N x M array.
BLOCK_ENTRIES = 1 << 22
# Coarse levels: an iteration runs on cells of side 2^L blur while its blur sqrt(eps) is at least
# COARSE_SWITCH cells; no level with fewer than COARSE_MIN_POINTS cells in either cloud.
COARSE_SWITCH = 2.0
COARSE_MIN_POINTS = 64
# Sinkhorn steps of the eps schedule down to blur^2, then steps at blur^2
PLAN_ITERS, PLAN_EXTRA_ITERS = 40, 10
# Exponents below this are raised to it before exp: exp(-80) = 1.8e-35 is still a normal float32,
# and a sum holding exp(0) = 1 cannot see it (n terms add at most n * 1.8e-35, far under float32's
# ulp of 1), while CPU exp takes a slow path on inputs whose result underflows or is subnormal: at
# the 64³ grid ~90 % of a block's entries (the kernel at the finest blur), ten times the time.
EXP_FLOOR = -80.0


def _softmin(P: torch.Tensor,  # [K, 3] the points summed over
             log_w: torch.Tensor,  # [K] their log masses
             potential: torch.Tensor,  # [K] their dual potential
             Q: torch.Tensor,  # [L, 3] the points the result is wanted at
             eps: float) -> torch.Tensor:  # [L]
    """-eps logsumexp_k(log w_k + (potential_k - |p_k - q_l|^2 / 2) / eps) for every q_l: one Sinkhorn
    half-update. With |p - q|^2 / 2 = |p|^2 / 2 + |q|^2 / 2 - p.q it is
    |q_l|^2 / 2 - eps logsumexp_k(h_k + p_k.q_l / eps), h_k = log w_k + (potential_k - |p_k|^2 / 2) / eps,
    one matrix product per block of Q's rows (the coordinates are centred by the caller, which
    keeps the float32 cancellation far below the plan's blur)."""
    h = log_w + (potential - 0.5 * (P * P).sum(1)) / eps
    Pt = P.T / eps
    rows = max(1, BLOCK_ENTRIES // max(len(P), 1))
    out = torch.empty(len(Q), dtype=Q.dtype, device=Q.device)
    for k in range(0, len(Q), rows):
        q = Q[k:k + rows]
        shifted, top = _exp_shifted(torch.addmm(h[None, :], q, Pt))
        out[k:k + rows] = 0.5 * (q * q).sum(1) - eps * (shifted.sum(1).log_() + top)
    return out


def _exp_shifted(B: torch.Tensor,  # [R, K], overwritten
                 ) -> tuple[torch.Tensor, torch.Tensor]:  # exp(B - max) [R, K], max [R]
    """exp(B_rk - max_k B_rk) row by row, in place, each exponent raised to EXP_FLOOR first: the
    factors of logsumexp_k B = log sum_k exp(B - max) + max and of softmax_k B = exp(B - max) /
    sum_k exp(B - max), equal to torch's to float rounding (tests/plasticity/test_transport.py)."""
    top = B.amax(dim=1)
    return B.sub_(top[:, None]).clamp_min_(EXP_FLOOR).exp_(), top


def sinkhorn_potentials(X: torch.Tensor,  # [N, 3]
                        Y: torch.Tensor,  # [M, 3]
                        log_a: torch.Tensor,  # [N]
                        log_b: torch.Tensor,  # [M]
                        eps_schedule: list[float],
                        g0: torch.Tensor | None = None,  # [M] the starting potential g (default 0)
                        ) -> tuple[torch.Tensor, torch.Tensor]:  # f [N], g [M]
    """Log-domain Sinkhorn: for each eps of the schedule one pair of updates
    f_i = -eps logsumexp_j(log b_j + (g_j - C_ij) / eps), g_j = -eps logsumexp_i(log a_i + (f_i - C_ij) / eps),
    C_ij = |x_i - y_j|^2 / 2 (each by :func:`_softmin`)."""
    f = torch.zeros_like(log_a)
    g = torch.zeros_like(log_b) if g0 is None else g0.clone()
    for eps in eps_schedule:
        f = _softmin(Y, log_b, g, X, eps)
        g = _softmin(X, log_a, f, Y, eps)
    return f, g


def _cell_centroids(p: np.ndarray,  # [K, 3]
                    m: np.ndarray,  # [K] masses (> 0)
                    origin: np.ndarray,  # [3]
                    cell: float) -> tuple[np.ndarray, np.ndarray]:  # [Kc, 3], [Kc]
    """The mass-weighted centroid and the total mass of the points in each occupied cube of side
    ``cell`` (cubes aligned at ``origin``)."""
    _, inv = np.unique(np.floor((p - origin) / cell).astype(np.int64), axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    mass = np.bincount(inv, weights=m)
    centroid = np.stack([np.bincount(inv, weights=m * p[:, d]) for d in range(3)], axis=1) / mass[:, None]
    return centroid, mass


def _multiscale_potentials(x: np.ndarray,  # [N, 3]
                           a: np.ndarray,  # [N] normalised masses
                           y: np.ndarray,  # [M, 3]
                           b: np.ndarray,  # [M] normalised masses
                           schedule: list[float],
                           blur: float,
                           dtype: torch.dtype,
                           coarse_switch: float,
                           min_points: int,
                           device: str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:  # f [N], g [M]
    """Sinkhorn over ``schedule`` (decreasing eps), each iteration on the coarsest level L whose cell
    2^L blur is at most sqrt(eps) / coarse_switch (levels stop once a cloud has fewer than
    ``min_points`` cells); between levels g is carried by one half-update against the coarser
    level's f. Returns the finest level's f and g, on ``device``. The points are centred by the
    caller; the levels' centroids and log masses are formed on the CPU in float64, then cast."""
    origin = np.minimum(x.min(0), y.min(0))
    levels = [(x, a, y, b)]
    while coarse_switch > 0:
        cell = blur * 2 ** len(levels)
        xc, ac = _cell_centroids(x, a, origin, cell)
        yc, bc = _cell_centroids(y, b, origin, cell)
        if min(len(xc), len(yc)) < min_points or (len(xc) == len(levels[-1][0]) and len(yc) == len(levels[-1][2])):
            break
        levels.append((xc, ac, yc, bc))

    def level_of(eps: float) -> int:
        fits = [L for L in range(len(levels)) if blur * 2 ** L * coarse_switch <= math.sqrt(eps)]
        return max(fits) if fits else 0

    def tensors(L: int):
        xl, al, yl, bl = levels[L]
        return (torch.from_numpy(xl).to(device, dtype), torch.from_numpy(yl).to(device, dtype),
                torch.log(torch.from_numpy(al)).to(device, dtype), torch.log(torch.from_numpy(bl)).to(device, dtype))

    runs: list[tuple[int, list[float]]] = []  # consecutive iterations on one level
    for i, eps in enumerate(schedule):
        L = level_of(eps) if i < len(schedule) - 1 else 0  # the last on the clouds themselves
        if runs and runs[-1][0] == L:
            runs[-1][1].append(eps)
        else:
            runs.append((L, [eps]))
    g = None
    prev = None
    for L, epss in runs:
        X, Y, log_a, log_b = tensors(L)
        if prev is not None:  # g on this level's targets from the coarser level's f
            Xp, log_ap, fp, eps_p = prev
            g = _softmin(Xp, log_ap, fp, Y, eps_p)
        f, g = sinkhorn_potentials(X, Y, log_a, log_b, epss, g0=g)
        prev = (X, log_a, f, epss[-1])
    return f, g


def _plan_rows(x: np.ndarray,  # [N, 3] source points
               a: np.ndarray,  # [N] their masses (> 0)
               y: np.ndarray,  # [M, 3] target points
               b: np.ndarray,  # [M] their masses (>= 0; zero entries are dropped)
               blur: float, iters: int, extra_iters: int, dtype: torch.dtype, coarse_switch: float,
               min_points: int, device: str):
    """The entropic plan of the module docstring as what its rows need: (X [N, 3], Y [M', 3] the
    targets with mass, both centred, h [M'], Y^T / eps, centre [3]), row i of the plan being
    P_i. / a_i = softmax_j(h_j + x_i . y_j / eps) (the factors of i alone cancel: h_j = log b_j +
    (g_j - |y_j|^2 / 2) / eps)."""
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
    a, b = a / a.sum(), b / b.sum()
    lo = np.minimum(x.min(0), y.min(0))
    hi = np.maximum(x.max(0), y.max(0))
    eps0 = max(float(((hi - lo) ** 2).sum()), blur ** 2)
    eps1 = blur ** 2
    schedule = [math.exp(math.log(eps0) + (math.log(eps1) - math.log(eps0)) * k / max(iters - 1, 1)) for k in range(iters)]
    schedule += [eps1] * extra_iters
    centre = 0.5 * (lo + hi)  # centred coordinates: small |p|^2 / eps in _softmin's expansion
    x, y = x - centre, y - centre
    _, g = _multiscale_potentials(x, a, y, b, schedule, blur, dtype, coarse_switch, min_points, device)
    X, Y = torch.from_numpy(x).to(device, dtype), torch.from_numpy(y).to(device, dtype)
    h = torch.log(torch.from_numpy(b)).to(device, dtype) + (g - 0.5 * (Y * Y).sum(1)) / eps1
    return X, Y, h, Y.T / eps1, centre


def transport_destinations(x: np.ndarray,  # [N, 3] source particles
                           a: np.ndarray,  # [N] their masses (> 0)
                           y: np.ndarray,  # [M, 3] target samples (e.g. grid nodes)
                           b: np.ndarray,  # [M] their masses (>= 0; zero entries are dropped)
                           blur: float,
                           iters: int = PLAN_ITERS,
                           extra_iters: int = PLAN_EXTRA_ITERS,
                           dtype: torch.dtype = torch.float32,
                           coarse_switch: float = COARSE_SWITCH,
                           min_points: int = COARSE_MIN_POINTS,
                           device: str = "cpu") -> np.ndarray:  # [N, 3]
    """T_i = sum_j P_ij y_j / a_i for the entropic plan of the module docstring, eps going from the
    squared diameter of the two clouds to blur^2 over ``iters`` Sinkhorn steps, then ``extra_iters``
    more at blur^2. The iterations and the projection run on the torch ``device`` ("cpu" or
    "cuda") in ``dtype`` (float32: the log-domain potentials need ~1e-4 of relative precision;
    on CUDA in IEEE float32, torch's default, not TF32); the kernel is handled by blocks of rows
    (BLOCK_ENTRIES). The same operations run on either device, so the two differ only by float32
    rounding (tests/plasticity/test_plasticity_device.py). Iterations whose blur is at least
    ``coarse_switch`` cells run on cell centroids (coarse_switch = 0: every iteration on the clouds
    themselves, the single-scale reference)."""
    X, Y, h, Yt, centre = _plan_rows(x, a, y, b, blur, iters, extra_iters, dtype, coarse_switch, min_points, device)
    rows = max(1, BLOCK_ENTRIES // len(Y))
    T = torch.empty_like(X)
    for k in range(0, len(X), rows):
        weights, _ = _exp_shifted(torch.addmm(h[None, :], X[k:k + rows], Yt))
        T[k:k + rows] = weights.div_(weights.sum(1, keepdim=True)) @ Y  # the softmax, then its mean of Y
    return T.cpu().numpy().astype(np.float64) + centre


def transport_draws(x: np.ndarray,  # [N, 3] source points
                    a: np.ndarray,  # [N] their masses (> 0)
                    y: np.ndarray,  # [M, 3] target points
                    b: np.ndarray,  # [M] their masses (>= 0; zero entries are dropped)
                    blur: float,
                    draws: np.ndarray,  # [N] how many targets to draw from each source point's row
                    seed: int = 0,
                    device: str = "cpu") -> np.ndarray:  # [sum(draws), 3]
    """Target points drawn from the rows of the plan of transport_destinations (its defaults): for
    each source point i in turn, draws_i points y_j drawn with probabilities P_ij / a_i, with
    replacement. The draws are made on the CPU from a generator seeded with ``seed`` (the same on
    every call and device); the plan runs on ``device``."""
    draws = np.asarray(draws, dtype=np.int64).reshape(-1)
    if len(draws) != len(np.asarray(x).reshape(-1, 3)) or (draws < 0).any():
        raise ValueError(f"transport_draws: {len(draws)} non-negative draw counts needed, one per source point")
    X, Y, h, Yt, centre = _plan_rows(x, a, y, b, blur, PLAN_ITERS, PLAN_EXTRA_ITERS, torch.float32, COARSE_SWITCH,
                                     COARSE_MIN_POINTS, device)
    generator = torch.Generator().manual_seed(seed)
    targets = Y.cpu().numpy().astype(np.float64) + centre
    rows = max(1, BLOCK_ENTRIES // len(Y))
    out = []
    for k in range(0, len(X), rows):
        n = draws[k:k + rows]
        if n.max(initial=0) == 0:
            continue
        weights, _ = _exp_shifted(torch.addmm(h[None, :], X[k:k + rows], Yt))
        picked = torch.multinomial(weights.cpu(), int(n.max()), replacement=True, generator=generator).numpy()
        out.append(targets[picked[np.arange(picked.shape[1])[None, :] < n[:, None]]])  # row i's first n_i
    return np.concatenate(out) if out else np.zeros((0, 3))


# The node plan is a function of the two grid masses alone: runs of the same inputs in one process
# (the tests' dozens of tiny runs, a notebook, the study driver) compute it once. Oldest out first.
_PLANS: dict[str, np.ndarray] = {}
_PLANS_KEPT = 4


def destinations_in_grid_mass(x: np.ndarray,  # [N, 3] source particles at rest
                              mass: np.ndarray,  # [N]
                              grid_mass: np.ndarray,  # [R, R, R] the target's grid mass
                              grid: Grid,
                              blur_cells: float = 1.0,
                              device: str = "cpu",
                              projection: str = "barycentric") -> np.ndarray:  # [N, 3]
    """Each particle's destination in the target's grid mass, from the plan between the two grid
    masses (the source's splatted: m_I = sum_p w_Ip m_p) from the source's non-empty nodes y_I to
    the target's, blur = blur_cells grid cells. projection "barycentric": transport_destinations
    gives node displacements D_I = T_I - y_I, and a particle moves by their B-spline
    interpolation, T_p = x_p + sum_I w_Ip D_I m_I / sum_I w_Ip m_I (its stencil's nodes all hold
    mass). "sampled" (PlasticityConfig.transport_projection): each particle is sent to a target
    node drawn from the plan's row of its nearest source node (transport_draws, seed 0), keeping
    its offset from that node, so every target node receives about the mass the plan gives it
    rather than the mean of its row (which draws mass off thin parts and rounds corners).
    Node to node, the plan is ~(N / nodes)^2 times cheaper than particle to node. The plan runs on
    the torch ``device``; the splat, the draws and the interpolation on the CPU."""
    R = grid.res
    if grid_mass.shape != (R, R, R):
        raise ValueError(f"target grid mass has shape {grid_mass.shape}, expected {(R, R, R)}")
    x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
    src = splat_mass(x, mass, grid)
    src_idx = np.argwhere(src > 0)
    tgt_idx = np.argwhere(grid_mass > 0)
    y = grid.lo + grid.dx * src_idx
    key = hashlib.sha1(b"".join((np.ascontiguousarray(src).tobytes(), np.ascontiguousarray(grid_mass, np.float64).tobytes(),
                                 np.array([R, grid.lo, grid.dx, blur_cells], np.float64).tobytes(),
                                 device.encode()))).hexdigest()
    if projection == "sampled":
        return _drawn_destinations(x, src, src_idx, tgt_idx, grid_mass, grid, blur_cells, device, key)
    if projection != "barycentric":
        raise ValueError(f"projection must be barycentric or sampled, got {projection!r}")
    T = _PLANS.get(key)
    if T is None:
        T = transport_destinations(y, src[src > 0], grid.lo + grid.dx * tgt_idx, grid_mass[grid_mass > 0],
                                   blur=blur_cells * grid.dx, device=device)
        if len(_PLANS) >= _PLANS_KEPT:
            _PLANS.pop(next(iter(_PLANS)))
        _PLANS[key] = T
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


def _drawn_destinations(x: np.ndarray,  # [N, 3]
                        src: np.ndarray,  # [R, R, R] the particles' grid mass
                        src_idx: np.ndarray,  # [S, 3] its non-empty nodes (np.argwhere order: the plan's rows)
                        tgt_idx: np.ndarray,  # [M, 3] the target's non-empty nodes
                        grid_mass: np.ndarray,  # [R, R, R] the target's
                        grid: Grid, blur_cells: float, device: str, plan_key: str) -> np.ndarray:  # [N, 3]
    """destinations_in_grid_mass's projection "sampled": particle p, whose nearest node I holds
    mass (a particle's own weight there is at least 1/8), goes to y_J + (x_p - y_I), J drawn from
    the plan's row of I; the draws of a node's particles in their order."""
    R = grid.res
    row_of = np.full((R, R, R), -1, dtype=np.int64)
    row_of[tuple(src_idx.T)] = np.arange(len(src_idx))
    near = np.clip(np.rint((x - grid.lo) / grid.dx).astype(np.int64), 0, R - 1)
    rows = row_of[near[:, 0], near[:, 1], near[:, 2]]
    if (rows < 0).any():  # cannot happen for particles with mass (see above)
        raise ValueError("a particle's nearest grid node holds no mass: are its masses positive?")
    counts = np.bincount(rows, minlength=len(src_idx))
    key = hashlib.sha1((plan_key + "sampled").encode() + counts.tobytes()).hexdigest()
    drawn = _PLANS.get(key)
    if drawn is None:
        drawn = transport_draws(grid.lo + grid.dx * src_idx, src[src > 0], grid.lo + grid.dx * tgt_idx,
                                grid_mass[grid_mass > 0], blur_cells * grid.dx, counts, device=device)
        if len(_PLANS) >= _PLANS_KEPT:
            _PLANS.pop(next(iter(_PLANS)))
        _PLANS[key] = drawn
    order = np.argsort(rows, kind="stable")  # the draws come row by row
    out = np.empty_like(x)
    out[order] = drawn + (x[order] - (grid.lo + grid.dx * near[order]))
    return out
