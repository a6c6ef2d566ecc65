"""Running the workflow in a scratch working directory, for the workflow's tests: a folder that
links the checkout's Snakefile, config/ and workflow/, snakemake run there on this checkout's
physmorph, and what a dry run plans (tests/workflow/, the README's commands, the stability map)."""

import io
import os
import re
import subprocess
import sys
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SNAKEMAKE = Path(sys.executable).with_name("snakemake")
TEST = ("--configfile", "config/test.yaml")


def scratch_workdir(tmp_path: Path) -> Path:
    for name in ("Snakefile", "config", "workflow"):
        (tmp_path / name).symlink_to(REPO / name)
    return tmp_path


def snakemake_run(wd: Path, *args: str, check: bool = True) -> subprocess.CompletedProcess:
    """`snakemake ARGS` in ``wd``: a dry run (-n) in this process, a run in a process of its own."""
    cmd = [str(SNAKEMAKE), *([] if "--profile" in args else ["--cores", "2"]), *args]
    if "-n" in args:
        out = plan_here(wd, cmd[1:])
    else:
        # the workflow imports this checkout's physmorph, whatever is installed
        env = {**os.environ, "PHYSMORPH_THREADS": "2", "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
        out = subprocess.run(cmd, cwd=wd, capture_output=True, text=True, timeout=1200, env=env)
    if check and out.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} failed:\n{out.stdout[-3000:]}\n{out.stderr[-5000:]}")
    return out


def plan_here(wd: Path, argv: list[str]) -> subprocess.CompletedProcess:
    """A dry run through Snakemake's own command line (its argument parser, then its API, as the
    `snakemake` command calls them) in this process, with what it prints and its exit status as a
    finished process's: about 0.3 s, where a new interpreter takes ~2.2 s to import Snakemake, its
    plugins and physmorph again (the suite plans ~40 times). A dry run starts no job, so the jobs'
    environment does not matter. Python's warnings go to pytest's record here, not to stderr:
    what the workflow says at DAG time goes through Snakemake's logger, which this captures."""
    from snakemake.cli import args_to_api, parse_args
    from snakemake.exceptions import print_exception

    stdout, stderr, here = io.StringIO(), io.StringIO(), os.getcwd()
    os.chdir(wd)
    try:
        with redirect_stdout(stdout), redirect_stderr(stderr):
            try:
                parser, args = parse_args(argv)
                status = 0 if args_to_api(args, parser) else 1
            except SystemExit as stop:  # the workflow's refusals (status 2) and argparse's
                status = stop.code if isinstance(stop.code, int) else 1
            except Exception as e:  # as `snakemake` itself reports it
                print_exception(e)
                status = 1
    finally:
        os.chdir(here)
    return subprocess.CompletedProcess(["snakemake", *argv], status, stdout.getvalue(), stderr.getvalue())


def planned_jobs(out: subprocess.CompletedProcess) -> dict[str, int]:
    """rule -> job count from a dry run's job stats ({} when nothing is to be done)."""
    text = out.stdout + out.stderr
    if "Nothing to be done" in text:
        return {}
    stats = text.split("Job stats:", 1)[1].split("total", 1)[0]
    return {m[1]: int(m[2]) for m in re.finditer(r"^(\w+)\s+(\d+)\s*$", stats, re.M)}


def planned_outputs(out: subprocess.CompletedProcess) -> list[str]:
    return [p.strip() for line in re.findall(r"^\s*output: (.*)$", out.stdout + out.stderr, re.M) for p in line.split(",")]
