"""Convergence study driver: run one experiment of the default profile with config overrides and
append its reachable-gap numbers to docs/study/runs.csv (the study's raw record).

    python benchmarks/study_convergence.py iso_bunny_full --tag baseline
    python benchmarks/study_convergence.py iso_bunny_full --tag lr003 --set mpm.learning_rate=0.003
    python benchmarks/study_convergence.py iso_bunny_full iso_cow_full --frames 20 --set morph.gamma=0.3

Needs the prepared particles and targets of the profile under results/{profile}/ (e.g.
`snakemake --cores 2 results/default/particles/iso_32x2x1.h5 results/default/targets/bunny_32x2x1.h5`),
or ``--prepare MESH_DIR``: what is missing made there by the workflow's stages from the raw meshes in
MESH_DIR (a machine without Snakemake, such as a lent GPU machine).
Each row: alpha MSE at frame 0 / best / final, the ceiling (the target's own particles at rest),
the share of the reachable gap closed at the best and last frame, silhouette IoU, Chamfer, wall,
and the body in 3D at the last saved frame as the export measures it (stray share, mass outside
the largest body, components, genus against the target's, 95th-percentile surface distance,
roughness) where the target's prepared mesh results/{profile}/meshes/{target}.h5 is there.
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import subprocess
import csv
import json
import sys
import time
from pathlib import Path

import numpy as np

from physmorph.settings.build import dotted_overrides
from physmorph.settings.workflow import load_settings
from physmorph.reports.metrics import sign_changes, swing_percent
from physmorph.morph.loop import morph_config, run_morph
from physmorph.records.runfile import read_metrics
from physmorph.reports.page_meta import run_wall_time_s
from physmorph.morph.quality import gap_closed
from physmorph.records.runfile import partial_dir
from physmorph.reports.export.measures import frame_measures
from physmorph.reports.export.runs import frame_state, saved_frames
from physmorph.reports.export.surface import particle_surface
from physmorph.stages import prepare_experiment_inputs

REPO = Path(__file__).resolve().parent.parent
CSV = REPO / "docs" / "study" / "runs.csv"
COLUMNS = ["tag", "experiment", "frames", "overrides", "a0", "a_best", "best_frame", "a_final", "ceiling",
           "closed_best", "closed_final", "iou0", "iou_best", "iou_final", "ceiling_iou", "chamfer0",
           "chamfer_final", "fp_det_min", "status", "wall_s", "volume_iou0", "volume_iou_final", "overfilled_final",
           "swing_percent", "sign_changes", "drop_points", "volume_change_percent"]
# the body in 3D at the last saved frame (physmorph.reports.export.measures.frame_measures; empty
# where the target's mesh is not prepared, and in rows older than these columns)
BODY_COLUMNS = ["stray_percent", "outside_body_percent", "components", "genus", "target_genus",
                "surface_p95_dx", "rough_percent", "surface_genus"]
COLUMNS += BODY_COLUMNS


def config_files(profile: str | None) -> list[Path]:
    """config/config.yaml and the --profile files merged on it, in order."""
    return [REPO / "config" / "config.yaml"] + [Path(p) for p in (profile or "").split(",") if p]


def body_columns(run_h5: Path, particles_h5: Path, mesh_h5: Path, export) -> dict:
    """BODY_COLUMNS of the run's last saved frame: its surface made as the export makes it
    (``export``: the ExportConfig) and measured against the target's prepared mesh; empty values
    where that mesh is not there."""
    if not Path(mesh_h5).exists():
        return {}
    k = saved_frames(run_h5)[-1]
    s = frame_state(run_h5, k, particles_h5=particles_h5)
    mesh = particle_surface(s["x"], s["volume"], s["det_F"], s["dx"], **export.surface())
    m = frame_measures(k, s, mesh, mesh_h5)
    return {"stray_percent": 100.0 * m["stray_share"], "outside_body_percent": 100.0 * m["outside_largest_body"],
            "components": m["components"], "genus": m["genus"], "target_genus": m["target_genus"],
            "surface_p95_dx": m["surface_p95_dx"], "rough_percent": m["roughness_percent"],
            "surface_genus": m["surface_genus"]}


def prepare_inputs(cfg, name: str, prepared: Path, mesh_dir: Path) -> None:
    """The experiment's prepared meshes, source particles and target under ``prepared`` (the
    workflow's layout: meshes/, particles/, targets/), made by the workflow's stages where missing."""
    res = cfg.sampling.tag
    paths = {"mesh": lambda shape: prepared / "meshes" / f"{shape}.h5",
             "particles": lambda shape: prepared / "particles" / f"{shape}_{res}.h5",
             "target": lambda shape: prepared / "targets" / f"{shape}_{res}.h5"}
    prepare_experiment_inputs(cfg, name, mesh_dir, lambda kind, shape: paths[kind](shape))


def study_row(tag: str, name: str, recorded: dict, run_h5: Path, wall: float, body: dict | None = None) -> dict:
    """One row of runs.csv from a finished run file (its reachable-gap numbers, and ``body``: its
    body_columns), printed as well."""
    m = read_metrics(run_h5)
    # The ceiling stored by the target stage (the target's own particles at rest, its sigma0);
    # rows before 2026-11-22 used the source's sigma0 here (a ~3 % lower gap, see the doc).
    ceil = {"alpha_mse": float(m["attrs"]["ceiling_alpha_mse"]), "iou": float(m["attrs"]["ceiling_iou"])}
    a = m["alpha_mse"]
    k = int(np.nanargmin(a))
    iou = m.get("iou", np.full_like(a, np.nan))
    row = {"tag": tag, "experiment": name, "frames": len(a) - 1, "overrides": json.dumps(recorded, sort_keys=True),
           "a0": a[0], "a_best": a[k], "best_frame": k, "a_final": a[-1], "ceiling": ceil["alpha_mse"],
           "closed_best": gap_closed(a[0], a[k], ceil["alpha_mse"]),
           "closed_final": gap_closed(a[0], a[-1], ceil["alpha_mse"]),
           "iou0": iou[0], "iou_best": np.nanmax(iou), "iou_final": iou[-1], "ceiling_iou": ceil["iou"],
           "chamfer0": m["chamfer"][0], "chamfer_final": m["chamfer"][-1],
           "fp_det_min": np.nanmin(m["fp_det_min"]), "status": m["attrs"].get("status", ""), "wall_s": wall,
           "volume_iou0": m["volume_iou"][0], "volume_iou_final": m["volume_iou"][-1],
           "overfilled_final": m["overfilled_mass"][-1],
           # how still the last frames are (physmorph.reports.metrics)
           "swing_percent": swing_percent(a), "sign_changes": sign_changes(a),
           "drop_points": 100.0 * (gap_closed(a[0], a[k], ceil["alpha_mse"]) - gap_closed(a[0], a[-1], ceil["alpha_mse"])),
           # the body's volume at the last frame against its first (sum V0 det F)
           "volume_change_percent": 100.0 * (m["total_volume"][-1] / m["total_volume"][0] - 1.0),
           **{c: (body or {}).get(c, "") for c in BODY_COLUMNS}}
    row = {k_: (f"{v:.4g}" if isinstance(v, (float, np.floating)) else v) for k_, v in row.items()}
    print(" ".join(f"{k_}={row[k_]}" for k_ in COLUMNS if k_ != "overrides"), flush=True)
    curve = " ".join(f"{v:.4f}" for v in a[:: max(1, len(a) // 20)])
    print(f"  alpha curve: {curve}", flush=True)
    return row


def append_rows(csv_path: Path, rows: list[dict]) -> None:
    """Append ``rows`` to the record, refusing one whose header is not COLUMNS."""
    new = not csv_path.exists()
    if not new:
        with csv_path.open(newline="") as fh:
            header = next(csv.reader(fh), [])
        if header != COLUMNS:
            raise SystemExit(f"{csv_path}: its header {header} is not this driver's columns {COLUMNS}; "
                             "add the missing columns (empty for the older rows) or pass --csv")
    with csv_path.open("a", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS)
        if new:
            w.writeheader()
        w.writerows(rows)


def record_runs(runs_dir: Path, names: list[str], tag: str, recorded: dict, csv_path: Path | None,
                body) -> list[dict]:
    """Rows for finished runs a workflow made (``runs_dir/{name}.h5``), without running them again:
    the wall time is each run's own over all its sittings (its ``wall_time_s``); ``body(name, run)``
    their body_columns."""
    rows = [study_row(tag, name, recorded, runs_dir / f"{name}.h5", run_wall_time_s(runs_dir / f"{name}.h5"),
                      body(name, runs_dir / f"{name}.h5"))
            for name in names]
    if csv_path is not None:
        append_rows(csv_path, rows)
    return rows


def main(argv: list[str] | None = None) -> list[dict]:
    """Run each named experiment once; returns the rows (also printed and, unless --no-csv, appended)."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("experiments", nargs="+")
    ap.add_argument("--tag", required=True)
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--set", action="append", default=[], help="dotted.key=value (YAML value)")
    ap.add_argument("--profile", default=None,
                    help="extra config files merged on config/config.yaml, left to right, comma-separated "
                         "(config/mid.yaml,config/heldout.yaml: the held-out shapes at the mid scale)")
    ap.add_argument("--workdir", default="/tmp/physmorph_study")
    ap.add_argument("--results", default=str(REPO / "results"), help="where results/{profile}/ lives")
    ap.add_argument("--csv", default=str(CSV), help="the record the rows are appended to")
    ap.add_argument("--no-csv", action="store_true")
    ap.add_argument("--no-release", action="store_true", help="no release frames after the run (the experiment's release_frames set to 0)")
    ap.add_argument("--resume", action="store_true",
                    help="continue a killed call's run from its last committed frame instead of starting again")
    ap.add_argument("--prepare", metavar="MESH_DIR", default=None,
                    help="make the missing prepared inputs under --results from the raw meshes in MESH_DIR (in a "
                         "process of its own: the stages start Taichi on the CPU, a run on CUDA could not follow)")
    ap.add_argument("--prepare-only", action="store_true", help="with --prepare: make the inputs, run nothing")
    ap.add_argument("--record", metavar="RUNS_DIR", default=None,
                    help="record the finished runs RUNS_DIR/{experiment}.h5 a workflow made, without running them")
    args = ap.parse_args(argv)
    csv_path = Path(args.csv)
    overrides = dotted_overrides(args.set)
    if args.frames:
        overrides.setdefault("morph", {})["frames"] = args.frames
    # the row names the profile file too, so it says how to rerun it
    recorded = {**({"--profile": args.profile} if args.profile else {}), **overrides}
    files = config_files(args.profile)
    cfg = load_settings(*files, overrides=overrides)
    res = cfg.sampling.tag
    prepared = Path(args.results) / cfg.profile

    def body(name: str, run: Path) -> dict:
        exp = cfg.experiment(name)
        return body_columns(run, prepared / "particles" / f"{exp.source}_{res}.h5",
                            prepared / "meshes" / f"{exp.target}.h5", cfg.export)

    if args.record:
        return record_runs(Path(args.record), args.experiments, args.tag, recorded,
                           None if args.no_csv else csv_path, body)
    if args.prepare and args.prepare_only:
        for name in args.experiments:
            prepare_inputs(cfg, name, prepared, Path(args.prepare))
        return []
    if args.prepare:
        subprocess.run([sys.executable, __file__, *(argv if argv is not None else sys.argv[1:]), "--prepare-only"],
                       check=True)
    rows = []
    for name in args.experiments:
        exp = cfg.experiment(name)
        mc = morph_config(cfg, name)
        mc = dataclasses.replace(mc, progress=False, **({"release_frames": 0} if args.no_release else {}))
        parts = Path(args.results) / cfg.profile / "particles" / f"{exp.source}_{res}.h5"
        tpath = Path(args.results) / cfg.profile / "targets" / f"{exp.target}_{res}.h5"
        out = Path(args.workdir) / args.tag / f"{name}.h5"
        out.parent.mkdir(parents=True, exist_ok=True)
        if not args.resume:
            out.unlink(missing_ok=True)
            shutil.rmtree(partial_dir(out), ignore_errors=True)  # a partial run of an earlier call
        t0 = time.time()
        run_morph(parts, tpath, out, mc, name=name, log=lambda m: print(m, file=sys.stderr, flush=True),
                  target_size=cfg.shape(exp.target).size)
        wall = time.time() - t0
        row = study_row(args.tag, name, recorded, out, wall, body(name, out))
        rows.append(row)
        if not args.no_csv:
            append_rows(csv_path, [row])
    return rows


if __name__ == "__main__":
    main()
