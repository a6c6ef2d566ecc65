"""What an exported frame shows, measured (the convergence table's stray and surface columns):

* stray share: the share of the body's mass farther than STRAY_DX grid cells outside the target's
  surface (the loose spray a picture shows around thin parts);
* surface distance: the symmetric Chamfer distance between the exported surface and the target
  mesh, (mean_a min_b |a - b| + mean_b min_a |b - a|) / 2 over SURFACE_SAMPLES points of each, in
  grid cells;
* closed: whether the exported surface is watertight;
* the body in 3D (physmorph.reports.export.body): the mass outside the largest connected body, the
  exported surface's components, the body's genus (its tunnels at half a cell) beside the target
  mesh's measured the same way, the exported surface's own genus (its Euler characteristic: every
  tunnel the drawing has, however narrow), the 95th-percentile surface distance and the surface's
  roughness.

The target's outside distance comes from its prepared mesh voxelised at half a cell (inside by
ray test) and a Euclidean distance transform of the outside.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import trimesh

from physmorph.reports.export.columns import MEASURE_COLUMNS
from physmorph.reports.export.body import (body_genus, components_and_genus, largest_body_outside_share,
                                           roughness_percent, surface_distance_p95)

STRAY_DX = 2.0  # a particle this many grid cells outside the target's surface is stray
SURFACE_SAMPLES = 20000


def target_mesh(mesh_h5: str | Path) -> trimesh.Trimesh:
    with h5py.File(mesh_h5, "r") as f:
        return trimesh.Trimesh(f["vertices"][()], f["faces"][()], process=False)


@lru_cache(maxsize=4)
def _outside_distance(mesh_h5: str, dx: float) -> tuple[np.ndarray, np.ndarray, float]:
    """(distance to the target outside it, in domain units, on a grid of half cells [X, Y, Z];
    the grid's origin [3]; its spacing)."""
    from scipy.ndimage import distance_transform_edt

    mesh = target_mesh(mesh_h5)
    cell = 0.5 * dx
    pad = STRAY_DX * dx + 4 * cell
    lo, hi = mesh.bounds[0] - pad, mesh.bounds[1] + pad
    shape = np.ceil((hi - lo) / cell).astype(int) + 1
    axes = [lo[i] + cell * np.arange(shape[i]) for i in range(3)]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    inside = mesh.contains(nodes).reshape(shape)
    return distance_transform_edt(~inside) * cell, lo, cell


def stray_share(x: np.ndarray,  # [N, 3] positions
                mass: np.ndarray,  # [N] masses (or volumes: any per-particle weight)
                mesh_h5: str | Path, dx: float) -> float:
    """Share of the weight farther than STRAY_DX cells outside the target mesh (the module docstring)."""
    from scipy.ndimage import map_coordinates

    dist, lo, cell = _outside_distance(str(mesh_h5), float(dx))
    idx = ((np.asarray(x, np.float64) - lo) / cell).T
    # beyond the grid (padded past the threshold) a particle is farther than the threshold
    d = map_coordinates(dist, idx, order=1, mode="constant", cval=np.inf)
    w = np.asarray(mass, np.float64)
    return float(w[d > STRAY_DX * dx].sum() / w.sum())


def _surface_samples(mesh: trimesh.Trimesh, seed: int = 0) -> np.ndarray:  # [SURFACE_SAMPLES, 3]
    return trimesh.sample.sample_surface_even(mesh, SURFACE_SAMPLES, seed=seed)[0]


def surface_distance(mesh: trimesh.Trimesh, target: trimesh.Trimesh, dx: float, seed: int = 0) -> float:
    """Symmetric Chamfer distance between two surfaces, in grid cells (the module docstring)."""
    return _chamfer_dx(_surface_samples(mesh, seed), _surface_samples(target, seed), dx)


def _chamfer_dx(a: np.ndarray,  # [S, 3]
                b: np.ndarray,  # [S, 3]
                dx: float) -> float:
    from scipy.spatial import cKDTree

    ab = cKDTree(b).query(a)[0].mean()
    ba = cKDTree(a).query(b)[0].mean()
    return float(0.5 * (ab + ba) / dx)


@lru_cache(maxsize=4)
def _target_surface(mesh_h5: str, dx: float) -> tuple[np.ndarray, int]:
    """The target mesh's surface samples and its body's genus (read once per target)."""
    target = target_mesh(mesh_h5)
    return _surface_samples(target), body_genus(target, dx)


def frame_measures(frame: int, state: dict, mesh: trimesh.Trimesh, target_mesh_h5: str | Path) -> dict:
    """The row of measures.csv for one exported frame (state: physmorph.reports.export.runs.frame_state
    with the particle file, mesh: its exported surface in domain coordinates)."""
    dx = float(state["dx"])
    target_samples, target_genus = _target_surface(str(target_mesh_h5), dx)
    samples = _surface_samples(mesh)
    components, surface_genus = components_and_genus(mesh)
    return {"frame": int(frame),
            "stray_share": stray_share(state["x"], state["volume"], target_mesh_h5, dx),
            "surface_distance_dx": _chamfer_dx(samples, target_samples, dx),
            "closed": bool(mesh.is_watertight), "faces": int(len(mesh.faces)),
            "outside_largest_body": largest_body_outside_share(state["x"], state["volume"], dx),
            "components": components, "genus": body_genus(mesh, dx), "target_genus": target_genus,
            "surface_genus": surface_genus,
            "surface_p95_dx": surface_distance_p95(samples, target_samples, dx),
            "roughness_percent": roughness_percent(mesh)}


def write_measures(rows: list[dict], path: Path) -> None:
    pd.DataFrame(rows, columns=list(MEASURE_COLUMNS)).to_csv(path, index=False)
