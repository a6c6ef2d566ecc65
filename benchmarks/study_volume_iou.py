"""The 3D checks (physmorph.morph.quality.volume_metrics: volume IoU, overfilled mass) at the saved frames of run files, for runs written
before the metric was recorded per frame (docs/study/log.md, part 11).

    python benchmarks/study_volume_iou.py --particles results/default/particles/iso_32x2x1.h5 \\
        --target results/default/targets/cow_32x2x1.h5 results/default/runs/iso_cow_*.h5

Prints one line per run: both checks at every saved frame and the alpha MSE at the last.
"""

from __future__ import annotations

import argparse

import h5py
import numpy as np

from physmorph.morph.quality import volume_metrics
from physmorph.morph.targets import load_target


def saved_volume_metrics(run_h5: str, mass: np.ndarray, target) -> dict[int, dict[str, float]]:  # mass [N]
    """{frame: {volume_iou, overfilled_mass}} over the frames the run file saved."""
    with h5py.File(run_h5, "r") as f:
        frames = sorted(f["states"].keys())
        return {int(k.split("_")[1]): volume_metrics(f["states"][k]["x"][()], mass, target.grid_mass, target.grid)
                for k in frames}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--particles", required=True, help="the runs' source particle file (its masses)")
    ap.add_argument("--target", required=True, help="the runs' target file")
    ap.add_argument("runs", nargs="+")
    args = ap.parse_args(argv)
    with h5py.File(args.particles, "r") as f:
        mass = f["mass"][()]
    target = load_target(args.target)
    for run in args.runs:
        v = saved_volume_metrics(run, mass, target)
        with h5py.File(run, "r") as f:
            a = f["metrics/alpha_mse"][()]
        print(f"{run}: volume IoU " + " ".join(f"{k}:{val['volume_iou']:.3f}" for k, val in v.items())
              + " | overfilled mass " + " ".join(f"{k}:{val['overfilled_mass']:.2f}" for k, val in v.items())
              + f" | alpha final {a[-1]:.4f}")


if __name__ == "__main__":
    main()
