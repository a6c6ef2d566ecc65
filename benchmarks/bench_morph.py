"""Seconds per frame by stage (physics, render, plasticity, mask) of the morph loop.

    python benchmarks/bench_morph.py                     # default profile, iso -> bunny, full
    python benchmarks/bench_morph.py --profile mid --frames 4
    python benchmarks/bench_morph.py --profile paper --frames 4
    python benchmarks/bench_morph.py --workdir /tmp/bench_morph --experiment iso_bunny_full
    python benchmarks/bench_morph.py --profile paper --device cuda   # solver and renderer on a GPU
    python benchmarks/bench_morph.py --profile paper --frames 7 --set morph.injection_calibration_every=5

Prepares the source particles and the target in --workdir (reused on later calls), then runs the
experiment for --frames frames with plasticity active from the first frame (so every stage is
timed, no release frames; the updates that commit the shape to Fp are those of the profile's whole
run, by default its last frame, not the bench's) and prints the mean seconds per stage over the frames after the ones
that compile Taichi kernels, and the peak RSS: frame 1 compiles the solver's and the renderer's
kernels, and with an injection gain to measure (f_inject, full) frame 2 compiles the calibration's
(MPMSolver.backward_pair), so those methods are timed from frame 3. The stages' sum (t_frame) leaves
out each frame's commit (its frame file and the checkpoint, written, checksummed and fsynced), so
the wall time from one frame's progress line to the next is printed as well, and the minor page
faults over that time (pages the process touched that the system had to supply: what a virtual
machine's host took back costs several ms per MB; physmorph.base.memory).
"""

from __future__ import annotations

import argparse
import shutil
import dataclasses
import multiprocessing
import os
import re
import resource
import time
from pathlib import Path

import numpy as np

from physmorph.settings.build import dotted_overrides
from physmorph.settings.workflow import load_settings
from physmorph.morph.loop import morph_config, run_morph
from physmorph.records.runfile import read_metrics
from physmorph.records.runfile import partial_dir
from physmorph.stages import prepare_experiment_inputs

REPO = Path(__file__).resolve().parent.parent


STAGES = ("t_physics", "t_render", "t_plasticity", "t_mask", "t_frame")


def prepare(cfg, experiment: str, wd: Path, mesh_dir: str | Path) -> None:
    """The source particles and the target of ``experiment`` in ``wd`` (kept where already there):
    {shape}.h5, p_{shape}.h5 and t_{shape}.h5."""
    prefix = {"mesh": "", "particles": "p_", "target": "t_"}
    prepare_experiment_inputs(cfg, experiment, mesh_dir, lambda kind, shape: Path(wd) / f"{prefix[kind]}{shape}.h5")


def bench(cfg, experiment: str, workdir: Path, frames: int, mesh_dir: str | Path) -> dict:
    """Prepare the source particles and the target in ``workdir`` (reused when there), run ``frames``
    frames of ``experiment`` (plasticity from the first frame, no release), and return the mean
    seconds per stage over the frames after those that compile kernels (timed_from: 2, or 3 where
    frame 2 runs the first injection calibration), the first frame, the particle count, the mask
    fraction, the peak RSS (MiB), the minor page faults a frame and the data preparation's seconds."""
    exp = cfg.experiment(experiment)
    wd = Path(workdir)
    t_prep = time.time()
    # In a process of its own: the target's ceiling is rendered on the CPU, and Taichi takes one
    # arch per process, so a morph on CUDA could not follow it in this one.
    child = multiprocessing.get_context("spawn").Process(target=prepare, args=(cfg, experiment, wd, mesh_dir))
    child.start()
    child.join()
    if child.exitcode != 0:
        raise SystemExit(f"data preparation in {wd} failed (exit code {child.exitcode}); its error is above")
    prep = time.time() - t_prep
    mc = morph_config(cfg, experiment)
    # the updates that commit the shape to Fp (absorb_start_frame) as in the profile's whole run: counted
    # from its end (the last update by default), none of the frames timed here is one of them
    absorb_from = mc.plasticity.absorb_start_frame
    if absorb_from is not None and absorb_from < 0:
        absorb_from = mc.frames + 1 + absorb_from
    mc = dataclasses.replace(mc, frames=frames, save_every=frames, release_frames=0,
                             plasticity=dataclasses.replace(mc.plasticity, start_frame=1, absorb_start_frame=absorb_from))
    out = wd / "run.h5"
    out.unlink(missing_ok=True)
    shutil.rmtree(partial_dir(out), ignore_errors=True)  # a partial run of an earlier call
    done_at = {}  # frame -> when its progress line came: after its commit (frame file and checkpoint)
    faults_at = {}  # frame -> the process's minor page faults then

    def log(msg: str) -> None:
        print(msg, flush=True)
        hit = re.search(r"\] frame (\d+)/", msg)
        if hit:
            done_at[int(hit.group(1))] = time.perf_counter()
            faults_at[int(hit.group(1))] = resource.getrusage(resource.RUSAGE_SELF).ru_minflt

    run_morph(wd / f"p_{exp.source}.h5", wd / f"t_{exp.target}.h5", out, mc, name=experiment, log=log)
    m = read_metrics(out)
    calibrates = mc.method in ("f_inject", "full") and mc.injection_calibration != "absolute"
    timed_from = min(3 if calibrates else 2, frames)
    sel = slice(timed_from, None)
    row = {key[2:]: float(np.nanmean(m[key][sel])) for key in STAGES}
    # the wall time from one frame's progress line to the next: the frame and its commit
    pairs = [k for k in range(max(timed_from, 2), frames + 1) if k - 1 in done_at and k in done_at]
    row["wall"] = float(np.mean([done_at[k] - done_at[k - 1] for k in pairs])) if pairs else float("nan")
    # pages faulted in by a frame: memory the system had taken back (physmorph.base.memory)
    row["faults"] = float(np.mean([faults_at[k] - faults_at[k - 1] for k in pairs])) if pairs else float("nan")
    row.update(first_frame=float(m["t_frame"][1]), particles=int(m["attrs"]["n_particles"]),
               mask_fraction=float(np.nanmean(m["mask_fraction"][sel])),
               peak_rss_mb=float(m["attrs"]["peak_rss_mb"]), preparation=prep, timed_from=timed_from)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--profile", default="default", choices=["default", "mid", "paper", "test"])
    ap.add_argument("--experiment", default="iso_bunny_full")
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--device", default=None, choices=["cpu", "cuda"], help="the config's `device` (default: the profile's)")
    ap.add_argument("--workdir", default="/tmp/physmorph_bench_morph")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a config value over the profile's, dotted.key=value (YAML value), e.g. "
                         "morph.injection_calibration_every=5; repeatable")
    ap.add_argument("--mesh-dir", default=os.environ.get("PHYSMORPH_MESH_DIR", str(REPO.parent / "shared" / "meshes")))
    args = ap.parse_args()
    files = [REPO / "config/config.yaml"] + ([REPO / f"config/{args.profile}.yaml"] if args.profile != "default" else [])
    overrides = dotted_overrides(args.set)
    if args.device:
        overrides["device"] = args.device
    cfg = load_settings(*files, overrides=overrides or None)
    s = cfg.sampling
    row = bench(cfg, args.experiment, Path(args.workdir) / f"{args.profile}_{s.tag}", args.frames, args.mesh_dir)
    print(f"\nprofile {args.profile} on {cfg.device} ({s.tag}, {cfg.target.width}x{cfg.target.height} x {cfg.target.cameras} views), "
          f"{args.experiment}, {row['particles']} particles, data preparation {row['preparation']:.1f} s")
    print(f"mean of frames {row['timed_from']}-{args.frames}")
    print("| stage | seconds per frame |\n|---|---|")
    for key in STAGES:
        print(f"| {key[2:]} | {row[key[2:]]:.2f} |")
    print(f"| frame and its commit (wall, progress line to progress line) | {row['wall']:.2f} |")
    print(f"| first frame (incl. compilation) | {row['first_frame']:.2f} |")
    print(f"mask fraction {row['mask_fraction']:.2f}, peak RSS {row['peak_rss_mb']:.0f} MiB, "
          f"{row['faults']:,.0f} minor page faults a frame (with its commit)")


if __name__ == "__main__":
    main()
