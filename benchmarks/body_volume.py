"""The body's volume two ways, for saved frames of a run: the solver's, sum_p V0_p det F_p (what the
run file's total_volume and the results pages' volume change report, and what the exported surface
is scaled to), against where the particles' mass lies on the grid (the same splat as the volume
IoU): the cells holding more than half the target's interior node mass (VOLUME_FILL of the
INTERIOR_PERCENTILE, physmorph.morph.quality) against the target's, and the body's mass-weighted
node mass over the target's. A body packed by a share c fills ~c fewer cells at a density ~1/(1 - c)
higher; one whose det F drifted without moving does neither (docs/study/log.md finding 246). Then
the exported surface's components and genus (physmorph.reports.export) drawn at the solver's
volume, at the rest volume (every det F 1) and at the solver's volume spread evenly (every det F
its mean): how much the genus a page reports depends on the volume the surface is drawn at
(finding 247).

    python benchmarks/body_volume.py RUN.h5 PARTICLES.h5 TARGET.h5 [FRAME ...]

PARTICLES.h5 and TARGET.h5: the run's source particles and target (results/{profile}/particles/,
targets/); frames: saved states (default: the first and the last).
"""

from __future__ import annotations

import sys

import h5py
import numpy as np

from physmorph.base.grid import Grid, splat_mass
from physmorph.base.linalg3 import det3
from physmorph.morph.quality import INTERIOR_PERCENTILE, VOLUME_FILL
from physmorph.reports.export.body import components_and_genus
from physmorph.reports.export.surface import particle_surface


def mass_weighted_node_mass(m: np.ndarray) -> float:  # m: [R, R, R]
    """sum_I m_I^2 / sum_I m_I: the node mass the average unit of mass sits on."""
    return float((m * m).sum() / m.sum())


def main(argv: list[str]) -> None:
    run_h5, particles_h5, target_h5, *frames = argv
    with h5py.File(target_h5, "r") as t:
        target = t["grid_mass"][()].astype(np.float64)
        grid = Grid(target.shape[0], float(t.attrs["lo"]), float(t.attrs["hi"]))
    with h5py.File(particles_h5, "r") as p:
        mass, rest = p["mass"][()].astype(np.float64), p["volume"][()].astype(np.float64)
    target *= mass.sum() / target.sum()
    fill = VOLUME_FILL * float(np.percentile(target[target > 0], INTERIOR_PERCENTILE))
    target_cells, target_density = int((target > fill).sum()), mass_weighted_node_mass(target)
    with h5py.File(run_h5, "r") as f:
        saved = sorted(int(k.removeprefix("frame_")) for k in f["states"])
        for k in [int(a) for a in frames] or [saved[0], saved[-1]]:
            state = f[f"states/frame_{k:04d}"]
            x, F = state["x"][()].astype(np.float64), state["F"][()].astype(np.float64)
            m = splat_mass(x, mass, grid)
            print(f"frame {k}: sum V0 det F / sum V0 {(rest * det3(F)).sum() / rest.sum():.3f}, "
                  f"filled cells {int((m > fill).sum())} (the target's {target_cells}), "
                  f"mass-weighted node mass / the target's {mass_weighted_node_mass(m) / target_density:.3f}")
            J = det3(F)
            for label, j in (("the solver's volume", J), ("the rest volume", np.ones(len(x))),
                             ("the solver's volume spread evenly", np.full(len(x), (rest * J).sum() / rest.sum()))):
                surface = particle_surface(x, rest, j, grid.dx)
                components, genus = components_and_genus(surface)
                print(f"  surface at {label}: volume {surface.volume:.0f}, {components} component(s), genus {genus}")


if __name__ == "__main__":
    main(sys.argv[1:])
