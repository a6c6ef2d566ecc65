"""Surface-focused rendering mask (paper section 3.6).

Particle density is splatted (trilinear) onto a ``voxels``^3 grid over the domain, blurred with a
Gaussian filter, and its iso-surface at ``level`` x (95th-percentile density, i.e. about half the
bulk density) is extracted with marching cubes. Particles within ``band`` voxels of that surface
form the density mask. Particles closer than ``target_band`` (domain units) to the target surface
are added, and the mask of a run only ever grows (union with the previous frame's mask).

The density splat runs on the Taichi runtime's arch; the blur and the marching cubes on the CPU
(grid-sized work); the particles' distances to the two surfaces by KD trees, or with
``search_device`` by physmorph.plasticity.nearest's exhaustive search on that torch device (the same mask, up
to particles within ~1e-12 of a band's edge).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from physmorph.base.grid import scatter_add
from physmorph.settings.surface import SurfaceMaskConfig  # noqa: F401 (declared with the settings)

if TYPE_CHECKING:  # scipy and scikit-image are imported where they are used (the workflow reads
    # the config classes at every start)
    from scipy.spatial import cKDTree


def density_grid(x: np.ndarray, weights: np.ndarray, voxels: int, lo: float, hi: float) -> np.ndarray:
    """Trilinear splat of weights [N] at x [N, 3] onto voxel centres; returns [voxels]^3."""
    h = (hi - lo) / voxels
    g = (x - lo) / h - 0.5
    base = np.floor(g).astype(np.int64)
    f = g - base
    out = np.zeros((voxels,) * 3)
    w = np.stack([1.0 - f, f], axis=-1)  # [N, 3 (axis), 2 (offset)]
    scatter_add(out, base, w[:, 0, :, None, None] * w[:, 1, None, :, None] * w[:, 2, None, None, :]
                * weights[:, None, None, None])
    return out


def density_surface_mask(x: np.ndarray, volume: np.ndarray, cfg: SurfaceMaskConfig, lo: float, hi: float,
                         search_device: str | None = None) -> np.ndarray:
    """Particles within ``cfg.band`` voxels of the density iso-surface. x: [N, 3], volume: [N] -> [N] bool.
    ``search_device``: the torch device of the distances' search; None: the KD tree (module docstring)."""
    from scipy import ndimage
    from scipy.spatial import cKDTree
    from skimage import measure

    from physmorph.morph.frame_measures import voxel_density  # Taichi: only where a mask is built

    h = (hi - lo) / cfg.voxels
    rho = ndimage.gaussian_filter(voxel_density(x, volume, cfg.voxels, lo, hi), cfg.blur_sigma)
    positive = rho[rho > 0]
    if positive.size == 0:
        return np.zeros(len(x), bool)
    level = cfg.level * np.percentile(positive, 95)
    if not (rho.min() < level < rho.max()):
        return np.ones(len(x), bool)
    verts, _, _, _ = measure.marching_cubes(rho, level=level)
    verts = lo + (verts + 0.5) * h  # voxel index -> domain position of the voxel centre
    if search_device is not None:
        from physmorph.plasticity.nearest import nearest_points

        return nearest_points(verts, x, search_device)[0] <= cfg.band * h
    # only "within the band" matters: the bounded query prunes the far particles (inf distance)
    dist, _ = cKDTree(verts).query(x, k=1, distance_upper_bound=cfg.band * h * (1.0 + 1e-9), workers=-1)
    return dist <= cfg.band * h


def update_surface_mask(
    x: np.ndarray,  # [N, 3]
    volume: np.ndarray,  # [N]
    target_tree: cKDTree,
    cfg: SurfaceMaskConfig,
    lo: float,
    hi: float,
    previous: np.ndarray | None = None,  # [N] bool
    target_distance: np.ndarray | None = None,  # [N] distance of x to the target surface, when known
    search_device: str | None = None,  # the torch device of the distances' search; None: the KD trees
) -> np.ndarray:
    """Density mask ∪ near-target particles ∪ previous mask (never shrinks). Returns [N] bool."""
    if not cfg.enabled:
        return np.ones(len(x), bool)
    mask = density_surface_mask(x, volume, cfg, lo, hi, search_device)
    dist = target_distance
    if dist is None and search_device is not None:
        from physmorph.plasticity.nearest import nearest_points

        dist, _ = nearest_points(target_tree.data, x, search_device)
    elif dist is None:
        dist, _ = target_tree.query(x, k=1, distance_upper_bound=cfg.target_band * (1.0 + 1e-9), workers=-1)
    mask |= dist <= cfg.target_band
    if previous is not None:
        mask |= previous
    return mask
