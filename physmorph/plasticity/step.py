"""Chamfer-guided plasticity (paper section 3.4, eq. 4): migrate the rest state toward the target.

Per frame k >= k0:
1. d_i = NN_T(x_i) - x_i, the nearest target-surface point per particle (KD tree); with
   ``correspondence="transport"`` (not the paper's) d_i = T_i - x_i instead, T_i the particle's
   optimal-transport destination in the target's mass (physmorph.plasticity.transport), fixed per material
   point;
2. smooth d by iterative KNN averaging (k neighbours, ``smooth_iters`` passes);
3. displacement Jacobian J_i from the particle's k neighbours and its symmetric part
   dFp_i = (J_i + J_i^T) / 2;
4. eq. 4 as printed: Fp_i <- (I + eta_i dFp_i) Fp_i, with
   eta_i = eta * |d_i| / (|d_i| + median_j |d_j|) (particles already on the target barely change,
   far ones move at up to eta);
5. damping toward identity Fp <- (1 - d_p) Fp + d_p I;
6. isochoric projection: singular values of Fp clamped so that det(Fp) stays in ``det_bounds``
   (uniform rescale, which leaves anisotropy unchanged) and max/min <= ``max_anisotropy``.

Jacobian estimator. Eq. 4 as printed, J_i = mean_j (d_j - d_i)(x_j - x_i)^T / |x_j - x_i|^2,
returns A M_i for an affine field d = A x + b, where M_i = mean_j e_j e_j^T / |e_j|^2 (M = I/3 for
an isotropic neighbourhood): it is a scaled, neighbourhood-biased estimate.

Update rule. The printed update integrates the Chamfer field: while the physics has not yet
closed a gap, every frame adds eta dFp again, so Fp keeps growing after the shape has arrived and
the stress from Fe = F Fp^-1 then pushes it past the target (an integrator's wind-up; with
eta = 0.2 the default profile overshoots and pins det Fp at its bound, docs/study/log.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from physmorph.base.linalg3 import det3, inverse3, right_stretch, singular_values
from physmorph.settings.plasticity import PlasticityConfig  # noqa: F401 (declared with the settings)

if TYPE_CHECKING:  # scipy.spatial is imported where it is used: the workflow reads the config classes at every start
    from scipy.spatial import cKDTree


# rows of the [N, k] neighbour arrays worked on at a time (their temporaries: ~17 MB at k = 64)
ROW_CHUNK = 32768


def nearest_target_displacement(x: np.ndarray, target_tree: cKDTree, target_points: np.ndarray) -> np.ndarray:
    """d_i = NN_T(x_i) - x_i.   x: [N, 3] -> [N, 3]"""
    _, idx = target_tree.query(x, k=1, workers=-1)
    return target_points[idx] - x


def knn_smooth(d: np.ndarray, neighbors: np.ndarray, iters: int) -> np.ndarray:
    """Iterative KNN averaging: d_i <- mean_{j in K_i} d_j (K_i includes i).  d: [N, 3], neighbors: [N, k]"""
    for _ in range(iters):
        d = d[neighbors].mean(axis=1)
    return d


def displacement_jacobian(x: np.ndarray,  # [N, 3]
                          d: np.ndarray,  # [N, 3]
                          neighbors: np.ndarray) -> np.ndarray:  # [N, k] indices -> [N, 3, 3]
    """Per-particle displacement Jacobian J_i of eq. 4 (see the module docstring): the reference of
    neighbourhood.displacement_jacobian_pairs. The particle itself may be among its neighbors; it
    adds nothing."""
    e = x[neighbors] - x[:, None, :]  # [N, k, 3]
    dd = d[neighbors] - d[:, None, :]  # [N, k, 3]
    r2 = np.einsum("nki,nki->nk", e, e)
    w = np.where(r2 > 0, 1.0 / np.where(r2 > 0, r2, 1.0), 0.0)  # self / coincident neighbours carry no information
    count = np.maximum((r2 > 0).sum(axis=1), 1)[:, None, None]
    return np.einsum("nk,nki,nkj->nij", w, dd, e) / count


# project_plastic leaves an Fp alone when inside its bounds by this relative margin, far above the
# closed-form singular values' error (1e-8 relative)
INSIDE_MARGIN = 1.0 - 1e-6


def project_plastic(Fp: np.ndarray, det_bounds: tuple[float, float], max_anisotropy: float) -> np.ndarray:
    """Isochoric projection of Fp [N, 3, 3]: clamp its stretches' anisotropy and determinant.

    Fp = U diag(s) V^T (signed so U, V are rotations); s is made positive, its spread about the
    geometric mean limited to max_anisotropy, then rescaled uniformly so det lies in det_bounds.
    An Fp inside both bounds is returned as it is (what its SVD would rebuild, to round-off), so
    only the particles the bounds act on pay for a batched SVD (the paper profile: 1.5 s a frame).
    """
    Fp = np.asarray(Fp, dtype=np.float64)
    return project_outside(Fp.copy(), inside_bounds(Fp, det_bounds, max_anisotropy), det_bounds, max_anisotropy)


def inside_bounds(Fp: np.ndarray,  # [N, 3, 3]
                  det_bounds: tuple[float, float], max_anisotropy: float) -> np.ndarray:  # [N] bool
    """Whether each Fp is inside project_plastic's bounds by INSIDE_MARGIN (it would keep it)."""
    sv = singular_values(Fp)
    det = det3(Fp)
    g = np.cbrt(np.maximum(det, 0.0))
    m = INSIDE_MARGIN
    return ((det > det_bounds[0] / m) & (det < det_bounds[1] * m)
            & (sv[:, 0] < g * np.sqrt(max_anisotropy) * m) & (sv[:, 2] * np.sqrt(max_anisotropy) * m > g))


def project_outside(Fp: np.ndarray,  # [N, 3, 3], projected in place where not inside
                    inside: np.ndarray,  # [N] bool
                    det_bounds: tuple[float, float], max_anisotropy: float) -> np.ndarray:  # [N, 3, 3]
    if not inside.all():
        Fp[~inside] = _project_plastic_svd(Fp[~inside], det_bounds, max_anisotropy)
    return Fp


def _project_plastic_svd(Fp: np.ndarray, det_bounds: tuple[float, float], max_anisotropy: float) -> np.ndarray:
    """project_plastic by a batched SVD of every Fp [N, 3, 3]."""
    U, s, Vt = np.linalg.svd(Fp)
    # Signed SVD: put any reflection into the smallest singular value, then force it positive,
    # which un-inverts an inverted Fp.
    flip = det3(U) * det3(Vt) < 0
    U[flip, :, 2] *= -1
    s = np.abs(s)
    s = np.maximum(s, 1e-6)
    g = np.exp(np.log(s).mean(axis=1, keepdims=True))  # geometric mean = det^(1/3)
    half = np.sqrt(max_anisotropy)
    s = np.clip(s, g / half, g * half)
    det = np.prod(s, axis=1, keepdims=True)
    det_c = np.clip(det, det_bounds[0], det_bounds[1])
    s = s * (det_c / det) ** (1.0 / 3.0)
    return np.einsum("nij,nj,njk->nik", U, s, Vt)


def fp_update_reference(J: np.ndarray,  # [N, 3, 3]
                        eta: np.ndarray,  # [N]
                        Fp: np.ndarray,  # [N, 3, 3]
                        damping: float, det_bounds: tuple[float, float], max_anisotropy: float,
                        scale_from: float = 1.0) -> tuple[np.ndarray, np.ndarray]:  # -> [N, 3, 3], [N] bool
    """Steps 4-5 and the projection's bounds test in NumPy: (Fp', inside) with
    Fp' = (1 - d_p) (I + eta dFp) Fp / s_from + d_p I, dFp = (J + J^T) / 2 (the reference of
    physmorph.plasticity.fp_update, which the update runs)."""
    dFp = 0.5 * (J + np.transpose(J, (0, 2, 1)))
    Fp_new = (np.eye(3) + eta[:, None, None] * dFp) @ (Fp if scale_from == 1.0 else Fp / scale_from)
    Fp_new = (1.0 - damping) * Fp_new + damping * np.eye(3)
    return Fp_new, inside_bounds(Fp_new, det_bounds, max_anisotropy)


def rebase_control(
    F: np.ndarray,  # [N, 3, 3] deformation gradient at the update
    control: np.ndarray,  # [Tc, N, 3, 3] dFc per control slot
    Fp_old: np.ndarray,  # [N, 3, 3]
    Fp_new: np.ndarray,  # [N, 3, 3]
) -> np.ndarray:  # [Tc, N, 3, 3]
    """dFc' = (F + dFc) Fp_old^-1 Fp_new - F, so that Fe = (F + dFc) Fp^-1 is the same before and
    after the Fp update (paper section 3.4: "modifying Fp redefines the material's rest state
    without creating stress").

    Why: the control here is persistent and enters the stress, so it already holds the achieved
    deformation; an Fp update that changes Fe is a stress step, and the weakly damped elastic body
    (period ~4 frames at the default profile) rings after it: the oscillation seen at eta >= 0.05.
    With the control re-based the step is absorbed, and Fp changes only the reference against
    which later deformation is measured.
    """
    M = inverse3(Fp_old) @ Fp_new  # Fp_old^-1 Fp_new, [N, 3, 3]
    return np.einsum("tnij,njk->tnik", F[None] + control, M) - F[None]


def absorb_control(
    F: np.ndarray,  # [N, 3, 3] deformation gradient at the update
    control_mean: np.ndarray,  # [N, 3, 3] mean_t dFc_t over the control slots
    Fp: np.ndarray,  # [N, 3, 3]
) -> np.ndarray:  # [N, 3, 3]
    """Fp' = Fp (F + mean_t dFc_t)^-1 F: the rest state in which F alone gives the elastic
    deformation the control produced, F Fp'^-1 = (F + mean dFc) Fp^-1.

    Why: the persistent control enters the stress and so holds the achieved shape by itself; the
    rest state never learns it, and with the control switched off the body springs back
    (docs/study/log.md, the release probe). Moving the control into Fp (then re-basing the
    control with rebase_control, which leaves it with zero mean) turns the achieved deformation
    into the material's rest state, the role section 3.4 gives plasticity. Particles whose
    F + mean dFc is near-singular keep their Fp. The 0 Fp added changes no value, only the sign
    of an exact zero, which it sets as in the results on record (absorb_shape too).
    """
    A = F + control_mean  # [N, 3, 3]
    ok = det3(A) > 1e-3
    out = Fp.copy()
    out[ok] = 0.0 * Fp[ok] + Fp[ok] @ (inverse3(A[ok]) @ F[ok])
    return out


def absorb_shape(
    F: np.ndarray,  # [N, 3, 3] deformation gradient at the update
    Fp: np.ndarray,  # [N, 3, 3]
) -> np.ndarray:  # [N, 3, 3]
    """Fp' = S, S = V diag(sigma) V^T the right stretch of F = U diag(sigma) V^T (for det F > 0,
    F S^-1 = U V^T is a rotation): Fe = F Fp'^-1 = U V^T, a rotation, so the fixed-corotated
    stress vanishes and the achieved shape is the rest shape (plastic flow to it).

    Why: absorb_control keeps the elastic deformation the *control* produced, which is the stress
    that drives the body; released, the body goes on along it, past the target (docs/study/log.md
    finding 42). This variant keeps the shape instead: with the control re-based afterwards
    (rebase_control) the running morph sees the same stress, and a released one has none.
    Particles with det F <= 1e-3 (near-inverted) keep their Fp.
    """
    ok = det3(F) > 1e-3
    out = Fp.copy()
    out[ok] = 0.0 * Fp[ok] + right_stretch(F[ok])  # V diag(sigma) V^T without the SVD; 0 Fp: see absorb_control
    return out


def absorbed_rest(
    F: np.ndarray,  # [N, 3, 3] deformation gradient at the update
    control_mean: np.ndarray,  # [N, 3, 3] mean_t dFc_t over the control slots
    Fp: np.ndarray,  # [N, 3, 3]
    cfg: PlasticityConfig,
) -> np.ndarray:  # [N, 3, 3]
    """The Fp an absorbing update starts from: the control (absorb_control) or the shape
    (absorb_shape) moved into it, per cfg.absorb_target."""
    if cfg.absorb_target == "shape":
        return absorb_shape(F, Fp)
    return absorb_control(F, control_mean, Fp)


def rebase_reference(
    cfg: PlasticityConfig,
    absorbing: bool,
    Fp_absorbed: np.ndarray,  # [N, 3, 3] Fp after the absorption, before the Chamfer step
    Fp_new: np.ndarray,  # [N, 3, 3] Fp after the whole update
) -> np.ndarray | None:  # [N, 3, 3] or None
    """The Fp to re-base the control onto (rebase_control), so Fe is continuous across that much of
    the update; None: no re-base, the update is a stress step (the default).

    The whole update with continuous_stress, and while the control is absorbed (as measured in docs/study/log.md part 3); only the absorption while the
    shape is absorbed, so the Chamfer step's pull toward the target remains a stress, as in the default (docs/study/log.md finding 47).
    """
    if cfg.continuous_stress or (absorbing and cfg.absorb_target == "control"):
        return Fp_new
    if absorbing:
        return Fp_absorbed
    return None


@dataclass
class PlasticityResult:
    Fp: np.ndarray  # [N, 3, 3]
    displacement: np.ndarray  # [N, 3] smoothed
    eta: np.ndarray  # [N]
    mean_distance: float  # mean |d| before smoothing (a Chamfer-like term)


def neighbour_pool(x: np.ndarray,  # [N, 3] positions at rest
                   lo: float, dx: float, ppc: int) -> np.ndarray | None:  # -> [P] sorted indices, or None
    """The particles the plasticity's neighbourhoods are drawn from (PlasticityConfig.neighbour_ppc):
    in each sub-cell of side dx / ppc of the simulation grid, the particle nearest its centre. None
    (every particle) when ppc <= 0 or no sub-cell holds two particles, as with a sampling of at most
    ppc particles per cell per axis (the jittered lattice puts one per sub-cell of dx / PPC)."""
    if ppc <= 0:
        return None
    h = dx / ppc
    cell = np.floor((x - lo) / h).astype(np.int64)  # [N, 3]
    off = x - (lo + (cell + 0.5) * h)
    cell -= cell.min(axis=0)
    span = cell.max(axis=0) + 1
    key = (cell[:, 0] * span[1] + cell[:, 1]) * span[2] + cell[:, 2]
    order = np.lexsort(((off * off).sum(axis=1), key))  # by sub-cell, nearest its centre first
    first = np.ones(len(x), dtype=bool)
    first[1:] = key[order[1:]] != key[order[:-1]]
    if first.all():
        return None
    return np.sort(order[first])


def nearest_neighbours(x: np.ndarray,  # [N, 3]
                       source: np.ndarray,  # [P] indices into x the neighbours are drawn from
                       k: int, chunk: int = ROW_CHUNK) -> tuple[np.ndarray, np.ndarray]:  # -> [N, k] indices, [N, k] r2
    """Each particle's k nearest particles of ``source`` (KD tree), nearest first, and their squared
    distances, 0 for the particle itself (it carries no information): the reference of
    neighbourhood.k_nearest, which the chamfer step uses. Queried by chunks of rows into int32
    indices (at 471K particles, k = 64: 0.36 GB for both instead of 0.96 GB with the query's own arrays)."""
    from scipy.spatial import cKDTree

    n = len(x)
    tree = cKDTree(x[source])
    neighbors = np.empty((n, k), dtype=np.int32 if n < np.iinfo(np.int32).max else np.int64)
    r2 = np.empty((n, k))
    for a in range(0, n, chunk):
        dist, j = tree.query(x[a:a + chunk], k=k, workers=-1)
        rows = slice(a, a + len(dist))
        neighbors[rows] = source[np.asarray(j).reshape(len(dist), k)]
        np.square(np.asarray(dist).reshape(len(dist), k), out=r2[rows])
        r2[rows][neighbors[rows] == np.arange(a, a + len(dist))[:, None]] = 0.0
    return neighbors, r2


def chamfer_plasticity_step(
    x: np.ndarray,  # [N, 3]
    Fp: np.ndarray,  # [N, 3, 3]
    target_points: np.ndarray,  # [M, 3]
    cfg: PlasticityConfig,
    target_tree: cKDTree | None = None,
    destination: np.ndarray | None = None,  # [N, 3] per-particle destinations (correspondence="transport")
    nearest_index: np.ndarray | None = None,  # [N] index of each x's nearest target point, when the caller has it
    pool: np.ndarray | None = None,  # [P] the particles neighbourhoods are drawn from (neighbour_pool); None: all
    search_device: str | None = None,  # the torch device of the nearest-target search; None: the KD tree
    rest_scale: tuple[float, float] = (1.0, 1.0),  # (s_from, s): the rest volume ratio's cube root before and after
) -> PlasticityResult:
    """One Chamfer-guided plasticity update (steps 1-6 of the module docstring); with
    ``destination`` step 1 is d_i = destination_i - x_i. With ``pool`` every particle's k neighbours
    are taken from the pool's particles, whose displacements the smoothing passes update as well.
    The nearest target points, where neither ``destination`` nor ``nearest_index`` gives them, come
    from the KD tree, or with ``search_device`` from physmorph.plasticity.nearest on that torch device; the
    neighbourhoods, the smoothing and the Jacobian (physmorph.plasticity.neighbourhood) run on the Taichi
    runtime's arch, as does the update of Fp with the projection's bounds test (physmorph.plasticity.fp_update);
    the SVD of the few Fp outside the bounds in NumPy. ``rest_scale`` (s_from, s): Fp arrives holding the rest
    volume ratio s_from³ (PlasticityConfig.rest_volume_ratio) and leaves holding s³; steps 4-6 act on
    the rest shape Fp / s_from, so the damping toward I and the det bounds keep that shape's volume."""
    from scipy.spatial import cKDTree

    from physmorph.plasticity.fp_update import fp_update  # Taichi
    from physmorph.plasticity.neighbourhood import displacement_jacobian_pairs, k_nearest, smooth_displacement

    if destination is not None:
        d_raw = np.asarray(destination, dtype=np.float64) - x
    elif nearest_index is None and search_device is not None:
        from physmorph.plasticity.nearest import nearest_points

        d_raw = target_points[nearest_points(target_points, x, search_device)[1]] - x
    else:
        tree = target_tree if target_tree is not None else cKDTree(target_points)
        d_raw = (nearest_target_displacement(x, tree, target_points) if nearest_index is None
                 else target_points[nearest_index] - x)
    source = np.arange(len(x)) if pool is None else np.asarray(pool)
    neighbors, _ = k_nearest(x, source, min(cfg.k_neighbors, len(source)), with_r2=False)
    d = smooth_displacement(d_raw, neighbors, cfg.smooth_iters, sources=source)
    J = displacement_jacobian_pairs(x, d, neighbors, None)
    del neighbors
    mag = np.linalg.norm(d, axis=1)
    scale = np.median(mag)
    eta = cfg.eta * mag / (mag + scale) if scale > 0 else np.zeros(len(x))
    scale_from, scale = rest_scale
    Fp_new, inside = fp_update(J, eta, Fp, cfg.damping, cfg.det_bounds, cfg.max_anisotropy, INSIDE_MARGIN, scale_from)
    Fp_new = project_outside(Fp_new, inside, cfg.det_bounds, cfg.max_anisotropy)
    if scale != 1.0:
        Fp_new = Fp_new * scale
    return PlasticityResult(Fp_new, d, eta, float(np.linalg.norm(d_raw, axis=1).mean()))
