"""The run file's own cost: commit K + 1 frames of N particles, then finish the run (each frame file
read, verified and copied into the run file, the metrics built), best of --reps.

    python benchmarks/bench_runfile.py 1200 40          # the tiny scale: N particles, K frames
    python benchmarks/bench_runfile.py 100000 20 --reps 2

Every fourth frame keeps its state (x, F, Fp), the others their motion, as a morph with
`morph.save_every: 4` does, and every frame writes its checkpoint (a control of N x 3), the
most a run writes (a morph spaces them by their cost, `CHECKPOINT_WALL_SHARE`).
Prints the commit and finish times and a digest of the finished file's datasets (equal across
commits that change only speed; the file's content checksum also covers its times).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

import physmorph.records.runfile as runfile
from physmorph.records.runfile import SCALARS, RunWriter
from physmorph.records.runkey import RunKey


def one_run(folder: Path, n: int, frames: int, rng: np.random.Generator) -> tuple[float, float, str]:
    """(commit seconds, finish seconds, datasets_digest) of one run file made in ``folder``."""
    key = RunKey(json.dumps({"bench": 1}), (("target", "bench"),))
    t0 = time.perf_counter()
    with RunWriter(folder / "run.h5", key, started=0.0) as writer:
        writer.resume(lambda _line: None)
        writer.set_meta({"experiment": "bench"})
        for k in range(frames + 1):
            x = rng.normal(size=(n, 3))  # [N, 3]
            F = np.eye(3) + 0.01 * rng.normal(size=(n, 3, 3))  # [N, 3, 3]
            state = {"x": x, "F": F, "Fp": F} if k % 4 == 0 else None
            writer.commit(k, {s: 0.1 * k for s in SCALARS[:5]}, np.full(8, float(k)), state, [], {"ctrl": x},
                          last=k == frames, motion=None if state is not None else {"x": x, "F": F})
        t1 = time.perf_counter()
        writer.finish("complete", {"note": "bench"}, None)
    t2 = time.perf_counter()
    return t1 - t0, t2 - t1, datasets_digest(folder / "run.h5")


def datasets_digest(path: Path) -> str:
    """SHA-256 of a file's datasets (names, dtypes, shapes, values), not its attributes: the
    content checksum holds the run's times and provenance, which differ between any two runs."""
    h = hashlib.sha256()
    with h5py.File(path, "r") as f:
        names: list[str] = []
        f.visit(names.append)
        for name in sorted(n for n in names if isinstance(f[n], h5py.Dataset)):
            a = np.ascontiguousarray(f[name][()])
            h.update(f"{name} {a.dtype.str} {a.shape}".encode())
            h.update(a.tobytes())
    return h.hexdigest()


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("particles", type=int)
    ap.add_argument("frames", type=int)
    ap.add_argument("--reps", type=int, default=3)
    args = ap.parse_args(argv)
    runfile.CHECKPOINT_WALL_SHARE = None  # a checkpoint every frame: the commit's worst case
    commit = finish = float("inf")
    checksum = ""
    for _ in range(args.reps):
        with tempfile.TemporaryDirectory() as d:
            c, f, checksum = one_run(Path(d), args.particles, args.frames, np.random.default_rng(0))
        commit, finish = min(commit, c), min(finish, f)
    print(f"N={args.particles} K={args.frames} commit {commit:.3f} s  finish {finish:.3f} s  "
          f"datasets {checksum[:16]}")


if __name__ == "__main__":
    main()
