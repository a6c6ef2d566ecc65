"""End-to-end: the Snakemake workflow on config/test.yaml, in a scratch working directory."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pytest

REPO = Path(__file__).resolve().parent.parent
SNAKEMAKE = Path(sys.executable).with_name("snakemake")


def _workdir(tmp_path: Path) -> Path:
    for name in ("Snakefile", "config", "workflow"):
        (tmp_path / name).symlink_to(REPO / name)
    return tmp_path


def _run(wd: Path, *args: str, check: bool = True) -> subprocess.CompletedProcess:
    cmd = [str(SNAKEMAKE), *([] if "--profile" in args else ["--cores", "2"]), *args]
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
    out = _run(wd, "tables", "figures", "tradeoff", "--configfile", "config/test.yaml", "--config", f"mesh_dir={mesh_dir}",
               check=False)
    assert out.returncode == 0, out.stderr[-4000:]
    for shape in ("iso", "bunny"):
        assert (wd / f"results/particles/{shape}_32x1x1.h5").exists()
        assert (wd / f"results/targets/{shape}_32x1x1.h5").exists()
        assert (wd / f"results/previews/targets/{shape}_32x1x1.png").stat().st_size > 1000
    with h5py.File(wd / "results/runs/iso_bunny_full.h5") as f:
        assert f.attrs["status"] == "complete"
        assert len(f["metrics/alpha_mse"]) == 13  # frame 0 + 12 frames
        assert "git_commit" in f.attrs and "peak_rss_mb" in f.attrs
    assert not list(wd.glob("results/**/*.partial"))
    # Tables: every table in three formats, well formed, with our numbers beside the paper's.
    main = pd.read_csv(wd / "results/tables/main.csv")
    assert list(main["target"]) == ["bunny", "cow", "duck"]
    bunny = main.set_index("target").loc["bunny"]
    assert bunny["paper_physics_only"] == 0.0799 and np.isfinite(bunny["physics_only"]) and np.isfinite(bunny["ours"])
    assert 0 <= bunny["frame"] <= 12
    timing = pd.read_csv(wd / "results/tables/timing.csv")
    assert set(timing["experiment"]) == {"iso_bunny_physics_only", "iso_bunny_full"}
    assert (timing["frame_s"] > 0).all() and (timing["peak_rss_mb"] > 0).all()
    conv = pd.read_csv(wd / "results/tables/convergence.csv").set_index("experiment")
    assert set(conv.index) == {"iso_bunny_physics_only", "iso_bunny_full"}
    assert (conv["ceiling"] > 0).all() and np.isfinite(conv[["closed_best_%", "closed_final_%"]].to_numpy()).all()
    for name in ("main", "ablation_components", "ablation_drag", "source_invariance", "plasticity", "shapes", "timing",
                 "convergence"):
        md = (wd / f"results/tables/{name}.md").read_text().splitlines()
        assert md[0].startswith("|") and set(md[1]) <= set("|-")
        assert "\\begin{tabular}" in (wd / f"results/tables/{name}.tex").read_text()
    # Speed/accuracy study: base + one point per changed knob value, Pareto front marked.
    trade = pd.read_csv(wd / "results/tradeoff/tradeoff.csv")
    assert set(trade["name"]) == {"base", "cameras-2", "image-32x24"}
    assert trade["pareto"].any() and (trade["time_s"] > 0).all() and np.isfinite(trade["best_alpha_mse"]).all()
    assert (wd / "results/targets/bunny_32x1x1_32x24.h5").exists()
    assert "accuracy per second" in (wd / "results/tradeoff/tradeoff.md").read_text()
    # Figures: real PNGs.
    for png in ("figures/sequences_main", "figures/drag_ablation", "figures/optimization_traces",
                "figures/gradient_coverage", "tradeoff/pareto"):
        data = (wd / f"results/{png}.png").read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000


def test_slurm_profile_dry_run(tmp_path):
    """The cluster profile parses and plans the paper-scale DAG with a GPU per morph job."""
    wd = _workdir(tmp_path)
    out = _run(wd, "--profile", str(REPO / "workflow/profiles/slurm"), "-n", "tables",
               "--configfile", "config/paper.yaml")
    assert "rule morph" in out.stdout or "morph" in out.stdout
    assert "results/runs/iso_bunny_full.h5" in out.stdout
    assert "_64x5x1.h5" in out.stdout
