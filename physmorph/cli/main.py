"""`physmorph morph SOURCE TARGET`: a user's own morph, start to finish, in one command.

Each of SOURCE and TARGET is a mesh file (anything trimesh reads), a point cloud, or the name of a
shape of the config (iso, bunny, cow, duck, A, S, C). The command sizes the shapes (the fit
helper's answer: the target holds the source's volume and fits the grid's particle region and the
target's views), writes the experiment's config file (morphs/{experiment}.yaml, commented), runs
the Snakemake workflow for it through the export, showing each job and the morph's frames, and
ends by printing where the video, the meshes, the splats and the viewer page are. Run again, it
resumes where it stopped; --dry-run plans only. A shape that cannot be used is refused in one
line before any job.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import physmorph
from physmorph.meshes.errors import REFUSED_STATUS, MeshError, refusal_line

# the checkout this physmorph runs from: its Snakefile, config/ and results/
CHECKOUT = Path(physmorph.__file__).resolve().parents[1]


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="physmorph", description="physmorph: physics-based shape morphing.")
    commands = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")
    m = commands.add_parser("morph", help="morph SOURCE into TARGET: a video, meshes, splats and a viewer page",
                            description=__doc__.split("\n\n")[1])
    m.add_argument("source", help="a mesh file, a point cloud, or a shape of the config (e.g. iso)")
    m.add_argument("target", help="a mesh file, a point cloud, or a shape of the config (e.g. bunny)")
    m.add_argument("--profile", default="default",
                   help="the profile: default, or NAME for config/NAME.yaml (fast, mid, paper, ...); default: default")
    m.add_argument("--name", default=None, help="the experiment's name (default: SOURCE_TARGET)")
    m.add_argument("--size", type=float, default=None,
                   help="the target's size (longest extent, domain units) instead of the one that holds the source's "
                        "volume")
    m.add_argument("--frames", type=int, default=None, help="frames of the morph (default: the profile's)")
    m.add_argument("--cores", type=int, default=2, help="cores for the workflow (default: 2)")
    m.add_argument("--mesh-dir", default=None, help="a folder holding the benchmark meshes (instead of downloading them)")
    m.add_argument("--workdir", type=Path, default=CHECKOUT,
                   help="the workflow's folder (its Snakefile, config/, results/; default: this checkout)")
    m.add_argument("--dry-run", "-n", action="store_true", help="plan only: print the jobs a run would do")
    m.epilog = "Arguments after -- go to snakemake as they are, e.g. -- --profile workflow/profiles/slurm."
    return ap


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    cut = argv.index("--") if "--" in argv else len(argv)
    args = _parser().parse_args(argv[:cut])
    args.snakemake_args = argv[cut + 1:]
    from physmorph.cli.morph_command import run_morph_command

    try:
        return run_morph_command(args)
    except MeshError as exc:  # a shape, a size or a name the morph cannot use: one line, before any job
        print(refusal_line(exc), file=sys.stderr)
        return REFUSED_STATUS


if __name__ == "__main__":
    raise SystemExit(main())
