"""The run files' command line (python -m physmorph.records.runfile, physmorph.records.runfile_cli):
usage with --help and without an argument, one line and a non-zero status for a path that is no run
(a mesh, a text file, another HDF5 file, a directory, a missing path) with no advice to delete it,
and a run's summary for a finished and a partial run; the delete remedy only for a damaged run file."""

import json
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from physmorph.records.runfile import RunFileError, RunWriter, describe_run, partial_dir, read_metrics
from physmorph.records.runkey import RunKey
from physmorph.records.runfile_cli import main

REPO = Path(__file__).resolve().parents[2]
KEY = RunKey(json.dumps({"frames": 2}), (("target", "bb" * 32),))

pytestmark = pytest.mark.usefixtures("checkpoint_every_frame")  # conftest


def _run_cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-m", "physmorph.records.runfile", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=120, env=env)


def _commit_frames(out: Path, frames: int, finish: bool) -> Path:
    """A run of ``frames`` frames with alpha MSE 0.06, 0.05, ...: finished into ``out`` or left partial."""
    with RunWriter(out, KEY) as w:
        w.resume(log=lambda m: None)
        w.set_meta({"experiment": "hand", "views": 1})
        for k in range(frames):
            w.commit(k, {"alpha_mse": 0.06 - 0.01 * k}, [0.06 - 0.01 * k], None, [], {"adam_step": k})
        if finish:
            w.finish("complete", {}, {"frames": frames - 1})
    return out if finish else partial_dir(out)


def _mesh(path: Path) -> Path:
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    return path


def _hdf5_without_the_run_layout(path: Path) -> Path:
    with h5py.File(path, "w") as f:
        f["vertices"] = np.zeros((3, 3))
        f.attrs["config"] = "{}"
    return path


def _advice(message: str, tmp_path: Path) -> str:  # the message without the paths (a test's name may hold any word)
    return message.replace(str(tmp_path), "<tmp>").lower()


FOREIGN = {  # name -> how to make it in a directory
    "some_mesh.obj": _mesh,
    "notes.txt": lambda p: (p.write_text("not a run\n"), p)[1],
    "mesh.h5": _hdf5_without_the_run_layout,
    "results": lambda p: (p.mkdir(), p)[1],
    "missing.h5": lambda p: p,
}


def test_help_prints_the_usage_and_what_it_prints(tmp_path):
    res = _run_cli("--help", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert res.stdout.startswith("usage: python -m physmorph.records.runfile") and "RUN" in res.stdout
    assert "one line about each run" in " ".join(res.stdout.split())
    assert not (tmp_path / "--help").exists()


def test_no_argument_prints_the_usage_on_stderr_and_exits_2(tmp_path):
    res = _run_cli(cwd=tmp_path)
    assert res.returncode == 2 and res.stdout == ""
    assert res.stderr.startswith("usage: python -m physmorph.records.runfile"), res.stderr


@pytest.mark.parametrize("name", sorted(FOREIGN))
def test_a_path_that_is_no_run_gets_one_line_naming_it_and_no_advice(tmp_path, capsys, name):
    path = FOREIGN[name](tmp_path / name)
    assert main(describe_run, [str(path)]) == 1
    out, err = capsys.readouterr()
    lines = (out + err).splitlines()
    assert len(lines) == 1 and str(path) in lines[0], lines
    assert ("not a physmorph run file" in lines[0] or "not found" in lines[0]), lines[0]
    assert "delete" not in _advice(lines[0], tmp_path) and "rm " not in lines[0], lines[0]
    assert path.exists() == (name != "missing.h5")  # nothing removed, nothing made


def test_a_mesh_through_the_module_command(tmp_path):
    _mesh(tmp_path / "some_mesh.obj")
    res = _run_cli("some_mesh.obj", cwd=tmp_path)
    lines = (res.stdout + res.stderr).splitlines()
    assert res.returncode != 0 and lines == ["error: some_mesh.obj: not a physmorph run file (not an HDF5 file)"], lines
    assert "delete" not in res.stdout + res.stderr


def test_a_run_and_a_partial_run_still_get_their_summaries(tmp_path):
    finished = _commit_frames(tmp_path / "run.h5", 3, finish=True)
    partial = _commit_frames(tmp_path / "half.h5", 2, finish=False)
    res = _run_cli(finished.name, partial.name, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert len(lines) == 2 and lines[0].startswith("run.h5: complete, 2 frames, alpha MSE 0.06 -> 0.04"), lines
    assert lines[1].startswith("half.h5.partial: a partial run, frames 0..1 committed"), lines
    mesh = _mesh(tmp_path / "some_mesh.obj")  # one path that is no run: the others still described, status 1
    res = _run_cli(finished.name, mesh.name, cwd=tmp_path)
    assert res.returncode == 1 and res.stdout.startswith("run.h5: complete") and "some_mesh.obj" in res.stderr


def test_only_a_damaged_run_file_is_told_to_be_removed(tmp_path):
    """A run file truncated (its attribute names still in its first bytes) is told to be deleted and
    made again; the same bytes cut before them, another HDF5 file or a run's frame file are not."""
    data = _commit_frames(tmp_path / "run.h5", 3, finish=True).read_bytes()
    torn = tmp_path / "torn.h5"
    torn.write_bytes(data[: len(data) // 2])
    with pytest.raises(RunFileError, match=r"torn\.h5: not a readable HDF5 file .*physmorph run file.*delete it"):
        read_metrics(torn)
    stub = tmp_path / "stub.h5"
    stub.write_bytes(data[:64])  # the HDF5 signature and no more
    with pytest.raises(RunFileError, match=r"stub\.h5: an HDF5 file that cannot be opened") as err:
        read_metrics(stub)
    assert "delete" not in _advice(str(err.value), tmp_path)
    with pytest.raises(RunFileError, match=r"mesh\.h5: not a physmorph run file") as err:
        read_metrics(_hdf5_without_the_run_layout(tmp_path / "mesh.h5"))  # what the tables read, too
    assert "delete" not in _advice(str(err.value), tmp_path)
    frame = _commit_frames(tmp_path / "more.h5", 1, finish=False) / "frame_0000.h5"
    with pytest.raises(RunFileError, match=r"frame_0000\.h5: a file of a partial run .*give its directory") as err:
        read_metrics(frame)
    assert "delete" not in _advice(str(err.value), tmp_path)
