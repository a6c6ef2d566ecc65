"""Stage 3: shell-biased volumetric particle sampling on the simulation grid (paper section 5, Setup).

The grid's cells (cell c covers [lo + c dx, lo + (c + 1) dx) per axis, between grid nodes) are
classified by the distance of their centre to the mesh surface:

- shell cells: distance < ``shell_cells * dx``; they get ``ppc_surface`` particles per axis
  (``ppc_surface^3`` per cell), because the surface is what is rendered and matched;
- interior cells: centre inside the mesh, farther from the surface; ``ppc_interior^3`` per cell.

Within a cell the particles are jittered-stratified: one uniformly random point in each of the
``ppc^3`` sub-cells (deterministic for a seed). A particle is kept iff it lies inside the mesh
(Embree ray containment; interior cells are wholly inside, so their particles skip the test).
Each particle carries the volume of its sub-cell, V_p = dx^3 / ppc^3, so sum_p V_p is an unbiased
estimate of the mesh volume, and mass m_p = rho V_p. The Gaussian size is sigma0 = c * d_nn with
d_nn the mean nearest-neighbour distance of the samples (c = 0.7 in the paper).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from physmorph.base.grid import BOUNDARY_CELLS, Grid
from physmorph.records.h5io import StageInputError, atomic_h5, open_h5, read_attr, read_field

if TYPE_CHECKING:  # trimesh, scipy and the mesh stage are imported where they are used: the
    # workflow reads stored_particle_count at every start
    import trimesh

# Cells whose centre is within this many cells of the surface get the surface PPC. The paper does
# not give its shell width; 2 cells reproduces its counts at grid 64, PPC 5/1 (iso: 496K here vs
# 534K in the paper; the range 372K-534K vs 375K-748K). sqrt(3)/2 is the least that still covers
# every cell the surface cuts.
DEFAULT_SHELL_CELLS = 2.0
# Dense surface samples per cell edge used to measure centre-to-surface distance.
_SURFACE_SAMPLES_PER_CELL = 6.0
# Extra distance (in cells) before a non-shell cell is trusted to lie wholly on one side.
_WHOLE_CELL_MARGIN = 0.35


def _surface_distance(mesh: trimesh.Trimesh, points: np.ndarray, spacing: float, rng: np.random.Generator) -> np.ndarray:
    """Approximate unsigned distance [Q] from points [Q, 3] to the mesh surface.

    Nearest of a dense area-weighted surface sample (mean spacing ~``spacing``) plus the mesh
    vertices; the error is O(spacing), small against a cell.
    """
    n = int(np.ceil(mesh.area / spacing ** 2)) + 1
    face = rng.choice(len(mesh.faces), size=n, p=mesh.area_faces / mesh.area)
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    bary = np.stack([1.0 - s, s * (1.0 - r2), s * r2], axis=1)  # uniform on each triangle
    tri = mesh.triangles[face]  # [n, 3, 3]
    surf = np.einsum("nk,nkd->nd", bary, tri)
    from scipy.spatial import cKDTree

    tree = cKDTree(np.concatenate([surf, mesh.vertices]))
    dist, _ = tree.query(points, k=1)
    return dist


def sample_volume(
    mesh: trimesh.Trimesh,
    grid: Grid,
    ppc_surface: int,
    ppc_interior: int,
    seed: int,
    shell_cells: float = DEFAULT_SHELL_CELLS,
    name: str | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shell-biased jittered-stratified samples of the solid bounded by ``mesh``.

    Returns x [N, 3] positions, volume [N] (dx^3 / ppc^3 of the particle's cell type) and
    is_surface [N] (particle came from a shell cell). Deterministic for a seed. Raises MeshError
    (naming ``name``) when the mesh does not fit within ``grid.interior_bounds()``.
    """
    from physmorph.meshes.errors import MeshError

    label = name or mesh.metadata.get("shape", "mesh")
    for key, val in (("ppc_surface", ppc_surface), ("ppc_interior", ppc_interior)):
        if int(val) != val or val < 1:
            raise ValueError(f"{key} must be a positive integer, got {val!r}")
    if not shell_cells >= 0:
        raise ValueError(f"shell_cells must be >= 0, got {shell_cells!r}")
    if len(mesh.faces) == 0:
        raise MeshError(f"{label}: mesh is empty, nothing to sample")
    inner_lo, inner_hi = grid.interior_bounds()
    if np.any(mesh.bounds[0] < inner_lo) or np.any(mesh.bounds[1] > inner_hi):
        raise MeshError(
            f"{label}: mesh bounds {np.round(mesh.bounds, 3).tolist()} do not fit the grid's particle region "
            f"[{inner_lo}, {inner_hi}]^3 (res {grid.res}, domain [{grid.lo}, {grid.hi}]; particles keep {BOUNDARY_CELLS} "
            f"cells from each face); raise sampling.grid_res, shrink the shape (shapes.{label}.size) or enlarge the domain",
            key="sampling.grid_res")
    rng = np.random.default_rng(seed)
    dx = grid.dx

    # Candidate cells: those overlapping the mesh bounding box.
    c_lo = np.floor((mesh.bounds[0] - grid.lo) / dx).astype(np.int64)
    c_hi = np.floor((mesh.bounds[1] - grid.lo) / dx).astype(np.int64)
    axes = [np.arange(c_lo[k], c_hi[k] + 1) for k in range(3)]
    cells = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)  # [C, 3]
    centres = grid.lo + (cells + 0.5) * dx
    dist = _surface_distance(mesh, centres, dx / _SURFACE_SAMPLES_PER_CELL, rng)
    shell = dist < shell_cells * dx
    # The sampled distance overestimates the true one by at most ~ the sample spacing, so a cell
    # counts as wholly inside only with a margin beyond half its diagonal; its particles then
    # skip the containment test. Other non-shell cells near the surface are tested per particle.
    whole_side = ~shell & (dist > (0.5 * np.sqrt(3.0) + _WHOLE_CELL_MARGIN) * dx)
    centre_inside = np.zeros(len(cells), dtype=bool)
    if whole_side.any():
        centre_inside[whole_side] = mesh.contains(centres[whole_side])
    whole_inside = whole_side & centre_inside
    partly = ~shell & ~whole_side

    def jittered(cell_idx: np.ndarray, ppc: int) -> np.ndarray:  # [len(cell_idx) * ppc^3, 3]
        sub = np.stack(np.meshgrid(*[np.arange(ppc)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
        u = rng.random((len(cell_idx), len(sub), 3))
        x = grid.lo + (cell_idx[:, None, :] + (sub[None, :, :] + u) / ppc) * dx
        return x.reshape(-1, 3)

    xs, vols, surf = [], [], []
    for mask, ppc, is_shell, test in (
        (shell, ppc_surface, True, True),
        (partly, ppc_interior, False, True),
        (whole_inside, ppc_interior, False, False),
    ):
        if not mask.any():
            continue
        x = jittered(cells[mask], int(ppc))
        if test:
            x = x[mesh.contains(x)]
        xs.append(x)
        vols.append(np.full(len(x), dx ** 3 / int(ppc) ** 3))
        surf.append(np.full(len(x), is_shell))
    x = np.concatenate(xs) if xs else np.zeros((0, 3))
    if len(x) == 0:
        raise MeshError(f"{label}: no particle fell inside the mesh (is it a closed solid larger than a cell?)")
    return x, np.concatenate(vols), np.concatenate(surf)


def mean_nn_distance(x: np.ndarray) -> float:
    """Mean distance from each point of x: [N, 3] to its nearest other point."""
    if len(x) < 2:
        raise ValueError("need at least two particles for a nearest-neighbour distance")
    from scipy.spatial import cKDTree

    d, _ = cKDTree(x).query(x, k=2)
    return float(d[:, 1].mean())


@dataclass(frozen=True)
class Particles:
    """Source particles as stored by sample_particles."""

    x: np.ndarray  # [N, 3]
    volume: np.ndarray  # [N]
    mass: np.ndarray  # [N]
    is_surface: np.ndarray  # [N] bool
    sigma0: float
    grid: Grid
    mesh_volume: float = float("nan")  # the sampled mesh's volume (NaN in files written before it was stored)

    @property
    def count(self) -> int:
        return int(self.x.shape[0])


def sample_particles(
    mesh_h5: str | os.PathLike,
    out_h5: str | os.PathLike,
    grid_res: int,
    ppc_surface: int,
    ppc_interior: int,
    density: float,
    sigma_scale: float = 0.7,
    seed: int = 0,
    preview_png: str | os.PathLike | None = None,
    shell_cells: float = DEFAULT_SHELL_CELLS,
) -> dict:
    """Stage sample_particles: mesh HDF5 -> particles HDF5 (and an optional preview PNG).

    Output layout: /x [N, 3] f64, /volume [N], /mass [N], /is_surface [N] bool; attrs count,
    n_surface, sigma0, d_nn, grid_res, lo, hi, dx, ppc_surface, ppc_interior, shell_cells,
    density, sigma_scale, seed, shape, sampled_volume, mesh_volume. Returns a summary dict.
    """
    if not (isinstance(grid_res, (int, np.integer)) and grid_res > 0):
        raise ValueError(f"grid_res must be a positive integer, got {grid_res!r}")
    if not (np.isfinite(density) and density > 0):
        raise ValueError(f"density must be positive, got {density!r}")
    if not (np.isfinite(sigma_scale) and sigma_scale > 0):
        raise ValueError(f"sigma_scale must be positive, got {sigma_scale!r}")
    from physmorph.meshes.prepare import load_mesh

    mesh = load_mesh(mesh_h5)
    shape = mesh.metadata["shape"]
    lo, hi = mesh.metadata["domain"]
    grid = Grid(int(grid_res), lo, hi)
    x, volume, is_surface = sample_volume(mesh, grid, ppc_surface, ppc_interior, seed, shell_cells, name=shape)
    mass = density * volume
    d_nn = mean_nn_distance(x)
    sigma0 = sigma_scale * d_nn
    summary = {
        "shape": shape, "count": int(len(x)), "n_surface": int(is_surface.sum()),
        "sampled_volume": float(volume.sum()), "mesh_volume": float(mesh.volume),
        "d_nn": d_nn, "sigma0": sigma0, "grid_res": grid.res, "dx": grid.dx,
    }
    config = {"grid_res": grid.res, "lo": lo, "hi": hi, "ppc_surface": int(ppc_surface),
              "ppc_interior": int(ppc_interior), "shell_cells": float(shell_cells), "density": float(density),
              "sigma_scale": float(sigma_scale), "seed": int(seed), "shape": shape}
    png_tmp = None
    if preview_png is not None:
        from physmorph.base.preview import particle_preview

        preview_png = Path(preview_png)
        png_tmp = preview_png.with_name(preview_png.name + ".partial.png")
    try:
        with atomic_h5(out_h5, config=config) as f:
            f.create_dataset("x", data=x.astype(np.float64))
            f.create_dataset("volume", data=volume.astype(np.float64))
            f.create_dataset("mass", data=mass.astype(np.float64))
            f.create_dataset("is_surface", data=is_surface.astype(bool))
            for key, val in config.items():
                f.attrs[key] = val
            f.attrs["dx"] = grid.dx
            for key in ("count", "n_surface", "sampled_volume", "mesh_volume", "d_nn", "sigma0"):
                f.attrs[key] = summary[key]
            if png_tmp is not None:  # inside the atomic block: a failing preview leaves no HDF5
                particle_preview(x, is_surface, png_tmp, f"{shape}: {len(x):,} particles (grid {grid.res}, "
                                 f"PPC {ppc_surface}/{ppc_interior})")
        if png_tmp is not None:
            os.replace(png_tmp, preview_png)
    finally:
        if png_tmp is not None:
            png_tmp.unlink(missing_ok=True)
    return summary


def stored_particle_count(path: str | os.PathLike) -> int | None:
    """The particle count a sample_particles file records, None when the file does not exist yet
    (a dry run, or a job whose inputs are still to be made)."""
    if not os.path.exists(path):
        return None
    with open_h5(path) as f:
        return int(read_attr(f, "count"))


def load_particles(path: str | os.PathLike) -> Particles:
    """Particles written by sample_particles; StageInputError on a missing/corrupt file or field."""
    with open_h5(path) as f:
        x = read_field(f, "x", (3,)).astype(np.float64)
        n = len(x)
        fields = {}
        for name in ("volume", "mass", "is_surface"):
            arr = read_field(f, name)
            if arr.shape != (n,):
                raise StageInputError(f"{path}: field '{name}' has shape {arr.shape}, expected ({n},)")
            fields[name] = arr
        sigma0 = float(read_attr(f, "sigma0"))
        grid = Grid(int(read_attr(f, "grid_res")), float(read_attr(f, "lo")), float(read_attr(f, "hi")))
        mesh_volume = float(f.attrs.get("mesh_volume", np.nan))
    if not np.all(np.isfinite(x)):
        raise StageInputError(f"{path}: field 'x' has non-finite values")
    return Particles(x=x, volume=fields["volume"].astype(np.float64), mass=fields["mass"].astype(np.float64),
                     is_surface=fields["is_surface"].astype(bool), sigma0=sigma0, grid=grid, mesh_volume=mesh_volume)
