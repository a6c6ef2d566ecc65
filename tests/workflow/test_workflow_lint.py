"""The workflow passes `snakemake --lint` with no finding, and its conda environments
(workflow/envs/physmorph.yaml, named by every rule, and physmorph_cuda.yaml where the config says
`device: cuda`) are the ones environment.lock and environment.cuda.lock give."""

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]
SNAKEMAKE = Path(sys.executable).with_name("snakemake")


def _make_env_module():
    spec = importlib.util.spec_from_file_location("make_env", REPO / "workflow" / "envs" / "make_env.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _lint(cwd: Path, *args: str) -> subprocess.CompletedProcess:
    # the workflow imports this checkout's physmorph, whatever is installed (as tests/workflow/test_workflow.py)
    env = {**os.environ, "PHYSMORPH_THREADS": "2",
           "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([str(SNAKEMAKE), "--lint", *args], cwd=cwd, capture_output=True, text=True, timeout=120,
                          env=env)


def test_conda_env_is_generated_from_the_lock():
    make_env = _make_env_module()
    lock = (REPO / "environment.lock").read_text()
    assert make_env.ENV_FILE == REPO / "workflow" / "envs" / "physmorph.yaml"
    assert make_env.ENV_FILE.read_text() == make_env.conda_env_text(lock), \
        "workflow/envs/physmorph.yaml is out of date with environment.lock: run `make conda-env`"
    env = yaml.safe_load(make_env.ENV_FILE.read_text())
    python, pip, pip_lines = env["dependencies"]
    assert python == f"python={make_env.lock_python(lock)}" and pip == "pip"
    assert pip_lines["pip"][1:] == make_env.lock_pins(lock) and "torch==2.13.0+cpu" in pip_lines["pip"]
    cuda_lock = (REPO / "environment.cuda.lock").read_text()
    assert make_env.CUDA_ENV_FILE.read_text() == make_env.conda_env_text(
        cuda_lock, "environment.cuda.lock", index=None, when=" with `device: cuda`"), \
        "workflow/envs/physmorph_cuda.yaml is out of date with environment.cuda.lock: run `make conda-env`"
    python, pip, pip_lines = yaml.safe_load(make_env.CUDA_ENV_FILE.read_text())["dependencies"]
    assert pip_lines["pip"] == make_env.lock_pins(cuda_lock)  # torch's CUDA build from PyPI: no CPU index
    assert "torch===2.13.0" in pip_lines["pip"] and any(p.startswith("nvidia-") for p in pip_lines["pip"])


def test_every_rule_takes_the_environment_of_its_device():
    """Each rule's `conda:` is CONDA_ENV, which common.smk sets to the CUDA environment for
    `device: cuda` and to the CPU one otherwise; each environment has the post-deploy script that
    installs this checkout (the CUDA one's a link to the CPU one's)."""
    rules = sorted((REPO / "workflow" / "rules").glob("*.smk"))
    named = [m for f in rules for m in re.findall(r"^\s+conda:\n\s+(.*)$", f.read_text(), re.M)]
    assert len(named) >= 15 and set(named) == {"CONDA_ENV"}, named
    common = (REPO / "workflow" / "rules" / "common.smk").read_text()
    assert 'CONDA_ENV = "../envs/physmorph_cuda.yaml" if S.device == "cuda" else "../envs/physmorph.yaml"' in common
    envs = REPO / "workflow" / "envs"
    assert (envs / "physmorph_cuda.post-deploy.sh").resolve() == (envs / "physmorph.post-deploy.sh").resolve()


def test_lock_parsing_reads_the_pins_and_the_python_version():
    make_env = _make_env_module()
    lock = "# Exact pins (Python 3.12, pip).\nnumpy==2.4.6\n\n# a comment\ntorch==2.13.0+cpu  # CPU build\n"
    assert make_env.lock_python(lock) == "3.12"
    assert make_env.lock_pins(lock) == ["numpy==2.4.6", "torch==2.13.0+cpu"]
    with pytest.raises(ValueError, match="Python X.Y"):
        make_env.lock_python("numpy==2.4.6\n")


@pytest.mark.parametrize("args", [(), ("--configfile", "config/test.yaml"), ("--config", "device=cuda")],
                         ids=["default", "test", "cuda"])
def test_snakemake_lint_finds_nothing(args):
    out = _lint(REPO, *args)
    text = out.stdout + out.stderr
    assert out.returncode == 0 and "Lints for" not in text, text[-5000:]


def test_lint_check_sees_a_finding(tmp_path):
    """The check above would fail on a finding (a rule naming no conda environment)."""
    (tmp_path / "Snakefile").write_text('rule a:\n    output:\n        "a.txt"\n    log:\n        "a.log"\n'
                                        '    shell:\n        "touch {output} 2> {log}"\n')
    out = _lint(tmp_path)
    assert out.returncode != 0 and "Lints for rule a" in out.stdout + out.stderr
