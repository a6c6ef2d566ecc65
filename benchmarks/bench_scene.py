"""Per-stage cost against what the scene holds: the same morph with the material filling 1-50 % of the domain.

    python benchmarks/bench_scene.py                          # default profile, 4 frames per run
    python benchmarks/bench_scene.py --profile mid --shares 0.04 0.1 --frames 3
    python benchmarks/bench_scene.py --scene box --shares 0.1 0.5

--scene sphere: the source is the iso-sphere scaled so its volume is the given share of the domain
cube, the target a cube of the same volume; a sphere holds at most ~28 % of the domain inside the
particle region (BOUNDARY_CELLS cells from each face). --scene box: the source is a box (a, a, b),
the target the box (a, b, a) of the same volume, with a the particle region's width (less one cell)
for shares that need it, so the material can fill about half the domain. The meshes are written to
--workdir; the profile's grid and particles per cell make the particle density the same in every row. Each share runs physics-only and with the full
method (benchmarks/bench_morph.py's measurement: mean seconds per stage over the frames after the
first, plasticity from the first frame). Prints a markdown table; docs/performance.md quotes it.
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

import trimesh

from bench_morph import REPO, bench
from physmorph.settings.workflow import load_settings
from physmorph.base.grid import BOUNDARY_CELLS

DOMAIN_SHARES = (0.01, 0.04, 0.10, 0.25)


def scene_settings(files: list[Path], share: float, workdir: Path, scene: str = "sphere"):
    """The profile's settings with a source and a target each holding ``share`` of the domain's
    volume (their meshes written to ``workdir``): the iso-sphere to a cube, or a box (a, a, b) to the
    box (a, b, a)."""
    base = load_settings(*files)
    width = base.domain[1] - base.domain[0]
    volume = share * width ** 3
    side = volume ** (1.0 / 3.0)
    if scene == "sphere":
        radius = (3.0 * volume / (4.0 * math.pi)) ** (1.0 / 3.0)
        trimesh.creation.box(extents=(side, side, side)).export(workdir / "cube.obj")
        shapes = {"src": {"kind": "isosphere", "size": 2.0 * radius},
                  "dst": {"kind": "file", "path": str(workdir / "cube.obj"), "size": side}}
    elif scene == "box":
        res = base.sampling.grid_res
        dx = width / res
        a = min(1.15 * side, (res - 2 * BOUNDARY_CELLS - 1) * dx)  # the region's width, less a cell
        b = volume / (a * a)
        if b > a:
            raise ValueError(f"share {share:g} does not fit the particle region as a box")
        trimesh.creation.box(extents=(a, a, b)).export(workdir / "box_src.obj")
        trimesh.creation.box(extents=(a, b, a)).export(workdir / "box_dst.obj")
        shapes = {"src": {"kind": "file", "path": str(workdir / "box_src.obj"), "size": a},
                  "dst": {"kind": "file", "path": str(workdir / "box_dst.obj"), "size": a}}
    else:
        raise ValueError(f"scene must be sphere or box, got {scene!r}")
    overrides = {"shapes": shapes,
                 "experiments": {f"src_dst_{m}": {"source": "src", "target": "dst", "method": m}
                                 for m in ("physics_only", "full")}}
    return load_settings(*files, overrides=overrides)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--profile", default="default", choices=["default", "mid", "paper", "test"])
    ap.add_argument("--shares", type=float, nargs="+", default=list(DOMAIN_SHARES),
                    help="volume of the shape over the domain's")
    ap.add_argument("--scene", default="sphere", choices=["sphere", "box"])
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--workdir", default="/tmp/physmorph_bench_scene")
    ap.add_argument("--mesh-dir", default=os.environ.get("PHYSMORPH_MESH_DIR", str(REPO.parent / "shared" / "meshes")))
    args = ap.parse_args()
    files = [REPO / "config/config.yaml"] + ([REPO / f"config/{args.profile}.yaml"] if args.profile != "default" else [])
    rows = []
    for share in args.shares:
        wd = Path(args.workdir) / f"{args.profile}_{args.scene}_share{share:g}"
        wd.mkdir(parents=True, exist_ok=True)
        cfg = scene_settings(files, share, wd, args.scene)
        for method in ("physics_only", "full"):
            r = bench(cfg, f"src_dst_{method}", wd, args.frames, args.mesh_dir)
            rows.append({"share": share, "method": method, **r})
            print(f"share {share:g} {method}: {r}", flush=True)
    print(f"\nscene {args.scene}, profile {args.profile} (grid {cfg.sampling.grid_res}, PPC {cfg.sampling.ppc_surface}/"
          f"{cfg.sampling.ppc_interior}), {args.frames} frames, mean of frames 2-{args.frames} (full: 3-{args.frames}, after the "
          "calibration's compilation); seconds per frame")
    print("| share of the domain | method | particles | physics | render | plasticity | mask | frame | "
          "frame per 1K particles | peak RSS |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {100 * r['share']:g} % | {r['method']} | {r['particles']:,} | {r['physics']:.2f} | {r['render']:.2f} | "
              f"{r['plasticity']:.2f} | {r['mask']:.2f} | {r['frame']:.2f} | {1000 * r['frame'] / r['particles']:.3f} | "
              f"{r['peak_rss_mb'] / 1024:.2f} GiB |")


if __name__ == "__main__":
    main()
