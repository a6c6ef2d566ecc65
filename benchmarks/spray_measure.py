"""Where a finished run's body sprays: loose particles, and material outside the target.

    python benchmarks/spray_measure.py RUN.h5 PARTICLES.h5 TARGET_MESH.h5 [--frame K] [--image out.png]

For the saved frame K (default: the last) of a run, with the particle file it was made from and
the target's prepared mesh (results/{profile}/meshes/{shape}.h5):

* loose: the volume share of particles with little material near them, the current volumes
  V_p det F_p of the particles within one grid cell summed and divided by that ball's volume
  (4/3 pi dx^3), below --loose (0.1; the body's median is ~0.8). It picks out the paper-scale
  bunny's ear spray and also a letter's thin face film (docs/study/log.md finding 227);
* beyond: the volume shares farther than 0.5, 1 and 2 cells outside the target mesh (the export's
  stray share is the 2-cell one), which also count material still on its way.

--image writes three projections with the loose particles in red. The neighbour query takes about
a minute at 471K particles on 2 cores.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from physmorph.reports.export import measures  # noqa: E402
from physmorph.reports.export.runs import frame_state, saved_frames  # noqa: E402


def loose_fraction(x: np.ndarray,  # [N, 3] positions
                   volume: np.ndarray,  # [N] current volumes V_p det F_p
                   dx: float) -> np.ndarray:  # [N]
    """The material within one cell of each particle (itself included) over the ball's volume."""
    from scipy.spatial import cKDTree

    near = cKDTree(x).query_ball_point(x, r=dx, workers=2)
    return np.array([volume[i].sum() for i in near]) / (4.0 / 3.0 * np.pi * dx ** 3)


def outside_cells(x: np.ndarray,  # [N, 3]
                  mesh_h5: str, dx: float) -> np.ndarray:  # [N]
    """Each particle's distance outside the target mesh, in cells (0 inside; inf beyond the grid)."""
    from scipy.ndimage import map_coordinates

    dist, lo, cell = measures._outside_distance(str(mesh_h5), float(dx))
    return map_coordinates(dist, ((x - lo) / cell).T, order=1, mode="constant", cval=np.inf) / dx


def write_image(x: np.ndarray, loose: np.ndarray, title: str, path: str) -> None:  # x [N, 3], loose [N] bool
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keep = np.random.default_rng(0).random(len(x)) < 150000 / len(x)
    fig, axs = plt.subplots(1, 3, figsize=(15, 5))
    for ax, (a, b) in zip(axs, [(0, 1), (0, 2), (2, 1)]):
        rest = keep & ~loose
        ax.scatter(x[rest, a], x[rest, b], s=0.2, c="0.75")
        ax.scatter(x[loose, a], x[loose, b], s=1.5, c="tab:red")
        ax.set_aspect("equal")
        ax.set_xlabel("xyz"[a])
        ax.set_ylabel("xyz"[b])
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=80)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run")
    ap.add_argument("particles")
    ap.add_argument("target_mesh")
    ap.add_argument("--frame", type=int, default=None)
    ap.add_argument("--loose", type=float, default=0.1)
    ap.add_argument("--image", default=None)
    args = ap.parse_args()
    k = saved_frames(args.run)[-1] if args.frame is None else args.frame
    s = frame_state(args.run, k, particles_h5=args.particles)
    dx, v = float(s["dx"]), s["volume"] * s["det_F"]
    share = lambda sel: 100.0 * s["volume"][sel].sum() / s["volume"].sum()  # noqa: E731
    frac = loose_fraction(s["x"], v, dx)
    loose = frac < args.loose
    out = outside_cells(s["x"], args.target_mesh, dx)
    print(f"{Path(args.run).stem} frame {k}: loose {share(loose):.3f} % ({int(loose.sum())} particles; median "
          f"material within a cell {np.median(frac):.2f}); outside the target beyond 0.5 / 1 / 2 cells "
          f"{share(out > 0.5):.2f} / {share(out > 1):.2f} / {share(out > 2):.2f} %")
    if loose.any():  # where the loose particles lie: the stray pull acts beyond stray_pull_onset cells
        q = np.quantile(out[loose], [0.1, 0.5, 0.9])
        print(f"  the loose particles' distance outside the target: 10 / 50 / 90 % quantiles "
              f"{q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f} cells; inside {100 * np.mean(out[loose] == 0):.0f} %, "
              f"beyond 1 cell {100 * np.mean(out[loose] > 1):.0f} %")
    if args.image:
        write_image(s["x"], loose, f"{Path(args.run).stem} frame {k}: loose particles (red, {int(loose.sum())})",
                    args.image)


if __name__ == "__main__":
    main()
