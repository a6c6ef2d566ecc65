"""End-to-end: the Snakemake workflow on config/test.yaml, in a scratch working directory."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import pytest

REPO = Path(__file__).resolve().parent.parent
SNAKEMAKE = Path(sys.executable).with_name("snakemake")


def _workdir(tmp_path: Path) -> Path:
    for name in ("Snakefile", "config", "workflow"):
        (tmp_path / name).symlink_to(REPO / name)
    return tmp_path


def _run(wd: Path, *args: str, check: bool = True) -> subprocess.CompletedProcess:
    cmd = [str(SNAKEMAKE), "--cores", "2", *args]
    return subprocess.run(cmd, cwd=wd, capture_output=True, text=True, check=check, timeout=900,
                          env={**os.environ, "PHYSMORPH_THREADS": "2"})


def test_dry_run_shows_the_dag(tmp_path):
    out = _run(_workdir(tmp_path), "-n", "tables")
    for rule in ("fetch_mesh", "prepare_mesh", "sample_particles", "rasterize_target"):
        assert rule in out.stdout


def test_bad_config_stops_with_the_key(tmp_path):
    wd = _workdir(tmp_path)
    out = _run(wd, "-n", "tables", "--config", "threads=many", check=False)
    assert out.returncode != 0
    assert "threads" in out.stdout + out.stderr


def test_unknown_experiment_is_named(tmp_path):
    out = _run(_workdir(tmp_path), "-n", "results/runs/iso_teapot_full.h5", check=False)
    assert out.returncode != 0
    assert "unknown experiment 'iso_teapot_full'" in out.stdout + out.stderr


def test_tables_on_test_profile(tmp_path, mesh_dir):
    wd = _workdir(tmp_path)
    out = _run(wd, "tables", "--configfile", "config/test.yaml", "--config", f"mesh_dir={mesh_dir}", check=False)
    assert out.returncode == 0, out.stderr[-4000:]
    for shape in ("iso", "bunny"):
        assert (wd / f"results/particles/{shape}_16x2x1.h5").exists()
        assert (wd / f"results/targets/{shape}_16x2x1.h5").exists()
        assert (wd / f"results/previews/targets/{shape}_16x2x1.png").stat().st_size > 1000
    with h5py.File(wd / "results/runs/iso_bunny_full.h5") as f:
        assert f.attrs["status"] == "complete"
        assert len(f["metrics/alpha_mse"]) == 5  # frame 0 + 4 frames
        assert "git_commit" in f.attrs and "peak_rss_mb" in f.attrs
    assert not list(wd.glob("results/**/*.partial"))
