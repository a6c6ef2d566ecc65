"""The body as a person sees it turned around, measured in 3D (the convergence table's body columns):

* outside the largest body: the share of the mass not in the largest connected body, the body
  being the grid cells that hold a particle, linked to their 26 neighbours (torn-off pieces and
  spray: a particle two cells from any other is a body of its own);
* components and genus of a closed surface: from its Euler characteristic chi = V - E + F, each
  closed orientable component of genus g having chi = 2 - 2g, so the surface's total genus is
  (2 c - chi) / 2 over its c components (a spurious tunnel raises it, a closed hole lowers it);
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
