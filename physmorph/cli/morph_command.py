"""What `physmorph morph` does: the settings of the profile, the morph's own config file, the
workflow run for its exports, and the four paths at the end (physmorph.cli.main parses the command
line)."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

from physmorph.cli.follow import WorkflowCall, follow
from physmorph.cli.own_shapes import OwnMorph, plan_own_morph
from physmorph.meshes.errors import REFUSED_STATUS, MeshError, refusal_line
from physmorph.meshes.fit import raw_mesh_on_disk, target_cameras
from physmorph.settings.errors import ConfigError
from physmorph.settings.workflow import load_settings

BASE_CONFIG = "config/config.yaml"
OWN_CONFIG_DIR = "morphs"


def _profile_files(workdir: Path, profile: str) -> list[str]:
    if profile == "default":
        return []
    path = f"config/{profile}.yaml"
    if not (workdir / path).is_file():
        known = sorted(p.stem for p in (workdir / "config").glob("*.yaml") if p.stem != "config")
        raise MeshError(f"--profile {profile}: no {path} in {workdir} (profiles: default, {', '.join(known)})")
    return [path]


def _own_config_path(workdir: Path, plan: OwnMorph, fixed_name: bool) -> Path:
    """morphs/{experiment}.yaml; another morph's file of that name is kept (the name takes a number)
    unless the name was asked for, when the file is rewritten (its run restarts if it changed)."""
    folder = workdir / OWN_CONFIG_DIR
    text = plan.config_text()
    base = plan.experiment
    for i in range(1, 100):
        if i > 1:
            plan.experiment = f"{base}{i}"
            text = plan.config_text()
        path = folder / f"{plan.experiment}.yaml"
        if fixed_name or not path.exists() or path.read_text() == text:
            return path
    raise MeshError(f"{folder}: 99 morphs named {base}...: give one --name")


def _outputs(root: str, name: str) -> dict[str, str]:
    return {"video": f"{root}/videos/{name}.mp4", "meshes": f"{root}/meshes/{name}",
            "splats": f"{root}/splats/{name}", "viewer page": f"{root}/viewer/{name}.html"}


def run_morph_command(args: argparse.Namespace) -> int:
    """The command's work; a refusal raises MeshError (or prints a config error) before any job."""
    workdir = args.workdir.resolve()
    if not (workdir / "Snakefile").is_file():
        raise MeshError(f"--workdir {workdir}: no Snakefile there (the physmorph checkout's root has one)")
    files = [BASE_CONFIG, *_profile_files(workdir, args.profile)]
    config = (f"mesh_dir={Path(args.mesh_dir).resolve()}",) if args.mesh_dir else ()
    overrides = {"mesh_dir": str(Path(args.mesh_dir).resolve())} if args.mesh_dir else None
    try:
        settings = load_settings(*(workdir / f for f in files), overrides=overrides)
        plan = plan_own_morph(args.source, args.target, settings, target_cameras(settings),
                              lambda shape: raw_mesh_on_disk(settings, shape, workdir), name=args.name,
                              size=args.size, frames=args.frames)
        own = _own_config_path(workdir, plan, fixed_name=args.name is not None)
        # the merged config, checked as the workflow will check it, before the file is written
        load_settings(*(workdir / f for f in files), overrides={**(overrides or {}), **plan.mapping()})
        if not args.dry_run:
            own.parent.mkdir(parents=True, exist_ok=True)
            own.write_text(plan.config_text())
    except ConfigError as exc:
        print(refusal_line(exc), file=sys.stderr)
        return REFUSED_STATUS
    print(plan.config_text(), end="")
    root = f"results/{settings.profile}"
    outputs = _outputs(root, plan.experiment)
    call = WorkflowCall(workdir, list(outputs.values()), [*files[1:], str(own)], args.cores, config,
                        tuple(args.snakemake_args))
    if args.dry_run:
        return _dry_run(call, own, plan)
    print(f"config: {own}\nrunning the workflow in {workdir} ({settings.profile} profile)", flush=True)
    status = follow(call, workdir / root / "logs" / "physmorph" / f"{plan.experiment}.snakemake.log",
                    workdir / root / "logs" / "morph" / f"{plan.experiment}.log")
    if status != 0:
        return status
    for what, path in outputs.items():
        print(f"{what}: {workdir / path}")
    return 0


def _dry_run(call: WorkflowCall, own: Path, plan: OwnMorph) -> int:
    """Plan with the config the run would write (kept apart, so nothing is written)."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        planned = Path(tmp) / own.name
        planned.write_text(plan.config_text())
        call.configfiles[-1] = str(planned)
        out = subprocess.run(call.command(dry_run=True), cwd=call.workdir, capture_output=True, text=True, check=False)
    text = out.stdout + out.stderr
    # the job counts (Snakemake prints them first and last), or what it said instead
    stats = text.rsplit("Job stats:", 1)[1].strip().split("\n\n", 1)[0] if "Job stats:" in text else text[-3000:]
    print(f"config (not written: a dry run): {own}\n{stats.rstrip()}")
    return out.returncode
