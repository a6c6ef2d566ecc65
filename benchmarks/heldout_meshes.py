"""Held-out target meshes: shapes the defaults were never tuned on (the default parameters are
tried, untouched, on meshes from outside the repository's benchmark set).

    python benchmarks/heldout_meshes.py            # writes resources/heldout/*.obj
    snakemake --cores 2 tables --configfile config/heldout.yaml

Each shape is the zero level set of a signed distance function, meshed with marching cubes, so it
is one watertight surface whatever its parts (overlapping primitives would need a boolean union):
  torus     genus 1: the sphere must open a hole
  jack      three orthogonal capsules: six thin limbs
  dumbbell  two balls on a thin bar: a neck that must thin out
  table     a slab on four legs: legs apart from each other, a flat top
It prints, for each, the `size` (longest extent) that gives the volume of the other benchmark
shapes (~1170 units^3, config/config.yaml), the value config/heldout.yaml uses.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import trimesh
from skimage.measure import marching_cubes

REPO = Path(__file__).resolve().parent.parent
TARGET_VOLUME = 1170.0  # units^3, the benchmark shapes' volume (config/config.yaml)


def _capsule(p: np.ndarray, a: np.ndarray, b: np.ndarray, r: float) -> np.ndarray:  # p: [..., 3]
    ab = b - a
    t = np.clip(((p - a) @ ab) / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1) - r


def _box(p: np.ndarray, center, half) -> np.ndarray:  # p: [..., 3]
    q = np.abs(p - np.asarray(center)) - np.asarray(half)
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)


def _smooth_min(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b * (1 - h) + a * h - k * h * (1 - h)


def sdf(name: str, p: np.ndarray) -> np.ndarray:  # p: [..., 3] in a unit-ish frame, y up
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    if name == "torus":  # ring in the x-y plane (stands upright), hole seen along z
        return np.sqrt((np.sqrt(x ** 2 + y ** 2) - 0.62) ** 2 + z ** 2) - 0.3
    if name == "jack":
        e = np.eye(3) * 0.78
        d = [_capsule(p, -e[i], e[i], 0.24) for i in range(3)]
        return np.minimum(np.minimum(d[0], d[1]), d[2])
    if name == "dumbbell":
        balls = np.minimum(np.linalg.norm(p - [0.55, 0, 0], axis=-1) - 0.42,
                           np.linalg.norm(p + [0.55, 0, 0], axis=-1) - 0.42)
        bar = _capsule(p, np.array([-0.55, 0.0, 0.0]), np.array([0.55, 0.0, 0.0]), 0.15)
        return _smooth_min(balls, bar, 0.05)
    if name == "table":
        d = _box(p, (0, 0.3, 0), (0.8, 0.1, 0.55))
        for sx in (-1, 1):
            for sz in (-1, 1):
                d = np.minimum(d, _box(p, (0.62 * sx, -0.2, 0.4 * sz), (0.1, 0.45, 0.1)))
        return d
    raise ValueError(f"unknown held-out shape {name!r}")


SHAPES = ("torus", "jack", "dumbbell", "table")


def mesh(name: str, res: int = 128) -> trimesh.Trimesh:
    lin = np.linspace(-1.1, 1.1, res)
    grid = np.stack(np.meshgrid(lin, lin, lin, indexing="ij"), axis=-1)
    verts, faces, _, _ = marching_cubes(sdf(name, grid), level=0.0, spacing=(lin[1] - lin[0],) * 3)
    m = trimesh.Trimesh(verts + lin[0], faces[:, ::-1], process=True)  # outward normals
    if not m.is_watertight:
        raise RuntimeError(f"{name}: marching cubes gave a mesh that is not watertight")
    if m.volume < 0:
        m.invert()
    return m


def size_for_volume(m: trimesh.Trimesh, volume: float = TARGET_VOLUME) -> float:
    """The longest extent at which ``m`` has ``volume``."""
    extent = float(m.extents.max())
    return extent * (volume / float(m.volume)) ** (1 / 3)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(REPO / "resources" / "heldout"))
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name in SHAPES:
        m = mesh(name)
        m.export(out / f"{name}.obj")
        print(f"{name:9s} {len(m.faces):7d} faces  watertight {m.is_watertight}  size {size_for_volume(m):.1f} "
              f"for {TARGET_VOLUME:.0f} units^3  -> {out / (name + '.obj')}")


if __name__ == "__main__":
    main()
