"""Per-frame α MSE of whole runs on one thread: record it, or compare the code now against a record.

    python benchmarks/identity_baseline.py record docs/study/identity_baseline.csv
    python benchmarks/identity_baseline.py compare docs/study/identity_baseline.csv

Runs each experiment (default: the default profile's iso -> bunny full and cow -> duck full) for
all its frames with the shipped settings and ``threads: 1`` (on one thread the CPU runs are
bit-identical run to run), in --workdir. ``record`` writes one row per (experiment, frame) with the
α MSE and the commit; ``compare`` runs them again and exits 1 where a frame's α MSE differs from
the record by more than --rtol (relative), printing the largest difference per experiment. A
restructuring of the code that promises unchanged results is checked with it.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import shutil
import sys
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_morph import prepare  # noqa: E402

from physmorph.settings.workflow import load_settings  # noqa: E402
from physmorph.morph.loop import morph_config, run_morph
from physmorph.records.runfile import read_metrics
from physmorph.records.provenance import git_state  # noqa: E402
from physmorph.records.runfile import partial_dir  # noqa: E402
from physmorph.stages import set_threads  # noqa: E402

REPO = Path(__file__).resolve().parent.parent


def run_alpha(cfg, experiment: str, wd: Path, mesh_dir: str) -> np.ndarray:  # -> [frames + 1]
    """α MSE at every frame of a whole run of ``experiment`` (data prepared in ``wd``, reused)."""
    child = multiprocessing.get_context("spawn").Process(target=prepare, args=(cfg, experiment, wd, mesh_dir))
    child.start()
    child.join()
    if child.exitcode != 0:
        raise SystemExit(f"data preparation in {wd} failed (exit code {child.exitcode})")
    exp = cfg.experiment(experiment)
    out = wd / f"{experiment}.h5"
    out.unlink(missing_ok=True)
    shutil.rmtree(partial_dir(out), ignore_errors=True)
    run_morph(wd / f"p_{exp.source}.h5", wd / f"t_{exp.target}.h5", out, morph_config(cfg, experiment),
              name=experiment, log=lambda msg: print(msg, flush=True))
    return np.asarray(read_metrics(out)["alpha_mse"], dtype=float)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mode", choices=["record", "compare"])
    ap.add_argument("csv")
    ap.add_argument("--experiments", nargs="+", default=["iso_bunny_full", "cow_duck_full"])
    ap.add_argument("--rtol", type=float, default=1e-4)
    ap.add_argument("--workdir", default="/tmp/physmorph_identity")
    ap.add_argument("--mesh-dir", default=os.environ.get("PHYSMORPH_MESH_DIR", str(REPO.parent / "shared" / "meshes")))
    args = ap.parse_args()
    cfg = load_settings(REPO / "config/config.yaml", overrides={"threads": 1})
    set_threads(1)  # torch's too, as the morph job sets them (physmorph.stages.morph_stage)
    wd = Path(args.workdir) / cfg.sampling.tag
    wd.mkdir(parents=True, exist_ok=True)
    commit, dirty = git_state(REPO)
    rows = []
    for name in args.experiments:
        alpha = run_alpha(cfg, name, wd, args.mesh_dir)
        rows += [{"experiment": name, "frame": k, "alpha_mse": float(a), "commit": commit, "dirty": dirty}
                 for k, a in enumerate(alpha)]
    now = pd.DataFrame(rows)
    if args.mode == "record":
        now.to_csv(args.csv, index=False, float_format="%.17g")  # exact: a float64 round-trips
        print(f"wrote {len(now)} frames to {args.csv}")
        return
    before = pd.read_csv(args.csv)
    worst_all = 0.0
    for name in args.experiments:
        a = before[before.experiment == name].sort_values("frame")["alpha_mse"].to_numpy()
        b = now[now.experiment == name].sort_values("frame")["alpha_mse"].to_numpy()
        if len(a) != len(b):
            print(f"{name}: {len(b)} frames now, {len(a)} in the record")
            worst_all = np.inf
            continue
        rel = np.abs(b - a) / np.maximum(np.abs(a), 1e-30)
        worst = float(np.nanmax(rel))
        worst_all = max(worst_all, worst)
        print(f"{name}: {len(a)} frames, largest relative difference {worst:.2e} "
              f"(frame {int(np.nanargmax(rel))}), record at {before.commit.iloc[0][:10]}")
    sys.exit(0 if worst_all <= args.rtol else 1)


if __name__ == "__main__":
    main()
