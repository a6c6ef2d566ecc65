"""A closed triangle surface of a particle body, its transform back to the input mesh's frame, writers.

Method of :func:`particle_surface` (all lengths in simulation domain units):

1. Volume splat. Each particle's current volume v_p = V_p det F_p is spread onto a grid of
   spacing ``h = dx / refine`` with the quadratic B-spline of MLS-MPM (physmorph.base.grid), and the
   sum divided by h^3: phi(node) = sum_p v_p N((x_node - x_p) / h) / h^3 is the body's volume
   fraction (about 1 inside, 0 outside; sum phi h^3 = sum v_p exactly, as the weights are a
   partition of unity).
2. Blur, at the local particle spacing. The samples are jittered-stratified, and inside the
   body sparser than h (one per dx^3): blurred by half their spacing s the noise of phi there is
   +-20 % and the level set has bubbles; blurred by s, +-5 % and none. The dense surface shell
   (ppc_surface^3 per cell) keeps its own, smaller s, or thin parts (the bunny's ears) erode.
   Particles are grouped by s_p = v_p^(1/3) in factors of sqrt(2) (group k: splat rho_k, blur
   s_k, G_k the Gaussian of standard deviation s_k) and
       phi = sum_k w_k phi_k,   phi_k = sum_j G_max(s_j, s_k) * rho_j,
       w_k = (G_c * rho_k) / (G_c * sum_j rho_j)   (G_c: the interior's spacing),
   i.e. where group k holds the volume nearby, everything is blurred by s_k, but no group below
   its own spacing. Blurring each group by its own s_k alone leaves a dip where the shell meets
   the interior (phi down to 0.47 there at the paper's 471K particles: bubbles); this form keeps
   phi >= 0.66 there and ~1 +- 5 % deeper inside. phi is ~0 outside; sum phi h^3 = sum v_p
   only approximately (steps 3 and 5 match the volume).
   Then, with ``pore_closing`` k > 1, phi is grey-closed over k^3 cells (a maximum filter, then a
   minimum filter): a dip of phi narrower than k cells is filled up to its rims (at k = 3 a
   particle-free gap about two MPM cells across, as phi's blur narrows it), and concave creases are
   raised a little; convex parts and wider dips are unchanged. After much shaping the particles
   are spread unevenly, and where phi dips to the level just under the surface the level set opens
   pores and thin tunnels, finer than the blur that made phi (the mid profile's bodies: genus 2-3
   whose count changes with the level by +-10 %; docs/study/log.md findings 305-306). The targets'
   own particles keep their holes with it (the torus, A, B, R, at the default and mid grids).
3. Marching cubes (scikit-image, Lewiner) on phi at an iso level c. The grid is padded by the
   kernel's and the blur's reach plus a margin and its outer layer is zero, so every level set is
   closed (watertight). The level is chosen by bisection on c in [0.02, 0.98] max(phi) until the
   enclosed volume is within 0.5 % of sum_p v_p (the volume decreases monotonically with c).
   Closed components enclosing a negative volume smaller than the largest particle's (cavities
   the sampling cannot resolve: a few remain in thin parts where shell meets interior) are removed.
4. Taubin lambda/mu smoothing (:func:`taubin_smooth`): removes the marching-cubes staircase
   without the shrinkage of plain Laplacian smoothing.
5. Volume correction. The mesh is scaled about its volume centroid by (sum_p v_p / V)^(1/3) so
   its enclosed volume V equals sum_p v_p to rounding (a change of well under 1 % in length after
   step 3; larger only where the level search could not bracket the volume, e.g. a body whose
   particles are far apart).

The mesh is returned as a ``trimesh.Trimesh`` built without processing (no vertex merging), with
faces oriented outward (positive volume), watertight and winding-consistent.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import trimesh

# Taubin's smoothing factors: lambda > 0 shrinks, mu < -lambda inflates back; the pass-band
# frequency 1/lambda + 1/mu = 0.11 keeps the body's shape and damps the voxel-scale staircase.
TAUBIN_LAMBDA, TAUBIN_MU = 0.5, -0.53
# The level search stops once the marching-cubes volume is this close to the particles' volume;
# the final rescale (step 5) removes the rest.
LEVEL_VOLUME_RTOL = 0.005
# The surface's float32 grids alive at once (2 per spacing group + 4) may hold at most this many
# voxels in all (512 MiB); a larger grid is refused rather than exhausting memory. The whole
# domain at grid 64 and refine 2 is 128^3 = 2.1M voxels.
MAX_VOXELS = 2 ** 27
# The blur of a particle's splat, in units of its spacing v_p^(1/3) (see the module docstring).
BLUR_PER_SPACING = 1.0
_STENCIL_CELLS = 2  # the quadratic B-spline reaches 1.5 cells from a particle: 2 cells of padding
_MARGIN_CELLS = 2


def _bspline(g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # g: [N, 3] positions in grid units
    """Quadratic B-spline stencil: base node [N, 3] and weights [N, 3 (axis), 3 (offset)]."""
    base = np.floor(g - 0.5).astype(np.int64)
    f = g - base
    w = np.stack([0.5 * (1.5 - f) ** 2, 0.75 - (f - 1.0) ** 2, 0.5 * (f - 0.5) ** 2], axis=-1)
    return base, w


def _splat(x: np.ndarray,  # [N, 3] positions
           volume: np.ndarray,  # [N]
           origin: np.ndarray, cell: float, shape: tuple[int, int, int]) -> np.ndarray:  # [X, Y, Z]
    """sum_p volume_p N((x_node - x_p) / cell) / cell^3 on the grid: 27 stencil offsets, one
    bincount over the particles each (np.add.at is ~10x slower)."""
    base, w = _bspline((x - origin) / cell)
    strides = np.array([shape[1] * shape[2], shape[2], 1], dtype=np.int64)
    flat = base @ strides
    acc = np.zeros(int(np.prod(shape)), dtype=np.float64)
    for a in range(3):
        for b in range(3):
            wab = volume * w[:, 0, a] * w[:, 1, b]
            for c in range(3):
                acc += np.bincount(flat + (a * strides[0] + b * strides[1] + c), weights=wab * w[:, 2, c],
                                   minlength=acc.size)
    return (acc / cell ** 3).reshape(shape)


def _coarse_spacing(volume: np.ndarray) -> float:  # volume: [N] current particle volumes
    """The volume-weighted 90th percentile of the spacings v_p^(1/3): the interior's spacing,
    which holds most of the volume (the dense shell holds most of the particles); a few stray,
    stretched particles do not set it."""
    order = np.argsort(volume)
    cumulative = np.cumsum(volume[order])
    return float(np.cbrt(volume[order][np.searchsorted(cumulative, 0.9 * cumulative[-1])]))


def volume_fraction(x: np.ndarray,  # [N, 3] positions
                    volume: np.ndarray,  # [N] current volumes V_p det F_p
                    cell: float) -> tuple[np.ndarray, np.ndarray]:
    """The blurred volume fraction phi [X, Y, Z] (float32) on a padded grid of spacing ``cell``
    around the particles, and the position [3] of its node (0, 0, 0): steps 1 and 2 of the module
    docstring, phi = sum_k w_k phi_k."""
    from scipy.ndimage import gaussian_filter

    def blur(field: np.ndarray, sigma: float) -> np.ndarray:  # sigma in cells
        return gaussian_filter(field, sigma=float(sigma), mode="constant", truncate=3.0)

    group = np.round(2.0 * np.log2(np.cbrt(volume) * BLUR_PER_SPACING / cell)).astype(np.int64)
    keys, member = np.unique(group, return_inverse=True)  # keys ascending: finest group first
    sigma = 2.0 ** (keys / 2.0)  # [G] each group's blur (standard deviation), in cells
    pad = _STENCIL_CELLS + int(np.ceil(3.0 * sigma.max())) + _MARGIN_CELLS
    origin = x.min(axis=0) - pad * cell
    shape = tuple(int(n) for n in np.ceil((x.max(axis=0) - x.min(axis=0)) / cell).astype(np.int64) + 2 * pad + 1)
    fields = 2 * len(keys) + 4  # float32 grids alive at once, at most
    if int(np.prod(shape)) * fields > MAX_VOXELS:
        raise ValueError(f"the particles span {np.round(x.max(axis=0) - x.min(axis=0), 3).tolist()} domain units: "
                         f"a surface grid of spacing {cell:.4g} would have {int(np.prod(shape)):,} voxels (at most "
                         f"{MAX_VOXELS // fields:,} here); pass a smaller refine")
    rho = [_splat(x[member == k], volume[member == k], origin, cell, shape).astype(np.float32)
           for k in range(len(keys))]
    if len(keys) == 1:
        phi = blur(rho[0], sigma[0])
    else:
        own = [blur(r, s) for r, s in zip(rho, sigma)]  # G_j * rho_j
        coarser = [np.sum(own[k + 1:], axis=0) if k + 1 < len(own) else 0.0 for k in range(len(own))]
        del own
        weight_sigma = BLUR_PER_SPACING * _coarse_spacing(volume) / cell
        total = blur(np.sum(rho, axis=0), weight_sigma)
        weighted, finer = np.zeros(shape, np.float32), np.zeros(shape, np.float32)
        for k in range(len(keys)):
            finer += rho[k]  # phi_k = G_k * (sum_{j <= k} rho_j) + sum_{j > k} G_j * rho_j
            weighted += blur(rho[k], weight_sigma) * (blur(finer, sigma[k]) + coarser[k])
        phi = np.divide(weighted, total, out=np.zeros(shape, np.float32), where=total > 1e-12)
    # a zero outer layer: the level set of any positive level is closed
    phi[0], phi[-1], phi[:, 0], phi[:, -1], phi[:, :, 0], phi[:, :, -1] = 0, 0, 0, 0, 0, 0
    return phi, origin


def close_pores(phi: np.ndarray,  # [X, Y, Z] a volume fraction with a zero outer layer
                width: int) -> np.ndarray:  # [X, Y, Z]
    """phi grey-closed over width^3 cells (step 2 of the module docstring), its outer layer zero again."""
    from scipy.ndimage import grey_closing

    out = grey_closing(phi, size=(width,) * 3, mode="constant", cval=0.0)
    out[0], out[-1], out[:, 0], out[:, -1], out[:, :, 0], out[:, :, -1] = 0, 0, 0, 0, 0, 0
    return out


def _iso_surface(phi: np.ndarray,  # [X, Y, Z]
                 level: float, origin: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes of phi at ``level``: vertices [V, 3] (domain units), faces [F, 3] outward."""
    from skimage.measure import marching_cubes

    verts, faces, _, _ = marching_cubes(phi, level=level, spacing=(cell, cell, cell), method="lewiner")
    verts = verts.astype(np.float64) + origin
    faces = faces.astype(np.int64)
    if _signed_volume(verts, faces) < 0:  # face the normals outward, whichever way the library winds
        faces = faces[:, ::-1].copy()
    return verts, faces


def _signed_volume(verts: np.ndarray, faces: np.ndarray) -> float:  # verts [V, 3], faces [F, 3]
    """Enclosed volume by the divergence theorem: sum over faces of v0 . (v1 x v2) / 6."""
    v0, v1, v2 = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    return float(np.einsum("ij,ij->", v0, np.cross(v1, v2)) / 6.0)


def _drop_small_cavities(verts: np.ndarray,  # [V, 3]
                         faces: np.ndarray,  # [F, 3]
                         max_volume: float) -> tuple[np.ndarray, np.ndarray]:
    """Remove the closed components that enclose a negative volume above -max_volume: cavities
    smaller than the body's sampling can resolve (noise where the dense shell meets the sparse
    interior, in thin parts), not holes of the body. Returns (vertices, faces) reindexed."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(verts)
    edges = faces[:, [0, 1, 1, 2]].reshape(-1, 2)
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    n_comp, label = connected_components(graph, directed=False)
    if n_comp == 1:
        return verts, faces
    v0, v1, v2 = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    face_label = label[faces[:, 0]]
    comp_volume = np.bincount(face_label, weights=np.einsum("ij,ij->i", v0, np.cross(v1, v2)) / 6.0, minlength=n_comp)
    keep_face = ~((comp_volume < 0) & (comp_volume > -max_volume))[face_label]
    used = np.zeros(n, dtype=bool)
    used[faces[keep_face].ravel()] = True
    new_index = np.cumsum(used) - 1
    return verts[used], new_index[faces[keep_face]]


def _level_for_volume(phi: np.ndarray, target: float, origin: np.ndarray, cell: float) -> float:
    """The iso level whose marching-cubes volume is within LEVEL_VOLUME_RTOL of ``target``, by
    bisection (the volume falls as the level rises); the nearest level tried when none is."""
    peak = float(phi.max())
    lo, hi = 0.02 * peak, 0.98 * peak
    level, best, best_err = float(np.clip(0.5, lo, hi)), None, np.inf
    for _ in range(24):
        vol = _signed_volume(*_iso_surface(phi, level, origin, cell))
        err = abs(vol - target) / target
        if err < best_err:
            best, best_err = level, err
        if err <= LEVEL_VOLUME_RTOL:
            break
        if vol > target:
            lo = level
        else:
            hi = level
        level = 0.5 * (lo + hi)
    return best


def taubin_smooth(vertices: np.ndarray,  # [V, 3]
                  faces: np.ndarray,  # [F, 3] vertex indices
                  iterations: int = 10, lam: float = TAUBIN_LAMBDA, mu: float = TAUBIN_MU) -> np.ndarray:  # [V, 3]
    """Taubin's lambda/mu smoothing (Taubin 1995): ``iterations`` times v <- v + lam L v, then
    v <- v + mu L v, with the umbrella Laplacian L v_i = mean of v_i's edge neighbours - v_i.

    The shrinking step (lam > 0) and the inflating one (mu < -lam) cancel at low frequencies, so
    the body keeps its size while the high-frequency noise is damped. Vertices without an edge
    stay where they are. Returns new vertices; the faces are unchanged.
    """
    from scipy import sparse

    n = len(vertices)
    edges = np.asarray(faces, dtype=np.int64)[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    rows = np.concatenate([edges[:, 0], edges[:, 1]])
    cols = np.concatenate([edges[:, 1], edges[:, 0]])
    adjacency = sparse.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    adjacency.data[:] = 1.0  # an edge shared by two faces was counted twice
    degree = np.asarray(adjacency.sum(axis=1)).ravel()
    has_edges = degree > 0
    mean_of_neighbours = sparse.diags(np.where(has_edges, 1.0 / np.maximum(degree, 1.0), 0.0)) @ adjacency
    v = np.array(vertices, dtype=np.float64, copy=True)
    for _ in range(int(iterations)):
        for factor in (lam, mu):
            laplacian = mean_of_neighbours @ v - v
            laplacian[~has_edges] = 0.0
            v += factor * laplacian
    return v


def particle_surface(x: np.ndarray,  # [N, 3] positions, domain units
                     volume: np.ndarray,  # [N] rest volumes V_p
                     det_F: np.ndarray,  # [N] det F_p (current volume V_p det F_p)
                     dx: float, refine: float = 2.0, smooth_iterations: int = 10,
                     transform: np.ndarray | None = None, pore_closing: int | None = None) -> trimesh.Trimesh:
    """The closed surface of the particle body whose enclosed volume is sum_p V_p det F_p.

    Volume splat on a grid of spacing dx / ``refine``, Gaussian blur, the grey closing over
    ``pore_closing``^3 cells (0 or 1: none; None: ExportConfig's default, as exported), marching
    cubes at the iso level whose volume matches, Taubin smoothing, final rescale about the centroid
    to the exact volume (see the module docstring). ``transform``: a 4x4 matrix applied last (e.g.
    :func:`domain_to_input`; its volume is then that of the transformed body). ~0.05 s at 7K
    particles, ~1 s and ~150 MB at 471K (2 cores). Raises ValueError on empty, mismatched or
    non-finite input, or on particles with V_p det F_p <= 0.
    """
    x = np.asarray(x, dtype=np.float64)
    current = np.asarray(volume, dtype=np.float64) * np.asarray(det_F, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or len(x) == 0 or current.shape != (len(x),):
        raise ValueError(f"need x [N, 3] and volume, det_F [N] with N > 0, got {x.shape} and {current.shape}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(current)) and np.all(current > 0)):
        raise ValueError("positions must be finite and volumes V_p det F_p finite and > 0")
    if not (np.isfinite(dx) and dx > 0 and refine > 0):
        raise ValueError(f"dx and refine must be > 0, got dx={dx!r}, refine={refine!r}")
    target = float(current.sum())
    cell = float(dx) / float(refine)
    phi, origin = volume_fraction(x, current, cell)
    if pore_closing is None:
        from physmorph.settings.export import ExportConfig

        pore_closing = ExportConfig().pore_closing
    if pore_closing > 1:
        phi = close_pores(phi, int(pore_closing))
    level = _level_for_volume(phi, target, origin, cell)
    verts, faces = _iso_surface(phi, level, origin, cell)
    del phi
    verts, faces = _drop_small_cavities(verts, faces, max_volume=float(current.max()))
    if smooth_iterations > 0:
        verts = taubin_smooth(verts, faces, smooth_iterations)
    mesh = trimesh.Trimesh(verts, faces, process=False)
    centre = np.asarray(mesh.center_mass, dtype=np.float64)
    factor = (target / _signed_volume(verts, faces)) ** (1.0 / 3.0)
    mesh = trimesh.Trimesh(centre + factor * (verts - centre), faces, process=False)
    mesh.metadata.update(iso_level=level, grid_cell=cell, target_volume=target)
    if transform is not None:
        mesh.apply_transform(np.asarray(transform, dtype=np.float64))
    return mesh


def domain_to_input(mesh_attrs: Mapping | str | os.PathLike) -> np.ndarray:  # [4, 4]
    """The 4x4 matrix from simulation domain coordinates to the input mesh's frame and units.

    prepare_mesh normalises the raw mesh (as load_raw_mesh reads it: scene transforms applied) by
    x_domain = scale * x_raw + translation (volume centroid to the origin, longest extent to the
    shape's ``size``) and records ``scale`` and ``translation`` in the mesh HDF5's attributes; the
    inverse is x_raw = (x_domain - translation) / scale. ``mesh_attrs``: those attributes (a
    mapping, e.g. ``h5py.File(...).attrs``) or the path of the mesh HDF5 (its checksum is
    verified). Use with ``mesh.apply_transform`` or ``particle_surface(..., transform=...)``.
    """
    if isinstance(mesh_attrs, (str, os.PathLike)):
        from physmorph.records.h5io import open_h5, read_attr

        with open_h5(mesh_attrs) as f:
            mesh_attrs = {"scale": read_attr(f, "scale"), "translation": read_attr(f, "translation")}
    scale = float(mesh_attrs["scale"])
    translation = np.asarray(mesh_attrs["translation"], dtype=np.float64).reshape(3)
    if not (np.isfinite(scale) and scale > 0 and np.all(np.isfinite(translation))):
        raise ValueError(f"mesh attributes: scale must be finite and > 0 and translation finite, got {scale!r}, "
                         f"{translation.tolist()}")
    matrix = np.eye(4)
    matrix[:3, :3] /= scale
    matrix[:3, 3] = -translation / scale
    return matrix


def _export_atomic(mesh: trimesh.Trimesh, path: str | os.PathLike, file_type: str, **kwargs) -> Path:
    """Export aside and rename into place: a reader never sees a half-written file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".partial")
    try:
        with open(tmp, "wb") as fh:
            mesh.export(file_obj=fh, file_type=file_type, **kwargs)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def write_ply(mesh: trimesh.Trimesh, path: str | os.PathLike) -> Path:
    """Write ``mesh`` as binary little-endian PLY (vertices float64 as trimesh writes them, faces)."""
    return _export_atomic(mesh, path, "ply", encoding="binary")


def write_glb(mesh: trimesh.Trimesh, path: str | os.PathLike) -> Path:
    """Write ``mesh`` as binary glTF (GLB). glTF is +y up like physmorph's world (physmorph.base.cameras)."""
    return _export_atomic(mesh, path, "glb")
