"""Running the workflow in a scratch working directory, for the workflow's tests: a folder that
links the checkout's Snakefile, config/ and workflow/, snakemake run there on this checkout's
physmorph, and what a dry run plans (test_workflow.py, test_workflow_dag.py)."""

import os
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SNAKEMAKE = Path(sys.executable).with_name("snakemake")
TEST = ("--configfile", "config/test.yaml")


def scratch_workdir(tmp_path: Path) -> Path:
    for name in ("Snakefile", "config", "workflow"):
        (tmp_path / name).symlink_to(REPO / name)
    return tmp_path


def snakemake_run(wd: Path, *args: str, check: bool = True) -> subprocess.CompletedProcess:
    cmd = [str(SNAKEMAKE), *([] if "--profile" in args else ["--cores", "2"]), *args]
    # the workflow imports this checkout's physmorph, whatever is installed
    env = {**os.environ, "PHYSMORPH_THREADS": "2", "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run(cmd, cwd=wd, capture_output=True, text=True, timeout=1200, env=env)
    if check and out.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} failed:\n{out.stdout[-3000:]}\n{out.stderr[-5000:]}")
    return out


def planned_jobs(out: subprocess.CompletedProcess) -> dict[str, int]:
    """rule -> job count from a dry run's job stats ({} when nothing is to be done)."""
    text = out.stdout + out.stderr
    if "Nothing to be done" in text:
        return {}
    stats = text.split("Job stats:", 1)[1].split("total", 1)[0]
    return {m[1]: int(m[2]) for m in re.finditer(r"^(\w+)\s+(\d+)\s*$", stats, re.M)}


def planned_outputs(out: subprocess.CompletedProcess) -> list[str]:
    return [p.strip() for line in re.findall(r"^\s*output: (.*)$", out.stdout + out.stderr, re.M) for p in line.split(",")]
