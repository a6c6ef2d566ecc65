"""Where a run's body misses its target, and how far its material is from where the plan sent it.

    python benchmarks/body_gaps.py RUN.h5 PARTICLES.h5 TARGET.h5 MESH.h5 [--voxel 0.25]

RUN.h5 a run file, PARTICLES.h5 its source particles, TARGET.h5 its target (results/{profile}/...),
MESH.h5 the target's prepared mesh (results/{profile}/meshes/{shape}.h5, in the simulation's frame).
For the last saved frame: the surface drawn at the solver's volume (as exported,
physmorph.reports.export.surface) against the target mesh on a voxel grid: the voxels inside the
target and outside the body grouped into connected pieces, the largest with their voxels, centre
and depth (the farthest voxel from the target's surface, in voxels: a piece deep inside is a hollow
or a missing part, a thin one a skin), and the voxels the body puts outside the target. Then, at the
first, middle and last saved frames, the mass-weighted distance of the particles to their transport
destinations (physmorph.plasticity.transport, the plasticity's plan from the source at rest), in
cells, and the share of the mass farther than 2 and 4 cells from them. Last, where the body's solid
has a higher genus than the target's, which of those pieces carries it: the missing pieces whose
filling, and the pieces outside the target whose removal, lowers the body's genus (a tear through a
thin part, or a bridge across a gap of the target).
"""

from __future__ import annotations

import argparse

import h5py
import numpy as np
import trimesh
from scipy import ndimage
from skimage import measure

from physmorph.base.grid import Grid
from physmorph.base.linalg3 import det3
from physmorph.plasticity.transport import destinations_in_grid_mass
from physmorph.reports.export.surface import particle_surface


def solid_genus(solid: np.ndarray) -> int:  # [X, Y, Z] bool
    """The summed genus of the closed surfaces of a voxel solid (marching cubes, each piece's Euler number)."""
    verts, faces, _, _ = measure.marching_cubes(np.pad(solid.astype(np.float32), 1), 0.5)
    pieces = trimesh.Trimesh(verts, faces).split(only_watertight=False)
    return int(sum((2 - piece.euler_number) // 2 for piece in pieces))


def genus_carriers(in_body: np.ndarray, in_target: np.ndarray,  # [X, Y, Z] bool each
                   axes: list, tried: int = 25) -> None:  # axes: the voxel centres along x, y, z
    """Print the pieces that carry the body's surplus genus: of the ``tried`` largest missing pieces
    (in the target, not the body) those whose filling lowers it, and of the largest pieces in the body
    outside the target (dilated by two voxels, so a skin's offset does not count) those whose
    removal does."""
    body_genus, target_genus = solid_genus(in_body), solid_genus(in_target)
    print(f"genus of the solids: body {body_genus}, target {target_genus}")
    if body_genus <= target_genus:
        return
    outside = in_body & ~ndimage.binary_dilation(in_target, iterations=2)
    for what, pieces, change in (("missing", in_target & ~in_body, np.logical_or),
                                 ("outside", outside, lambda solid, piece: solid & ~piece)):
        labels, n = ndimage.label(pieces)
        sizes = ndimage.sum(pieces, labels, range(1, n + 1))
        for i in np.argsort(-sizes)[:tried]:
            piece = labels == i + 1
            lowered = solid_genus(change(in_body, piece))
            if lowered < body_genus:
                centre = [a[idx].mean() for a, idx in zip(axes, np.nonzero(piece))]
                span = [np.ptp(a[idx]) for a, idx in zip(axes, np.nonzero(piece))]
                print(f"  {what} piece of {sizes[i]:.0f} voxels at ({centre[0]:.1f}, {centre[1]:.1f}, {centre[2]:.1f}), "
                      f"spanning {span[0]:.1f} x {span[1]:.1f} x {span[2]:.1f}: the body's genus {body_genus} -> {lowered}")


def missing_pieces(body: trimesh.Trimesh, target: trimesh.Trimesh, voxel: float, shown: int = 6) -> None:
    """Print the body against the target on voxels of side ``voxel``: IoU, missing pieces, outside,
    and the pieces that carry a surplus genus (genus_carriers)."""
    lo = np.minimum(body.bounds[0], target.bounds[0]) - 2 * voxel
    hi = np.maximum(body.bounds[1], target.bounds[1]) + 2 * voxel
    axes = [np.arange(a, b, voxel) + voxel / 2 for a, b in zip(lo, hi)]  # voxel centres: none on a bound's face
    points = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)  # [V, 3]
    shape = tuple(len(a) for a in axes)
    in_target, in_body = target.contains(points).reshape(shape), body.contains(points).reshape(shape)
    missing = in_target & ~in_body
    print(f"voxels of {voxel}: target {in_target.sum()}, body {in_body.sum()}, IoU "
          f"{(in_target & in_body).sum() / (in_target | in_body).sum():.3f}, inside the target and not the body "
          f"{missing.sum()}, in the body outside the target {(in_body & ~in_target).sum()}")
    labels, n = ndimage.label(missing)
    sizes = ndimage.sum(missing, labels, range(1, n + 1))
    depth = ndimage.distance_transform_edt(in_target)
    for i in np.argsort(-sizes)[:shown]:
        piece = labels == i + 1
        centre = [a[idx].mean() for a, idx in zip(axes, np.nonzero(piece))]
        print(f"  missing piece of {sizes[i]:.0f} voxels at ({centre[0]:.1f}, {centre[1]:.1f}, {centre[2]:.1f}), "
              f"{depth[piece].max():.1f} voxels deep")
    genus_carriers(in_body, in_target, axes)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    for name in ("run", "particles", "target", "mesh"):
        ap.add_argument(name)
    ap.add_argument("--voxel", type=float, default=None, help="voxel side (default: half the grid's cell)")
    args = ap.parse_args(argv)
    with h5py.File(args.target, "r") as t:
        grid_mass = t["grid_mass"][()].astype(np.float64)
        grid = Grid(grid_mass.shape[0], float(t.attrs["lo"]), float(t.attrs["hi"]))
    with h5py.File(args.particles, "r") as p:
        x0, mass, rest = (p[k][()].astype(np.float64) for k in ("x", "mass", "volume"))
    with h5py.File(args.mesh, "r") as m:
        target = trimesh.Trimesh(m["vertices"][()], m["faces"][()], process=False)
    destination = destinations_in_grid_mass(x0, mass, grid_mass, grid, 1.0)  # [N, 3]
    share = mass / mass.sum()
    with h5py.File(args.run, "r") as f:
        saved = sorted(f["states"])
        for name in dict.fromkeys([saved[0], saved[len(saved) // 2], saved[-1]]):
            x = f["states"][name]["x"][()].astype(np.float64)
            cells = np.linalg.norm(x - destination, axis=1) / grid.dx
            print(f"{name}: mean distance to the destinations {np.sum(share * cells):.2f} cells, mass farther "
                  f"than 2 cells {share[cells > 2].sum():.3f}, than 4 cells {share[cells > 4].sum():.3f}")
        last = f["states"][saved[-1]]
        x, F = last["x"][()].astype(np.float64), last["F"][()].astype(np.float64)
    body = particle_surface(x, rest, det3(F), grid.dx)
    missing_pieces(body, target, args.voxel or grid.dx / 2)


if __name__ == "__main__":
    main()
