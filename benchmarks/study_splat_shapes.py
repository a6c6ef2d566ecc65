"""Is a run's α MSE held by where its particles are or by the shapes of their splats?

    python benchmarks/study_splat_shapes.py RUN.h5 PARTICLES.h5 TARGET.h5 [--profile config/mid.yaml]

For every saved frame of RUN (a finished run file with states, e.g. from
`benchmarks/study_convergence.py ... --set morph.save_every=10`), the α MSE over all the target's
views of the particles rendered three ways: with the run's F (the run's own metric), with F = I
(round splats of the rest size at the same positions), and with F / det(F)^(1/3) (each splat's
shape kept, its change of volume removed); each also as the share of the reachable gap. And the
spread of the deformation: the 99th percentile of the largest singular value and of the condition
number, the 1st of the smallest, the 1st and 99th of det F.
"""

from __future__ import annotations

import argparse

import h5py
import numpy as np

from physmorph.settings.workflow import load_settings
from physmorph.meshes.particles import load_particles
from physmorph.render.api import render_views
from physmorph.morph.targets import load_target


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run")
    ap.add_argument("particles")
    ap.add_argument("target")
    ap.add_argument("--profile", default=None, help="a profile YAML over config/config.yaml (its render settings)")
    ap.add_argument("--experiment", default="iso_bunny_full")
    args = ap.parse_args()
    settings = load_settings("config/config.yaml", *([args.profile] if args.profile else []))
    render_cfg = settings.experiment_config(args.experiment).render
    sigma0 = load_particles(args.particles).sigma0
    target = load_target(args.target)

    def alpha_mse(x: np.ndarray, F: np.ndarray) -> float:  # x [N, 3], F [N, 3, 3]
        alpha = render_views(x, F, sigma0, target.cameras, render_cfg)[0]
        return float(((alpha - target.alpha) ** 2).mean())

    with h5py.File(args.run) as f:
        metric = f["metrics/alpha_mse"][()]
        ceiling = float(f.attrs["ceiling_alpha_mse"])
        states = {int(g.split("_")[1]): (f["states"][g]["x"][()].astype(np.float64),
                                         f["states"][g]["F"][()].astype(np.float64)) for g in f["states"]}
    share = lambda a: 100.0 * (metric[0] - a) / (metric[0] - ceiling)  # noqa: E731
    print("| frame | run's metric | F | F = I | F / det^(1/3) | s_max p99 | s_min p1 | cond p99 | det F p1 / p99 |")
    print("|---|---|---|---|---|---|---|---|---|")
    for k, (x, F) in sorted(states.items()):
        s = np.linalg.svd(F, compute_uv=False)
        det = np.linalg.det(F)
        rows = [alpha_mse(x, F), alpha_mse(x, np.broadcast_to(np.eye(3), F.shape)),
                alpha_mse(x, F / np.cbrt(np.abs(det))[:, None, None])]
        cells = " | ".join(f"{a:.5f} ({share(a):.1f} %)" for a in [metric[k]] + rows)
        print(f"| {k} | {cells} | {np.percentile(s[:, 0], 99):.2f} | {np.percentile(s[:, 2], 1):.2f} | "
              f"{np.percentile(s[:, 0] / s[:, 2], 99):.2f} | {np.percentile(det, 1):.2f} / {np.percentile(det, 99):.2f} |",
              flush=True)


if __name__ == "__main__":
    main()
