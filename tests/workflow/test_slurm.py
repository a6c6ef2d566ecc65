"""The SLURM profile on a real SLURM cluster: `bash tests/cluster/slurm-up.sh && pytest -m slurm`.

slurm-up.sh brings up a one-node cluster on this machine (munge, MariaDB + slurmdbd, slurmctld,
slurmd). The test profile (config/test.yaml) goes through `--profile workflow/profiles/slurm` to
its tables, which must equal a local run's to 4 digits; a morph cancelled mid-run (scancel) must
resume on the profile's retry from its last committed frame and end equal to the uninterrupted
run; a job no node can hold must stop the run, naming the setting, before anything is submitted.
Skips, saying why, only where no cluster answers (SLURM could not be installed or started).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pytest

from physmorph.records.runfile import read_metrics

pytestmark = pytest.mark.slurm

REPO = Path(__file__).resolve().parents[2]
SNAKEMAKE = Path(sys.executable).with_name("snakemake")
STATE = Path(os.environ.get("PHYSMORPH_SLURM_STATE", "/var/lib/physmorph-slurm"))
ACCOUNT = os.environ.get("PHYSMORPH_SLURM_ACCOUNT", "physmorph")
TEST = ("--configfile", "config/test.yaml")
# poll SLURM every few seconds instead of the executor's 40 s start and 10 s steps: the test
# profile's jobs take seconds
FAST = ("--slurm-init-seconds-before-status-checks", "5", "--seconds-between-status-checks", "3")


def _cmd(*args: str) -> str:
    return subprocess.run(args, capture_output=True, text=True, timeout=60).stdout


@pytest.fixture(scope="module")
def cluster() -> dict:
    why = None
    if shutil.which("sinfo") is None or shutil.which("sbatch") is None:
        why = "the SLURM client tools (sinfo, sbatch) are not installed"
    elif subprocess.run(["scontrol", "ping"], capture_output=True, text=True, timeout=60).returncode != 0:
        why = "slurmctld does not answer (scontrol ping)"
    if why:
        unavailable = STATE / "unavailable"
        if unavailable.exists():
            why += f"; slurm-up.sh said: {unavailable.read_text().strip()}"
        pytest.skip(f"no SLURM cluster here: {why}. Bring one up with `bash tests/cluster/slurm-up.sh` (root, Debian)")
    cpus = max(int(c) for c in _cmd("sinfo", "-h", "-N", "-o", "%c").split())
    return {"cpus": cpus}


def _workdir(path: Path) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    for name in ("Snakefile", "config", "workflow"):
        (path / name).symlink_to(REPO / name)
    return path


def _env() -> dict:
    # the workflow (and every job it submits: sbatch --export=ALL) imports this checkout's physmorph
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}


def _slurm(wd: Path, *args: str) -> list[str]:
    return [str(SNAKEMAKE), "--profile", str(REPO / "workflow/profiles/slurm"), *args, *TEST,
            "--default-resources", f"slurm_account={ACCOUNT}", *FAST]


def _sacct(run_dir: Path) -> list[dict]:
    """This cluster's jobs whose working directory is run_dir: id, comment (rule and wildcards), state, CPUs."""
    rows = []
    out = _cmd("sacct", "-X", "-n", "-P", "-S", "now-1days", "-o", "JobIDRaw,Comment%200,State,AllocCPUS,WorkDir%400")
    for line in out.splitlines():
        jobid, comment, state, cpus, workdir = line.split("|")
        if Path(workdir) == run_dir:
            rows.append({"id": int(jobid), "comment": comment, "state": state.split()[0], "cpus": int(cpus or 0)})
    return sorted(rows, key=lambda r: r["id"])


@pytest.fixture(scope="module")
def runs(cluster, tmp_path_factory, mesh_dir):
    """The test profile through the SLURM profile (threads=8 asked: more than the node has) and,
    at the same time, the same profile run locally."""
    base = tmp_path_factory.mktemp("slurm")
    local, slurm = _workdir(base / "local"), _workdir(base / "slurm")
    config = ("--config", f"mesh_dir={mesh_dir}", "threads=8")
    t0 = time.time()
    p_slurm = subprocess.Popen(_slurm(slurm, "tables", *config), cwd=slurm, env=_env(), text=True,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    p_local = subprocess.run([str(SNAKEMAKE), "--cores", "2", "tables", *TEST, "--config", f"mesh_dir={mesh_dir}"],
                             cwd=local, env={**_env(), "PHYSMORPH_THREADS": "2"}, capture_output=True, text=True, timeout=1500)
    out, _ = p_slurm.communicate(timeout=1500)
    assert p_local.returncode == 0, p_local.stderr[-4000:]
    assert p_slurm.returncode == 0, out[-6000:]
    print(f"SLURM profile run of the test profile: {time.time() - t0:.0f} s")
    return {"local": local, "slurm": slurm, "out": out, "mesh_dir": mesh_dir, "cpus": cluster["cpus"]}


def _same_numbers(a: pd.DataFrame, b: pd.DataFrame, what: str) -> float:
    """Assert equal to 4 digits; return the largest relative difference."""
    assert list(a.columns) == list(b.columns) and a.shape == b.shape, what
    worst = 0.0
    for col in a.columns:
        x, y = a[col], b[col]
        if pd.api.types.is_numeric_dtype(x) and pd.api.types.is_numeric_dtype(y):
            u, v = x.to_numpy(float), y.to_numpy(float)
            # a percentage of a difference (the rebound %: (last - best) / best of alpha MSEs that
            # agree to 1e-5, checked below) magnifies the float32 atomics' round-off of two runs:
            # percentages (a column named "%" or "_points", or a directions row whose measure is
            # one) are compared in their own unit, to 0.01 percentage point
            pct = np.full(len(a), "%" in str(col) or str(col).endswith("_points"))
            if "measure" in a.columns:
                pct |= a["measure"].astype(str).str.contains("%").to_numpy()
            # a distance in grid cells measured on a marching-cubes surface of the particles (the
            # export's surface_dx) moves where an iso-crossing moves: compared in its own unit, to
            # a thousandth of a cell
            cells = np.full(len(a), str(col).endswith("_dx")) & ~pct
            plain = ~pct & ~cells
            # a percentile of those distances (surface_p95_dx) is one sample's distance, so it moves
            # by the gap between neighbouring samples too (0.002 cells measured): to a hundredth
            cells_atol = 1e-2 if str(col).endswith("p95_dx") else 1e-3
            np.testing.assert_allclose(v[plain], u[plain], rtol=1e-4, atol=1e-12, equal_nan=True, err_msg=f"{what}: {col}")
            np.testing.assert_allclose(v[pct], u[pct], rtol=0, atol=1e-2, equal_nan=True, err_msg=f"{what}: {col} (%)")
            np.testing.assert_allclose(v[cells], u[cells], rtol=0, atol=cells_atol, equal_nan=True,
                                       err_msg=f"{what}: {col} (dx)")
            both = np.isfinite(u) & np.isfinite(v) & (u != 0)
            worst = max([worst, *np.abs((v[both] - u[both]) / u[both])])
        else:
            assert x.fillna("").astype(str).tolist() == y.fillna("").astype(str).tolist(), f"{what}: {col}"
    return worst


def test_slurm_profile_runs_every_job_on_the_cluster_to_the_local_tables(runs):
    slurm, local = runs["slurm"] / "results/test", runs["local"] / "results/test"
    jobs = _sacct(runs["slurm"])
    rules = {re.match(r"rule_(\w+?)(_wildcards_|$)", j["comment"]).group(1) for j in jobs}
    # every stage ran as a SLURM job, and every job completed
    assert {"fetch_mesh", "prepare_mesh", "sample_particles", "rasterize_target", "morph", "make_tables"} <= rules, jobs
    assert all(j["state"] == "COMPLETED" for j in jobs), jobs
    # threads=8 asked; each morph got the node's CPUs (capped, not pending for ever)
    morphs = [j for j in jobs if j["comment"].startswith("rule_morph_")]
    assert len(morphs) == 2 and all(j["cpus"] == min(8, runs["cpus"]) for j in morphs), morphs
    # the job logs are kept, one per job, where docs/cluster.md says
    for j in morphs:
        assert list((runs["slurm"] / ".snakemake/slurm_logs/rule_morph").glob(f"*/{j['id']}.log"))
    # the tables equal the local run's to 4 digits (timing.csv holds wall times and memory: not compared)
    tables = sorted(p.name for p in (local / "tables").glob("*.csv") if p.name != "timing.csv")
    assert len(tables) >= 8 and tables == sorted(p.name for p in (slurm / "tables").glob("*.csv") if p.name != "timing.csv")
    worst = max(_same_numbers(pd.read_csv(local / "tables" / name), pd.read_csv(slurm / "tables" / name), name)
                for name in tables)
    print(f"{len(tables)} tables through SLURM vs local: largest relative difference {worst:.1e}")
    for exp in ("iso_bunny_full", "iso_bunny_physics_only"):
        a, b = read_metrics(local / f"runs/{exp}.h5"), read_metrics(slurm / f"runs/{exp}.h5")
        for key in ("alpha_mse", "physics_loss", "chamfer", "total_volume"):
            np.testing.assert_allclose(b[key], a[key], rtol=1e-4, err_msg=f"{exp}: {key}")
        if "release_alpha_mse" in a["attrs"]:  # the release probe the rebound % comes from
            np.testing.assert_allclose(json.loads(str(b["attrs"]["release_alpha_mse"])),
                                       json.loads(str(a["attrs"]["release_alpha_mse"])), rtol=1e-4,
                                       err_msg=f"{exp}: release_alpha_mse")
        # the silhouette IoU thresholds alpha: a pixel at the threshold can flip with the renderer's
        # float32 round-off (seen once: 4e-4, one pixel of the ~300 in one view's union, over 8 views), so it is
        # compared to two pixels' worth
        np.testing.assert_allclose(b["iou"], a["iou"], rtol=0, atol=1e-3, err_msg=f"{exp}: iou")


def _progress(partial: Path) -> tuple[int, int]:
    """The partial run's last committed frame and the frame its checkpoint holds (what a retry
    resumes after; the checkpoint follows the frames at a wall-time cadence)."""
    try:
        attrs = read_metrics(partial)["attrs"]
        return int(attrs["frames_completed"]), int(attrs["resumes_after"])
    except Exception:  # not there yet, or being replaced right now
        return -1, -1


def test_cancelled_morph_resumes_on_the_retry_and_equals_the_uninterrupted_run(runs):
    """On one thread a resumed run is bit-identical to the uninterrupted one (with more threads,
    float32 atomics add in another order and the runs drift apart by round-off over the frames)."""
    wd = runs["slurm"]
    out = wd / "results/test/runs/iso_bunny_full.h5"
    uninterrupted = wd / "uninterrupted_iso_bunny_full.h5"
    one_thread = (*_slurm(wd, str(out.relative_to(wd)), "--config", f"mesh_dir={runs['mesh_dir']}", "threads=8"),
                  "--set-threads", "morph=1")
    out.unlink()
    done = subprocess.run(one_thread, cwd=wd, env=_env(), capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, (done.stdout + done.stderr)[-6000:]
    shutil.move(out, uninterrupted)
    before = {j["id"] for j in _sacct(wd)}
    proc = subprocess.Popen(one_thread, cwd=wd, env=_env(), text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    partial = out.with_name(out.name + ".partial")
    try:
        # wait until the morph job has committed a few of its 12 frames, then cancel it
        deadline, job = time.time() + 600, None
        while time.time() < deadline and _progress(partial)[0] < 3:
            assert proc.poll() is None, proc.stdout.read()[-4000:]
            time.sleep(0.5)
        for line in _cmd("squeue", "-h", "-o", "%i|%k").splitlines():
            jobid, comment = line.split("|", 1)
            if comment == "rule_morph_wildcards_iso_bunny_full" and int(jobid) not in before:
                job = int(jobid)
        assert job is not None, _cmd("squeue")
        seen, checkpoint = _progress(partial)
        assert 3 <= seen < 12 and 0 <= checkpoint <= seen
        subprocess.run(["scancel", str(job)], check=True)
        text, _ = proc.communicate(timeout=900)
    finally:
        if proc.poll() is None:
            proc.terminate()
    assert proc.returncode == 0, text[-6000:]
    # SLURM's record: the cancelled job, then the retry that completed
    jobs = [j for j in _sacct(wd) if j["id"] not in before]
    assert [(j["id"], j["state"]) for j in jobs][:1] == [(job, "CANCELLED")], jobs
    assert len(jobs) == 2 and jobs[1]["state"] == "COMPLETED" and jobs[1]["comment"] == jobs[0]["comment"], jobs
    # the retry resumed from the last checkpoint (at least the one seen before the cancel)
    log = (wd / "results/test/logs/morph/iso_bunny_full.log").read_text()
    resumed = [int(k) for k in re.findall(r"\[iso_bunny_full\] resuming after frame (\d+)/12", log)]
    assert len(resumed) == 1 and checkpoint <= resumed[0] < 12, log[-3000:]
    print(f"SLURM job {job} cancelled with {seen} frames committed, its checkpoint at frame {checkpoint}; retry "
          f"{jobs[1]['id']} resumed after frame {resumed[0]}/12")
    assert not partial.exists()
    a, b = read_metrics(uninterrupted), read_metrics(out)
    assert len(json.loads(b["attrs"]["wall_time_segments_s"])) == 2  # two attempts, one run
    for key in ("alpha_mse", "iou", "physics_loss", "fp_det_max", "total_volume", "chamfer"):
        np.testing.assert_array_equal(b[key], a[key], err_msg=key)
    with h5py.File(uninterrupted) as fa, h5py.File(out) as fb:
        assert sorted(fb["states"]) == sorted(fa["states"])
        for frame in sorted(fa["states"]):
            for k in ("x", "F", "Fp"):
                np.testing.assert_array_equal(fb["states"][frame][k][()], fa["states"][frame][k][()], err_msg=f"{frame}/{k}")


@pytest.mark.parametrize("args, names", [
    (("--set-threads", "morph=64"), ["--set-threads morph=64", "offers"]),
    (("--config", "morph_gpus=1"), ["config key 'morph_gpus'", "no node with a GPU"]),
    (("--set-resources", "morph:mem_mb=99000000"), ["--set-resources morph:mem_mb", "MB"]),
    (("--set-resources", "morph:slurm_partition=nosuch"), ["partition 'nosuch' does not exist"]),
])
def test_a_job_no_node_can_hold_stops_the_run_naming_the_setting(cluster, tmp_path, mesh_dir, args, names):
    wd = _workdir(tmp_path / "wd")
    config = ["--config", f"mesh_dir={mesh_dir}", *(args[1:] if args[0] == "--config" else ())]
    cmd = _slurm(wd, "tables", *config, *(() if args[0] == "--config" else args))
    t0 = time.time()
    out = subprocess.run(cmd, cwd=wd, env=_env(), capture_output=True, text=True, timeout=300)
    text = out.stdout + out.stderr
    assert out.returncode != 0, text[-3000:]
    assert "could never start on this SLURM cluster (nothing was submitted)" in text, text[-3000:]
    for name in names:
        assert name in text, text[-3000:]
    assert _sacct(wd) == [] and not (wd / "results").exists()  # nothing submitted, nothing written
    assert time.time() - t0 < 120
