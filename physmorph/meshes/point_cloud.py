"""A closed surface from a point cloud (points on a shape's surface, or filling it), so a shape can
arrive as points: marching cubes (scikit-image) on the points' signed distance.

The distance to the nearest point is zero on the points and grows away from them; its sign comes
from a solid: the voxels the points touch, closed over gaps of a few point spacings (dilated, holes
filled, eroded back), are inside. Marching cubes at level 0 then puts the surface through the points
themselves rather than half a voxel outside them. Points that bound no volume (an open patch, a
line) close into a sheet with no depth, and are refused: "no closed surface" in one line naming the file.

Open3D's Poisson or ball-pivoting reconstruction would do the same job; its wheel is 400 MB and
imports plotly and dash at import time, which a CPU workflow need not carry for one step.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree

from .errors import MeshError

# fewer points than this describe no shape (a handful of vertices is a broken mesh file, not a cloud)
MIN_POINTS = 100
# voxels along the longest extent at most (the surface's resolution: 2M voxels, ~1 s)
MAX_VOXELS = 128
# the points' spacing: the median distance to this many-th nearest neighbour (random samples leave
# gaps a few nearest-neighbour distances wide; this one is about the widest common gap)
SPACING_NEIGHBOUR = 8
# the solid keeps this share of its voxels when eroded by two more: else it is a sheet, enclosing nothing
MIN_DEEP_SHARE = 0.05


def point_spacing(points: np.ndarray) -> float:  # points: [N, 3]
    """The median distance from a point to its SPACING_NEIGHBOUR-th nearest other point."""
    d, _ = cKDTree(points).query(points, k=SPACING_NEIGHBOUR + 1)
    return float(np.median(d[:, -1]))


def _solid(points: np.ndarray, origin: np.ndarray, cell: float, shape: tuple[int, int, int],
           radius: int) -> tuple[np.ndarray, float]:  # points: [N, 3]
    """The voxels inside (a boolean [X, Y, Z] grid) and the share of them two voxels deep."""
    occupied = np.zeros(shape, bool)
    idx = np.clip(np.floor((points - origin) / cell).astype(int), 0, np.array(shape) - 1)
    occupied[tuple(idx.T)] = True
    ball = ndimage.generate_binary_structure(3, 2)
    filled = ndimage.binary_fill_holes(ndimage.binary_dilation(occupied, ball, iterations=radius))
    inside = ndimage.binary_erosion(filled, ball, iterations=radius, border_value=0) | occupied
    deep = ndimage.binary_erosion(inside, ball, iterations=2, border_value=0)
    return inside, float(deep.sum()) / max(float(inside.sum()), 1.0)


def surface_from_points(points: np.ndarray, label: str) -> trimesh.Trimesh:  # points: [N, 3]
    """A watertight mesh through ``points`` (see the module's docstring); MeshError naming ``label``
    where they are too few or enclose no volume."""
    from skimage.measure import marching_cubes

    points = np.unique(np.asarray(points, np.float64), axis=0)
    if len(points) < MIN_POINTS:
        raise MeshError(f"{label}: no faces and only {len(points)} points (a point cloud needs at least {MIN_POINTS})")
    extent = float(np.max(points.max(0) - points.min(0)))
    spacing = point_spacing(points)
    if not extent > 0 or not spacing > 0:
        raise MeshError(f"{label}: the points span no volume (extent {extent:g})")
    cell = max(0.5 * spacing, extent / MAX_VOXELS)
    radius = max(1, int(np.ceil(spacing / cell)))
    pad = radius + 2
    origin = points.min(0) - pad * cell
    shape = tuple(int(n) for n in np.ceil((points.max(0) - origin) / cell).astype(int) + pad + 1)
    inside, deep = _solid(points, origin, cell, shape, radius)
    if deep < MIN_DEEP_SHARE:
        raise MeshError(f"{label}: no closed surface results from its {len(points)} points: they enclose no volume "
                        "(an open surface or a patch; a closed shape's points, or a mesh, are needed)")
    centres = origin + (np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1) + 0.5) * cell
    distance, _ = cKDTree(points).query(centres.reshape(-1, 3), workers=-1)
    signed = np.where(inside, -1.0, 1.0) * distance.reshape(shape)
    verts, faces, _, _ = marching_cubes(signed, level=0.0, spacing=(cell, cell, cell))
    mesh = trimesh.Trimesh(verts + origin + 0.5 * cell, faces, process=True)
    # one body: a bubble of a voxel or two where the closing left a gap inside is not part of the shape
    mesh = max(mesh.split(only_watertight=False), key=lambda m: abs(m.volume))
    if mesh.volume < 0:
        mesh.invert()
    return mesh
