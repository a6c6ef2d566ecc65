"""Benchmark the mesh and particle stages: prepared vs raw volume, particle counts and wall time.

    python benchmarks/bench_particles.py [--mesh-dir DIR] [--configs 32:2:1 64:5:1]

Prints one Markdown table row per shape and sampling setting. Times are wall-clock seconds of
prepare_mesh and of sample_particles (sampling + nearest-neighbour d_nn + HDF5 write).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from physmorph.meshes.shapes import ShapeSpec
from physmorph.meshes.prepare import prepare_mesh
from physmorph.meshes.particles import sample_particles

SHAPES = [
    ShapeSpec("iso", "isosphere", size=14.0),
    ShapeSpec("bunny", "file", file="stanford-bunny.obj", size=16.0),
    ShapeSpec("cow", "file", file="spot.obj", size=16.0),
    ShapeSpec("duck", "file", file="Duck.glb", size=16.0),
    ShapeSpec("A", "letter", glyph="A", size=16.0),
    ShapeSpec("S", "letter", glyph="S", size=16.0),
    ShapeSpec("C", "letter", glyph="C", size=16.0),
]


def main() -> None:
    here = Path(__file__).resolve().parents[1]
    ap = argparse.ArgumentParser()
    ap.add_argument("--mesh-dir", default=os.environ.get("PHYSMORPH_MESH_DIR", str(here.parent / "shared" / "meshes")))
    ap.add_argument("--configs", nargs="+", default=["32:2:1", "64:5:1"], help="grid_res:ppc_surface:ppc_interior")
    ap.add_argument("--density", type=float, default=75.0)
    args = ap.parse_args()
    configs = [tuple(int(v) for v in c.split(":")) for c in args.configs]
    print("| shape | raw volume | prepared volume | repair | prepare s | grid | PPC s/i | particles | shell | sampled volume | sample s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for spec in SHAPES:
            raw = Path(args.mesh_dir) / spec.file if spec.file else None
            mesh_h5 = Path(tmp) / f"{spec.name}.h5"
            t0 = time.perf_counter()
            m = prepare_mesh(spec, raw, mesh_h5)
            t_prep = time.perf_counter() - t0
            for res, ps, pi in configs:
                t0 = time.perf_counter()
                p = sample_particles(mesh_h5, Path(tmp) / f"{spec.name}_{res}.h5", res, ps, pi, args.density)
                t_s = time.perf_counter() - t0
                print(f"| {spec.name} | {m['raw_volume']:.1f} | {m['volume']:.1f} | {'; '.join(m['repair']) or '-'} | "
                      f"{t_prep:.2f} | {res} | {ps}/{pi} | {p['count']:,} | {p['n_surface']:,} | "
                      f"{p['sampled_volume']:.1f} | {t_s:.2f} |", flush=True)


if __name__ == "__main__":
    main()
