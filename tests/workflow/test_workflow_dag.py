"""The Snakemake workflow's plans, in a scratch working directory: dry runs only (what is planned,
what is refused before any job, and how). The one real run of the test profile is test_workflow.py's."""

import re
import time

import h5py
import pytest

from snakemake_runs import REPO, TEST, planned_jobs, planned_outputs
from snakemake_runs import scratch_workdir as _workdir, snakemake_run as _run


def test_dry_run_names_a_target_of_another_volume_before_any_job(tmp_path, mesh_dir):
    """The morph's volume warning, at DAG time: the isosphere shrunk to 12.4 (its volume from its
    formula) against the bunny (the raw mesh repaired, before any job) holds 134 % of its volume."""
    wd = _workdir(tmp_path)
    out = _run(wd, "-n", "results/default/runs/iso_bunny_full.h5", "--config", f"mesh_dir={mesh_dir}",
               "shapes={iso: {kind: isosphere, size: 12.4}}")
    lines = [line for line in (out.stdout + out.stderr).splitlines() if "of the source's volume" in line]
    assert len(lines) == 1, lines
    assert lines[0].startswith("warning: iso_bunny_full: the target holds 13")
    assert "a target size of 16.3 (now 18) would hold the source's volume" in lines[0]
    plain = _run(wd, "-n", "results/default/runs/iso_bunny_full.h5", "--config", f"mesh_dir={mesh_dir}")
    assert "of the source's volume" not in plain.stdout + plain.stderr


def test_dry_run_shows_the_dag(tmp_path):
    out = _run(_workdir(tmp_path), "-n", "tables")
    for rule in ("fetch_mesh", "prepare_mesh", "sample_particles", "rasterize_target", "morph", "make_tables"):
        assert rule in planned_jobs(out)
    outs = planned_outputs(out)
    assert "results/default/runs/iso_bunny_full.h5" in outs
    assert all(p.startswith(("results/default/", "resources/meshes/")) for p in outs), outs


def test_bad_config_stops_with_the_key(tmp_path):
    wd = _workdir(tmp_path)
    out = _run(wd, "-n", "tables", "--config", "threads=many", check=False)
    assert out.returncode != 0
    assert "config key 'threads': expected an integer, got 'many'" in out.stdout + out.stderr


@pytest.mark.parametrize("override, message", [
    ("mpm={dt: -0.1}", "config key 'mpm.dt'"),
    ("mpm={substeps: 0}", "config key 'mpm.substeps'"),
    ("morph={frames: 0}", "config key 'morph.frames'"),
    ("morph={cameras: 100}", "config key 'morph.cameras': 100 render-loss views, but the target has only 8"),
    ("mpm={optimizer: sgd}", "config key 'mpm.optimizer': 'sgd' is not allowed (allowed: adam, normalized_gd)"),
    ("target={elevation_spread_deg: 80}", "config key 'target.elevation_spread_deg': elevation_spread_deg: the views "
                                          "at 101 degrees (elevation 21 ± 80) are past a pole"),
])
def test_dry_run_refuses_bad_settings_naming_the_key(tmp_path, override, message):
    out = _run(_workdir(tmp_path), "-n", "tables", "--config", override, check=False)
    assert out.returncode != 0
    assert message in out.stdout + out.stderr


def test_grid_too_big_for_the_machine_is_refused_quickly(tmp_path):
    started = time.time()
    out = _run(_workdir(tmp_path), "-n", "tables", "--config", "sampling={grid_res: 512}", check=False)
    assert out.returncode != 0
    text = out.stdout + out.stderr
    assert re.search(r"needs an estimated [\d,]+ MB .*512\^3.*above the limit of [\d,]+ MB \(max_memory_mb", text), text[-2000:]
    assert time.time() - started < 60


def test_numbers_from_the_command_line_and_integers_are_accepted(tmp_path):
    out = _run(_workdir(tmp_path), "-n", "tables", "--config", "mpm={smoothing: 0.5, drag: 0}", "plasticity={eta: 1}")
    assert planned_jobs(out)["morph"] == 18


def test_unknown_experiment_is_named(tmp_path):
    out = _run(_workdir(tmp_path), "-n", "results/default/runs/iso_teapot_full.h5", check=False)
    assert out.returncode != 0
    assert "unknown experiment 'iso_teapot_full'" in out.stdout + out.stderr


def test_paper_main_plans_the_main_tables_six_runs(tmp_path):
    """`snakemake paper_main` makes the main table's six runs (physics-only and full to bunny, cow,
    duck; config/paper_results.yaml) at the profile's scale, and their tables and figures, nothing else."""
    out = _run(_workdir(tmp_path), "-n", "paper_main", "--configfile", "config/paper.yaml")
    jobs = planned_jobs(out)
    assert jobs["morph"] == 6 and jobs["make_main_tables"] == 1 and jobs["make_main_figures"] == 1, jobs
    assert "make_tables" not in jobs and "make_figures" not in jobs, jobs
    runs = {p for p in planned_outputs(out) if "/runs/" in p}
    assert runs == {f"results/paper/runs/iso_{t}_{m}.h5" for t in ("bunny", "cow", "duck")
                    for m in ("physics_only", "full")}
    assert "results/paper/main_tables/main.md" in planned_outputs(out)
    assert "results/paper/main_figures/sequences_main.png" in planned_outputs(out)


def test_morph_asks_for_memory_from_the_sampled_particle_count(tmp_path):
    """Once the particles exist, the morph job's memory and run time follow their recorded count,
    not the DAG-time estimate (which can be 20 % low, e.g. the paper profile's sphere)."""
    from physmorph.records.h5io import stamp_checksum

    wd = _workdir(tmp_path)
    args = ("--profile", str(REPO / "workflow/profiles/slurm"), "-n", "results/test/runs/iso_bunny_full.h5", *TEST)

    def morph_mem() -> int:
        block = _run(wd, *args).stdout.split("rule morph:", 1)[1].split("rule ", 1)[0]
        return int(re.search(r"mem_mb=(\d+)", block)[1])

    estimated = morph_mem()
    particles = wd / "results/test/particles/iso_32x1x1.h5"
    particles.parent.mkdir(parents=True)
    with h5py.File(particles, "w") as f:
        f.attrs["count"] = 1_000_000
        stamp_checksum(f)
    assert estimated < 1500 and morph_mem() > 10_000


def test_slurm_profile_dry_run(tmp_path):
    """The cluster profile plans the paper-scale DAG; memory, runtime and a GPU come from the rules."""
    wd = _workdir(tmp_path)
    out = _run(wd, "--profile", str(REPO / "workflow/profiles/slurm"), "-n", "tables", "--configfile", "config/paper.yaml")
    assert "results/paper/runs/iso_bunny_full.h5" in planned_outputs(out)
    assert "_64x5x2.h5" in out.stdout
    planned = planned_outputs(out)
    assert "results/paper/particles/isob_64x5x2.h5" in planned  # a source only: no target rasterised for it
    assert not any("targets/isob" in p for p in planned) and "results/paper/targets/bunny_64x5x2.h5" in planned
    morph = out.stdout.split("rule morph:", 1)[1].split("rule ", 1)[0]
    assert re.search(r"mem_mb=\d{4,}", morph) and re.search(r"runtime=\d{3,}", morph) and "gpu=1" in morph, morph


