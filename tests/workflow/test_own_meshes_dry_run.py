"""`snakemake -n` with a user's own meshes (file shapes given by path): a mesh the run would refuse
stops the dry run in that one line, before any job is planned; separate bodies are warned and the
jobs planned (physmorph.meshes.user_shapes, workflow/rules/common.py check_user_shapes)."""

from pathlib import Path

import trimesh
import yaml

from snakemake_runs import scratch_workdir, snakemake_run


def _dry_run(tmp_path: Path, shape: dict):
    wd = tmp_path / "wd"
    wd.mkdir()
    scratch_workdir(wd)
    (wd / "mine.yaml").write_text(yaml.safe_dump({"shapes": {"mine": shape},
                                                  "experiments": {"iso_mine": {"source": "iso", "target": "mine",
                                                                               "method": "full"}}}))
    return snakemake_run(wd, "-n", "results/default/runs/iso_mine.h5", "--configfile", "mine.yaml", check=False)


def test_a_mesh_too_large_for_the_grid_stops_the_dry_run_in_one_line(tmp_path):
    trimesh.creation.capsule(height=30, radius=1).export(tmp_path / "long.obj")
    out = _dry_run(tmp_path, {"kind": "file", "path": str(tmp_path / "long.obj"), "size": 30.0})
    assert out.returncode == 2
    ours = [line for line in (out.stdout + out.stderr).splitlines() if "long.obj" in line]
    assert ours == [f"{tmp_path / 'long.obj'} (shape 'mine'): size 30 does not fit grid 32's particle region "
                    f"[-13, 13]^3: the largest size that fits is 26.0 (python -m physmorph.meshes.fit {tmp_path / 'long.obj'})"]
    assert "Job stats" not in out.stdout + out.stderr and "Traceback" not in out.stdout + out.stderr


def test_separate_bodies_are_warned_and_planned(tmp_path):
    a = trimesh.creation.icosphere(2)
    trimesh.util.concatenate([a, a.copy().apply_translation([3, 0, 0])]).export(tmp_path / "two.obj")
    out = _dry_run(tmp_path, {"kind": "file", "path": str(tmp_path / "two.obj"), "size": 12.0})
    text = out.stdout + out.stderr
    assert out.returncode == 0 and "Job stats" in text
    assert f"warning: {tmp_path / 'two.obj'} (shape 'mine'): 2 separate bodies" in text
