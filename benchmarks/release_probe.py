"""Release probe: does a morph's shape persist once the control is switched off?

Takes the last saved state of finished runs (x, F, Fp), zeroes the control dFc and the velocities,
and simulates K more frames with no optimisation and no plasticity, rendering the alpha MSE
against the run's target after each. The release rebound is the share of the run's gain that is
lost: 100 (a_release - a_final) / (a_0 - a_final) (0 %: the rest state holds the morphed shape;
100 %: back to where the run started). Measures what the paper's Chamfer plasticity is for
(migrating the rest state so achieved deformation persists, section 3.4); docs/study/log.md.

    python benchmarks/release_probe.py iso_bunny_full iso_bunny_f_inject --frames 40
    python benchmarks/release_probe.py iso_bunny_full --runs /tmp/physmorph_study/cs_eta02
"""

from __future__ import annotations

import argparse
from pathlib import Path

import h5py
import numpy as np

from physmorph.settings.workflow import load_settings
from physmorph.morph.loop import morph_config
from physmorph.mpm.solver import MPMSolver
from physmorph.mpm.state import ParticleState
from physmorph.meshes.particles import load_particles
from physmorph.render.api import render_views
from physmorph.records.runfile import read_metrics
from physmorph.morph.targets import load_target

REPO = Path(__file__).resolve().parent.parent


def release_curve(run_h5: Path, particles_h5: Path, target_h5: Path, mc, frames: int) -> tuple[np.ndarray, str]:
    """Alpha MSE after 0..frames released frames (control off) from the run's last saved state."""
    parts, target = load_particles(particles_h5), load_target(target_h5)
    with h5py.File(run_h5, "r") as f:
        last = sorted(f["states"])[-1]
        x, F, Fp = (f["states"][last][k][()].astype(np.float64) for k in ("x", "F", "Fp"))
    n = len(x)
    st = ParticleState(x=x, v=np.zeros((n, 3)), F=F, C=np.zeros((n, 3, 3)), Fp=Fp, mass=parts.mass, volume=parts.volume)
    solver = MPMSolver(mc.mpm, n)

    def alpha_mse(s: ParticleState) -> float:
        alpha, _ = render_views(s.x, s.F, parts.sigma0, target.cameras, mc.render)
        return float(((alpha - target.alpha) ** 2).mean())

    curve = [alpha_mse(st)]
    for _ in range(frames):
        solver.load_state(st)
        solver.reset_control()
        st = solver.rollout()
        curve.append(alpha_mse(st))
    return np.array(curve), last


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("experiments", nargs="+")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--profile", default=None, help="extra config file merged on config/config.yaml")
    ap.add_argument("--runs", default=None, help="directory of the run files (default results/{profile}/runs)")
    args = ap.parse_args()
    files = [REPO / "config" / "config.yaml"] + ([Path(args.profile)] if args.profile else [])
    settings = load_settings(*files)
    root = REPO / "results" / settings.profile
    runs = Path(args.runs) if args.runs else root / "runs"
    res = settings.sampling.tag
    print("| run | saved state | alpha MSE frame 0 / final | after release (every 10 frames) | release rebound |")
    print("|---|---|---|---|---|")
    for name in args.experiments:
        exp = settings.experiment(name)
        run = runs / f"{name}.h5"
        curve, last = release_curve(run, root / "particles" / f"{exp.source}_{res}.h5",
                                    root / "targets" / f"{exp.target}_{res}.h5", morph_config(settings, name), args.frames)
        a = read_metrics(run)["alpha_mse"]
        rebound = 100.0 * (curve[-1] - a[-1]) / (a[0] - a[-1])
        print(f"| {run} | {last} | {a[0]:.4f} / {a[-1]:.4f} | {' '.join(f'{c:.4f}' for c in curve[::10])} "
              f"| {rebound:.0f} % |", flush=True)


if __name__ == "__main__":
    main()
