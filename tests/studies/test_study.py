"""The convergence-study driver (benchmarks/study_convergence.py): an override reaches the run, and
the row it records is the run's own numbers."""

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from physmorph.settings.build import dotted_overrides
from physmorph.settings.workflow import load_settings
from physmorph.morph.quality import gap_closed
from physmorph.records.runfile import read_metrics

from benchmark_scripts import load_benchmark

REPO = Path(__file__).resolve().parents[2]


study = load_benchmark("study_convergence")


def test_set_items_become_a_nested_override_with_yaml_values():
    """The scripts' --set items (study_convergence.py, bench_morph.py)."""
    got = dotted_overrides(["mpm.learning_rate=0.003", "plasticity.continuous_stress=true", "morph.frames=7",
                           "experiments.x={source: iso, target: cow}"])
    assert got == {"mpm": {"learning_rate": 0.003}, "plasticity": {"continuous_stress": True}, "morph": {"frames": 7},
                   "experiments": {"x": {"source": "iso", "target": "cow"}}}


def test_profile_lists_several_files_merged_in_order():
    files = study.config_files("config/mid.yaml,config/heldout.yaml")
    assert [f.name for f in files] == ["config.yaml", "mid.yaml", "heldout.yaml"]
    cfg = load_settings(*[REPO / f for f in files])  # an absolute path stays itself
    assert cfg.profile == "heldout" and cfg.sampling.grid_res == 64  # heldout's name, mid's grid
    assert "iso_torus_full" in cfg.experiments
    assert study.config_files(None) == [REPO / "config" / "config.yaml"]


@pytest.fixture(scope="module")
def test_profile_results(tmp_path_factory, tiny):
    """The session's tiny iso particles and bunny target (conftest), laid out as results/{profile}/ is."""
    cfg, made = tiny
    root = tmp_path_factory.mktemp("results")
    tag = cfg.sampling.tag
    for folder, name, path in (("particles", f"iso_{tag}.h5", made / "p_iso.h5"),
                               ("targets", f"bunny_{tag}.h5", made / "t_bunny.h5"),
                               ("meshes", "bunny.h5", made / "bunny.h5")):
        (root / cfg.profile / folder).mkdir(parents=True)
        (root / cfg.profile / folder / name).symlink_to(path)
    return root


def test_study_run_applies_its_overrides_and_records_the_runs_numbers(test_profile_results, tmp_path):
    record = tmp_path / "runs.csv"
    common = ["--profile", str(REPO / "config" / "test.yaml"), "--results", str(test_profile_results),
              "--workdir", str(tmp_path / "runs"), "--csv", str(record)]
    rows = study.main(["iso_bunny_full", "--tag", "t1", "--frames", "2", "--set", "mpm.learning_rate=0.003",
                       "--set", "plasticity.start_frame=1", *common])
    study.main(["iso_bunny_physics_only", "--tag", "t2", "--frames", "3", *common])

    run = tmp_path / "runs" / "t1" / "iso_bunny_full.h5"
    m = read_metrics(run)
    resolved = json.loads(m["attrs"]["config"])["resolved"]
    # The overrides reached the run (a driver that dropped them would still run, at the defaults).
    assert resolved["mpm"]["learning_rate"] == 0.003
    assert resolved["plasticity"]["start_frame"] == 1
    assert resolved["frames"] == 2 and len(m["alpha_mse"]) == 3
    assert m["fp_det_max"][-1] > 1.0  # plasticity acted from frame 1

    with record.open() as fh:
        written = list(csv.DictReader(fh))
    assert [r["tag"] for r in written] == ["t1", "t2"]  # one header, rows appended
    row = written[0]
    assert row == {k: str(v) for k, v in rows[0].items()}
    assert json.loads(row["overrides"])["mpm"] == {"learning_rate": 0.003}
    assert json.loads(row["overrides"])["--profile"].endswith("test.yaml")
    a, ceiling = m["alpha_mse"], float(m["attrs"]["ceiling_alpha_mse"])
    k = int(np.argmin(a))
    assert int(row["frames"]) == 2 and int(row["best_frame"]) == k
    assert float(row["a_final"]) == pytest.approx(a[-1], rel=1e-3)
    assert float(row["closed_best"]) == pytest.approx(gap_closed(a[0], a[k], ceiling), rel=1e-3, abs=1e-4)
    assert float(row["closed_final"]) == pytest.approx(gap_closed(a[0], a[-1], ceiling), rel=1e-3, abs=1e-4)
    assert int(written[1]["frames"]) == 3 and written[1]["experiment"] == "iso_bunny_physics_only"
    assert float(row["volume_iou_final"]) == pytest.approx(m["volume_iou"][-1], rel=1e-3)
    assert float(row["overfilled_final"]) == pytest.approx(m["overfilled_mass"][-1], rel=1e-3, abs=1e-4)
    # the body in 3D at the last saved frame, against the prepared bunny (genus 0)
    assert row["target_genus"] == "0" and int(row["components"]) >= 1 and int(row["genus"]) >= 0
    assert 0.0 <= float(row["stray_percent"]) <= 100.0 and 0.0 <= float(row["outside_body_percent"]) <= 100.0
    assert float(row["surface_p95_dx"]) > 0.0
    # --record: the same numbers from the finished run file, not run again; its wall time is the run's own
    recorded = study.main(["iso_bunny_full", "--tag", "r1", "--record", str(run.parent), "--csv", str(record),
                           "--profile", "config/test.yaml", "--results", str(test_profile_results)])
    with record.open() as fh:
        assert [r["tag"] for r in csv.DictReader(fh)] == ["t1", "t2", "r1"]
    same = {k: v for k, v in row.items() if k not in ("tag", "overrides", "wall_s")}
    assert {k: str(v) for k, v in recorded[0].items() if k in same} == same
    assert float(recorded[0]["wall_s"]) == pytest.approx(float(m["attrs"]["wall_time_s"]), rel=1e-3)
    assert json.loads(recorded[0]["overrides"]) == {"--profile": "config/test.yaml"}
    # The 3D checks recomputed from the saved states (the study tool for older run files)
    # equals the one the run recorded at those frames (states are stored as float32).
    import h5py
    from physmorph.morph.targets import load_target
    tag = load_settings(REPO / "config" / "config.yaml", REPO / "config" / "test.yaml").sampling.tag
    res = test_profile_results / "test"
    with h5py.File(res / "particles" / f"iso_{tag}.h5", "r") as f:
        mass = f["mass"][()]
    saved = load_benchmark("study_volume_iou").saved_volume_metrics(str(run), mass, load_target(res / "targets" / f"bunny_{tag}.h5"))
    assert sorted(saved) == [0, 2]
    for k, v in saved.items():
        assert v["volume_iou"] == pytest.approx(m["volume_iou"][k], abs=0.01)
        assert v["overfilled_mass"] == pytest.approx(m["overfilled_mass"][k], abs=0.01)


def test_benchmarks_prepare_an_experiments_inputs_as_the_workflow_does(tmp_path):
    """physmorph.stages.prepare_experiment_inputs (bench_morph.py's and study_convergence.py's inputs):
    each file where the layout puts it, the source sampled with its shape's own seed (the workflow's
    sample_particles rule), and nothing made again on a second call."""
    from physmorph.meshes.particles import load_particles
    from physmorph.stages import prepare_experiment_inputs, sample_particles_stage

    cfg = load_settings(REPO / "config" / "config.yaml", REPO / "config" / "test.yaml", overrides={
        "shapes": {"isob": {"kind": "isosphere", "size": 13.7, "seed": 1}},
        "experiments": {"isob_iso": {"source": "isob", "target": "iso", "method": "full"}}})
    paths = []

    def path_of(kind, shape):
        paths.append((kind, shape))
        return tmp_path / kind / f"{shape}.h5"

    prepare_experiment_inputs(cfg, "isob_iso", tmp_path / "no-raw-meshes", path_of)
    made = {p: p.stat().st_mtime_ns for p in tmp_path.rglob("*.h5")}
    assert sorted(p.relative_to(tmp_path).as_posix() for p in made) == [
        "mesh/iso.h5", "mesh/isob.h5", "particles/isob.h5", "target/iso.h5"]
    assert (tmp_path / "particles" / "isob.png").exists() and (tmp_path / "target" / "iso.png").exists()
    x = load_particles(tmp_path / "particles" / "isob.h5").x
    for seed in (0, 1):
        sample_particles_stage(tmp_path / "mesh" / "isob.h5", tmp_path / f"s{seed}.h5", tmp_path / f"s{seed}.png",
                               cfg.sampling, seed)
    assert np.array_equal(x, load_particles(tmp_path / "s1.h5").x)
    assert not np.array_equal(x, load_particles(tmp_path / "s0.h5").x)
    prepare_experiment_inputs(cfg, "isob_iso", tmp_path / "no-raw-meshes", path_of)
    assert {p: p.stat().st_mtime_ns for p in made} == made
