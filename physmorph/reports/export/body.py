"""The body as a person sees it turned around, measured in 3D (the convergence table's body columns):

* outside the largest body: the share of the mass not in the largest connected body, the body
  being the grid cells that hold a particle, linked to their 26 neighbours (torn-off pieces and
  spray: a particle two cells from any other is a body of its own);
* components and genus of a closed surface: from its Euler characteristic chi = V - E + F, each
  closed orientable component of genus g having chi = 2 - 2g, so the surface's total genus is
  (2 c - chi) / 2 over its c components (a spurious tunnel raises it, a closed hole lowers it);
* the body's genus: the tunnels through the solid a closed surface encloses, voxelised at
  BODY_PITCH_DX of a grid cell (the voxels the surface touches, then filled), counted from the
  solid's Euler number (26-connected, its background 6-connected): chi = pieces - tunnels +
  cavities. A tunnel narrower than about half a cell is never counted, one a cell wide always
  (between, by where the voxels fall). Two walls less than a cell apart share the grid nodes
  whose velocities move them, so the physics cannot hold such a tunnel open or shut; the surface
  drawn over the particles opens or shuts it with its own grid's settings (docs/study/log.md
  findings 322 and 324). The voxels also close a gap narrower than about a voxel, which can join
  two parts that nearly touch into a loop the surface does not have (Homer's legs, a third of a
  unit apart at the ankles: finding 327), so the count is the smaller of the solid's and the
  closed surface's own genus: a tunnel is counted where the surface has it and it is as wide as
  the body's scale. The target mesh is measured the same way;
* surface distance, 95th percentile: the 95th percentile of the distance from each of two point
  samples of the surfaces to the other surface, the larger of the two directions, in grid cells (a
  mean hides a missing hole or a stroke: this does not);
* roughness: how much of the surface's area is lumps and wrinkles, 100 (A / A_smooth - 1) %, A_smooth
  the area after ROUGHNESS_PASSES more Taubin passes, at the body's volume (0 for a smooth body).
"""

from __future__ import annotations

import numpy as np
import trimesh

from physmorph.base.grid import occupied_pieces

ROUGHNESS_PASSES = 50
P95 = 95.0
# The body's tunnels are counted in voxels of this many grid cells (the module docstring).
BODY_PITCH_DX = 0.5


def largest_body_outside_share(x: np.ndarray,  # [N, 3] positions
                               mass: np.ndarray,  # [N] masses (or any per-particle weight)
                               dx: float) -> float:
    """Share of the weight outside the largest connected body (the module docstring): O(N), the
    occupied cells in 26-connected pieces (physmorph.base.grid.occupied_pieces)."""
    w = np.asarray(mass, np.float64)
    piece, count = occupied_pieces(x, dx)
    body = np.bincount(piece, weights=w, minlength=count + 1)
    return float(max(0.0, 1.0 - body.max() / w.sum()))  # one body: 0, not its rounding (-1e-16)


def components_and_genus(mesh: trimesh.Trimesh) -> tuple[int, int]:
    """(closed components, total genus) of a closed surface; (-1, -1) for one that is not closed
    (its Euler characteristic says nothing of its genus)."""
    if not mesh.is_watertight:
        return -1, -1
    components = int(mesh.body_count)
    chi = int(mesh.euler_number)
    return components, (2 * components - chi) // 2


def solid_topology(solid: np.ndarray) -> tuple[int, int, int]:  # solid: [X, Y, Z] bool
    """(pieces, tunnels, cavities) of a voxel solid, 26-connected (its background 6-connected):
    the Euler number chi = pieces - tunnels + cavities (scikit-image), the pieces and the cavities
    (background pieces that do not reach the padded border) counted directly."""
    from scipy import ndimage
    from skimage.measure import euler_number

    padded = np.pad(np.asarray(solid, dtype=bool), 1)
    pieces = int(ndimage.label(padded, structure=np.ones((3, 3, 3)))[1])
    cavities = int(ndimage.label(~padded)[1]) - 1  # the default structure is 6-connected
    chi = int(euler_number(padded, connectivity=3))
    return pieces, pieces + cavities - chi, cavities


def voxel_topology(mesh: trimesh.Trimesh, pitch: float) -> tuple[int, int, int]:
    """solid_topology of ``mesh`` voxelised at ``pitch`` (the voxels its surface touches, then filled)."""
    return solid_topology(mesh.voxelized(pitch).fill().matrix)


def body_genus(mesh: trimesh.Trimesh, dx: float) -> int:
    """The tunnels through the solid a closed surface encloses, in voxels of BODY_PITCH_DX grid cells,
    no more than the surface's own genus (the module docstring); -1 for a surface that is not closed."""
    if not mesh.is_watertight:
        return -1
    return min(components_and_genus(mesh)[1], voxel_topology(mesh, BODY_PITCH_DX * float(dx))[1])


def surface_distance_p95(samples: np.ndarray,  # [S, 3] points on the surface
                         target_samples: np.ndarray,  # [S, 3] points on the target's surface
                         dx: float) -> float:
    """The larger of the two directions' 95th-percentile distance, in grid cells (the module docstring)."""
    from scipy.spatial import cKDTree

    ab = cKDTree(target_samples).query(samples)[0]
    ba = cKDTree(samples).query(target_samples)[0]
    return float(max(np.percentile(ab, P95), np.percentile(ba, P95)) / dx)


def roughness_percent(mesh: trimesh.Trimesh) -> float:
    """100 (A / A_smooth - 1): the area lumps and wrinkles add over the surface smoothed further,
    the smoothed surface's area taken at the body's volume (A_smooth (V / V_smooth)^(2/3): Taubin's
    passes swell a surface a little, which alone would read as negative roughness)."""
    from physmorph.reports.export.surface import taubin_smooth

    smooth = trimesh.Trimesh(taubin_smooth(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces),
                                           ROUGHNESS_PASSES), mesh.faces, process=False)
    volume, volume_smooth = abs(mesh.volume), abs(smooth.volume)
    if not (smooth.area > 0 and volume > 0 and volume_smooth > 0):
        return float("nan")
    return float(100.0 * (mesh.area / (smooth.area * (volume / volume_smooth) ** (2.0 / 3.0)) - 1.0))
