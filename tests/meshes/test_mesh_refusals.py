"""A mesh that cannot be used is refused in one line naming the file and the reason, never a
traceback: by the fit helper (python -m physmorph.meshes.fit, exit status 2) and by the
prepare_mesh job (the line ends its log; the job exits 2)."""

import os
import runpy
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from physmorph.meshes.errors import MeshError
from physmorph.meshes.fit import advise_size_for_file, main

REPO = Path(__file__).resolve().parents[2]
CONFIG = REPO / "config" / "config.yaml"


def _bad_mesh(directory: Path, case: str) -> Path:
    """A mesh file of each refused kind (``missing`` is not written)."""
    path = directory / f"{case}.obj"
    box = trimesh.creation.box()
    if case == "garbage":
        path.write_bytes(b"\x00\xff garbage \x13\x37" * 50)
    elif case == "empty":
        path.write_text("# only vertices\nv 0 0 0\nv 1 0 0\nv 0 1 0\n")
    elif case == "flat":
        trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]], process=False).export(path)
    elif case == "zerovolume":  # a closed box and the same box inside out: the two enclose nothing
        n = len(box.vertices)
        trimesh.Trimesh(np.vstack([box.vertices, box.vertices]), np.vstack([box.faces, box.faces[:, ::-1] + n]),
                        process=False).export(path)
    elif case == "huge":  # its volume (~1e600) overflows double precision
        trimesh.Trimesh(box.vertices * 1e200, box.faces, process=False).export(path)
    return path


REFUSALS = [
    ("missing", "mesh file not found"),
    ("garbage", "cannot be read as a mesh"),
    ("empty", "no faces and only 3 points (a point cloud needs at least 100)"),
    ("flat", "mesh is flat"),
    ("zerovolume", "the raw mesh encloses no volume"),
    ("huge", "too large"),
]


def _one_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


@pytest.mark.parametrize("case, reason", REFUSALS, ids=[c for c, _ in REFUSALS])
def test_fit_refuses_a_mesh_in_one_line(tmp_path, capfd, case, reason):
    path = _bad_mesh(tmp_path, case)
    with pytest.raises(SystemExit) as exit_:
        main([str(path), "--configfile", str(CONFIG)])
    assert exit_.value.code == 2
    out, err = capfd.readouterr()  # file descriptors: C++ output (MeshFix's) would show here too
    line = _one_line(err)
    assert line.startswith(str(path)) and reason in line, line
    assert out == ""


def test_fit_refusal_from_the_command_line(tmp_path):
    """As a user runs it: status 2, one line on stderr, nothing on stdout."""
    path = _bad_mesh(tmp_path, "garbage")
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    run = subprocess.run([sys.executable, "-m", "physmorph.meshes.fit", path.name, "--configfile", str(CONFIG)],
                         cwd=tmp_path, capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 2, run.stderr
    assert _one_line(run.stderr) == "garbage.obj: cannot be read as a mesh (no vertices or faces in its 650 bytes)"
    assert run.stdout == ""


def test_a_refusal_after_meshfix_is_still_one_line(tmp_path, capfd, monkeypatch):
    """MeshFix prints from C++ to the process's stderr ("MeshFix could not fix everything"); a
    refusal after it must still be the only line there."""
    import physmorph.meshes.repair as repair

    sphere = trimesh.creation.icosphere(subdivisions=2)
    shells = trimesh.util.concatenate([trimesh.Trimesh(sphere.vertices + c, sphere.faces[5:], process=False)
                                       for c in ([0, 0, 0], [0.8, 0.3, 0.1])])
    path = tmp_path / "shells.obj"
    shells.export(path)
    box = trimesh.creation.box()
    monkeypatch.setattr(repair, "remesh_winding_number", lambda mesh: trimesh.Trimesh(box.vertices, box.faces[1:]))
    with pytest.raises(SystemExit) as exit_:
        main([str(path), "--configfile", str(CONFIG)])
    assert exit_.value.code == 2
    line = _one_line(capfd.readouterr().err)
    assert line.startswith(f"{path}: irreparable, not watertight: 3 open edges after ") and "pymeshfix" in line


def test_a_mesh_that_cannot_be_sized_for_the_grid_is_too_large(tmp_path):
    """In a 0.1-unit domain the particles' region is under one SIZE_STEP: no size can be printed
    (it printed 0.0). A valid config always leaves room, so this is the library's check."""
    path = tmp_path / "cube.obj"
    trimesh.creation.box().export(path)
    with pytest.raises(MeshError, match=rf"^{path}: too large for grid 32 in \[-0.05, 0.05\]\^3"):
        advise_size_for_file(path, volume=1170.0, grid_res=32, domain=(-0.05, 0.05))


def test_an_open_self_intersecting_shell_gets_a_size(tmp_path, capsys):
    """Two open spheres through each other: the remesh repairs them and fit prints a size."""
    sphere = trimesh.creation.icosphere(subdivisions=2)
    shells = trimesh.util.concatenate([trimesh.Trimesh(sphere.vertices + c, sphere.faces[5:], process=False)
                                       for c in ([0, 0, 0], [0.8, 0.3, 0.1])])
    path = tmp_path / "shells.obj"
    shells.export(path)
    assert main([str(path), "--configfile", str(CONFIG)]) == 0
    out = capsys.readouterr().out
    assert "winding-number remesh (marching cubes)" in out
    size = float(out.split("size for the source's volume")[1].split(":")[1].split()[0])
    assert size > 0


# ------------------------------------------------------------------------------ prepare_mesh job

def _run_job_script(tmp_path, raw: Path, shape: str = "bad"):
    """workflow/scripts/prepare_mesh.py as Snakemake runs it, with the ``snakemake`` object it reads."""
    from physmorph.settings.sections import ShapeSettings
    from physmorph.settings.params import params_json

    log = tmp_path / "logs" / "prepare_mesh" / f"{shape}.log"
    out = tmp_path / "meshes" / f"{shape}.h5"
    snakemake = SimpleNamespace(
        wildcards=SimpleNamespace(shape=shape), input=[str(raw)], output=[str(out)], log=[str(log)],
        params=SimpleNamespace(spec=params_json(ShapeSettings(kind="file", path=str(raw), size=10.0)),
                               domain=[-16.0, 16.0], raw_sha256=None))
    runpy.run_path(str(REPO / "workflow" / "scripts" / "prepare_mesh.py"), init_globals={"snakemake": snakemake},
                   run_name="__main__")
    return log, out


JOB_REFUSALS = [r for r in REFUSALS if r[0] in ("missing", "garbage", "flat", "zerovolume")]


@pytest.mark.parametrize("case, reason", JOB_REFUSALS, ids=[c for c, _ in JOB_REFUSALS])
def test_a_refused_mesh_ends_the_prepare_job_log_in_one_line(tmp_path, capfd, case, reason):
    raw = _bad_mesh(tmp_path, case)
    (tmp_path / "logs" / "prepare_mesh").mkdir(parents=True)
    (tmp_path / "logs" / "prepare_mesh" / "bad.log").write_text("an earlier run's line\n")  # the log is appended to
    with pytest.raises(SystemExit) as exit_:
        _run_job_script(tmp_path, raw)
    assert exit_.value.code == 2
    log = (tmp_path / "logs" / "prepare_mesh" / "bad.log").read_text()
    last = log.splitlines()[-1]
    assert last.startswith(str(raw)) and reason in last, log
    assert "Traceback" not in log
    assert _one_line(capfd.readouterr().err) == last  # what Snakemake shows of the failed job
    assert not (tmp_path / "meshes" / "bad.h5").exists()


def test_the_prepare_job_still_prepares_a_good_mesh(tmp_path):
    raw = tmp_path / "cube.obj"
    trimesh.creation.box().export(raw)
    log, out = _run_job_script(tmp_path, raw, shape="cube")
    from physmorph.meshes.prepare import load_mesh

    assert load_mesh(out).is_watertight
    assert "Traceback" not in (log.read_text() if log.exists() else "")

