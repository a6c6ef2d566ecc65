"""The README's commands, as written: each `snakemake` command of its code blocks is planned (a dry
run through Snakemake's own command line in the test's process, in a scratch working directory,
with the README's own `mine.yaml`), and the run-file summary command runs on a run file. The SLURM
command is covered by tests/workflow/test_slurm.py (it needs a cluster); `make` targets wrap these
commands."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from physmorph.records.runfile import RunWriter
from physmorph.records.runkey import RunKey
from snakemake_runs import plan_here

REPO = Path(__file__).resolve().parents[2]
README = REPO / "README.md"


def _blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", README.read_text(), re.S)


def readme_commands() -> list[str]:
    """Every shell command of the README's bash blocks and indented blocks (comments dropped)."""
    lines = [ln for block in _blocks("bash") for ln in block.splitlines()]
    lines += [ln[4:] for ln in README.read_text().splitlines() if ln.startswith("    ") and not ln.startswith("     ")]
    return [ln.split("#", 1)[0].strip() for ln in lines if ln.split("#", 1)[0].strip()]


def _snakemake_commands() -> list[str]:
    inline = re.findall(r"`(snakemake [^`]*--configfile mine\.yaml[^`]*)`", README.read_text().replace("\n", " "))
    return [c for c in readme_commands() + inline if c.startswith("snakemake ") and "--profile" not in c]


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}


def _mesh_here(directory: Path, mesh_dir: Path) -> None:
    """path/to/mesh.obj in ``directory``: the Bunny."""
    (directory / "path" / "to").mkdir(parents=True, exist_ok=True)
    (directory / "path" / "to" / "mesh.obj").symlink_to(mesh_dir / "stanford-bunny.obj")


@pytest.fixture(scope="module")
def mine_yaml(tmp_path_factory, mesh_dir) -> Path:
    """The README's mine.yaml, as its fit command writes it for path/to/mesh.obj (the Bunny here),
    made once (the fit repairs the mesh) in a folder of its own."""
    directory = tmp_path_factory.mktemp("fit")
    command = re.findall(r"`(python -m physmorph\.meshes\.fit [^`]*)`", README.read_text())[0]
    (directory / "config").symlink_to(REPO / "config")
    _mesh_here(directory, mesh_dir)
    res = subprocess.run(command.replace("python", shlex.quote(sys.executable), 1), shell=True, cwd=directory,
                         capture_output=True, text=True, timeout=120, env=_env())
    assert res.returncode == 0, res.stderr
    return directory / "mine.yaml"


def test_the_readme_has_the_commands_it_promises():
    cmds = readme_commands()
    assert {"make tables", "make test"} <= set(cmds)
    assert re.findall(r"`(python -m physmorph\.records\.runfile[^`]*)`", README.read_text())
    assert len(_snakemake_commands()) >= 3, _snakemake_commands()


@pytest.mark.parametrize("command", _snakemake_commands())
def test_readme_snakemake_command_plans_as_written(command, tmp_path, mesh_dir, request):
    for name in ("Snakefile", "config", "workflow"):
        (tmp_path / name).symlink_to(REPO / name)
    if "mine.yaml" in command:  # the README's mine.yaml, its mesh beside it
        (tmp_path / "mine.yaml").write_text(request.getfixturevalue("mine_yaml").read_text())
        _mesh_here(tmp_path, mesh_dir)
    args = shlex.split(command)[1:]
    if "--report" in args:  # a report is written after the jobs have run; plan the jobs
        i = args.index("--report")
        del args[i:i + 2]
    if "-n" not in args:
        args.insert(0, "-n")
    out = plan_here(tmp_path, args)  # the command's own words, through Snakemake's command line
    text = out.stdout + out.stderr
    assert out.returncode == 0, f"{command}\n{text[-4000:]}"
    targets = [a for a in args if not a.startswith("-") and "=" not in a and not a.endswith(".yaml") and a != "2"]
    assert targets and "Job stats:" in text, text[-3000:]
    for t in targets:
        if "/" in t:
            assert f"output: {t}" in text or f" {t}" in text, (t, text[-3000:])


def test_readme_runfile_summary_runs(tmp_path):
    out = tmp_path / "results" / "default" / "runs" / "iso_bunny_full.h5"
    out.parent.mkdir(parents=True)
    with RunWriter(out, RunKey("{}", ())) as w:
        w.resume(log=lambda m: None)
        w.set_meta({"experiment": "iso_bunny_full", "views": 1})
        for k in range(3):
            w.commit(k, {"alpha_mse": 0.06 - 0.01 * k}, [0.06 - 0.01 * k], None, [], {})
        w.finish("complete", {}, {"frames": 2})
    command = re.findall(r"`(python -m physmorph\.records\.runfile[^`]*)`", README.read_text())[0]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    # the README's glob, expanded by the shell as a user's would be
    res = subprocess.run(command.replace("python", shlex.quote(sys.executable), 1), shell=True, cwd=tmp_path,
                         capture_output=True, text=True, timeout=120, env=env)
    assert res.returncode == 0, res.stderr
    assert "iso_bunny_full.h5: complete, 2 frames, alpha MSE 0.06 -> 0.04" in res.stdout, res.stdout


def test_readme_mesh_size_command_runs(mine_yaml):
    """The README's size helper, as written, on a real mesh: it writes mine.yaml, a config file the
    workflow's loader accepts."""
    written = mine_yaml.read_text()  # the command writes the config file it names
    # the bunny is compact: its size for the iso's volume fits, the value config/config.yaml uses
    assert "mesh: {kind: file, path: path/to/mesh.obj, size: 18.0}" in written, written
    from physmorph.settings.workflow import load_settings

    assert load_settings(REPO / "config/config.yaml", mine_yaml).shape("mesh").size == 18.0


def test_readme_morph_command_plans_as_written(tmp_path, mesh_dir):
    """The README's one command for a user's own mesh, as written (path/to/mesh.obj: the Bunny),
    with -n: it plans the morph and its exports and writes nothing."""
    command = next(c for c in readme_commands() if c.startswith("physmorph morph "))
    (tmp_path / "path" / "to").mkdir(parents=True)
    (tmp_path / "path" / "to" / "mesh.obj").symlink_to(mesh_dir / "stanford-bunny.obj")
    wd = tmp_path / "wd"
    wd.mkdir()
    for name in ("Snakefile", "config", "workflow"):
        (wd / name).symlink_to(REPO / name)
    args = [*shlex.split(command)[1:], "-n", "--workdir", str(wd), "--mesh-dir", str(mesh_dir)]
    res = subprocess.run([str(Path(sys.executable).with_name("physmorph")), *args], cwd=tmp_path, capture_output=True,
                         text=True, timeout=300, env=_env())
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    assert "iso_mesh: {source: iso, target: mesh, method: full}" in res.stdout
    for rule in ("morph", "export_video", "export_meshes", "export_splats", "export_viewer_run"):
        assert re.search(rf"^{rule}\s+1$", res.stdout, re.M), res.stdout
    assert not (wd / "morphs").exists()
