"""Benchmark of the differentiable MPM solver (physmorph.mpm): a script, not a test.

For each particle count N, grid resolution and CPU thread count it prints forward and
forward+backward throughput in particle-steps/s (N * T / seconds per rollout), the first-call
(compile + warm-up) time, and the bytes per particle per stored substep. T = 20, float32, the
paper's material and drag, F smoothing s = 0.955 (`--smoothing-mode`, default the library's
default, isochoric; `full` is the paper's blend), per-substep control, squared mass loss.

    .venv/bin/python benchmarks/bench_mpm.py                     # full table (minutes)
    .venv/bin/python benchmarks/bench_mpm.py --n 5000 --res 32 --threads 2 --reps 2
    .venv/bin/python benchmarks/bench_mpm.py --n 20000 --res 32 --threads 2 --reps 30 --best

Thread counts need separate processes (Taichi is initialised once per process), so the driver
re-runs this file per thread count with PHYSMORPH_THREADS set. Compile time depends on the
Taichi offline cache (warm after the first run with the same shapes).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

BALL_RADIUS = 7.0  # fits the default domain [-16, 16]^3 inside the 3-cell boundary layer


def lattice_ball(n: int, radius: float = BALL_RADIUS) -> np.ndarray:  # [n, 3]
    """About n particles on a cubic lattice inside a ball (lattice order, as a sampler gives)."""
    h = radius * (4.0 * np.pi / (3.0 * n)) ** (1.0 / 3.0)
    for _ in range(20):
        a = np.arange(-radius, radius + 1e-9, h)
        X = np.stack(np.meshgrid(a, a, a, indexing="ij"), -1).reshape(-1, 3)
        X = X[np.linalg.norm(X, axis=1) <= radius]
        if len(X) >= n:
            return X[:n]
        h *= 0.99
    return X


def run_case(n: int, res: int, T: int, reps: int, precision: str, smoothing_mode: str, best: bool = False) -> dict:
    from physmorph.base.grid import Grid, splat_mass
    from physmorph.settings.mpm import MPMConfig
    from physmorph.mpm.solver import MPMSolver
    from physmorph.mpm.state import ParticleState

    cfg = MPMConfig(grid_res=res, substeps=T, precision=precision, smoothing_mode=smoothing_mode)
    x = lattice_ball(n)
    spacing = BALL_RADIUS * (4.0 * np.pi / (3.0 * n)) ** (1.0 / 3.0)
    st = ParticleState.at_rest(x, np.full(n, cfg.density * spacing ** 3), np.full(n, spacing ** 3))
    t0 = time.perf_counter()
    solver = MPMSolver(cfg, n)
    solver.set_target_grid_mass(splat_mass(x * np.array([1.1, 0.95, 0.95]), st.mass, Grid(res)))
    solver.load_state(st)
    solver.optimize_control(iters=1)  # compiles every kernel of the loop
    warmup = time.perf_counter() - t0

    fwd, fb = [], []
    for _ in range(reps):
        t0 = time.perf_counter()
        solver.forward()
        fwd.append(time.perf_counter() - t0)
    for _ in range(reps):
        t0 = time.perf_counter()
        solver.forward()
        solver.backward()
        fb.append(time.perf_counter() - t0)
    pick = min if best else (lambda ts: sum(ts) / len(ts))
    t_fwd, t_fb = pick(fwd), pick(fb)

    item = 4 if precision == "float32" else 8
    state_b = solver.bytes_per_particle_substep()
    # control dFc + its gradient + 2 Adam moments: 4 x 9 floats per particle per control slot
    ctrl_b = 36 * item * cfg.n_control_slots / T
    ppc = n / (4.0 / 3.0 * np.pi * BALL_RADIUS ** 3 / cfg.dx ** 3)
    return dict(n=n, res=res, T=T, threads=int(os.environ.get("PHYSMORPH_THREADS", "0")),
                ppc=ppc, fwd_ps=n * T / t_fwd, fb_ps=n * T / t_fb, warmup_s=warmup,
                state_bytes=state_b, ctrl_bytes=ctrl_b)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, nargs="+", default=[5000, 20000, 100000])
    ap.add_argument("--res", type=int, nargs="+", default=[32, 64])
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--substeps", type=int, default=20)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--precision", default="float32", choices=["float32", "float64"])
    ap.add_argument("--smoothing-mode", default="isochoric", choices=["isochoric", "full"])
    ap.add_argument("--best", action="store_true",
                    help="rates from the fastest repetition, not the mean: the stable figure where other "
                         "tenants of the machine come and go (compare two commits with it, alternated)")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()

    if args.worker:  # one process per thread count: print one JSON line per case
        for res in args.res:
            for n in args.n:
                print(json.dumps(run_case(n, res, args.substeps, args.reps, args.precision,
                                          args.smoothing_mode, args.best)),
                      flush=True)
        return

    rows = []
    for th in args.threads:
        env = dict(os.environ, PHYSMORPH_THREADS=str(th))
        cmd = [sys.executable, __file__, "--worker", "--n", *map(str, args.n), "--res", *map(str, args.res),
               "--substeps", str(args.substeps), "--reps", str(args.reps), "--precision", args.precision,
               "--smoothing-mode", args.smoothing_mode, *(["--best"] if args.best else [])]
        out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True,
                             cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        rows += [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]

    print(f"MPM benchmark: T={args.substeps}, {args.precision}, "
          f"smoothing={args.smoothing_mode}, "
          f"reps={args.reps} ({'the fastest' if args.best else 'their mean'}), cpu_count={os.cpu_count()}")
    hdr = (f"{'N':>7} {'grid':>5} {'thr':>3} {'PPC':>5} {'fwd p-steps/s':>14} {'fwd+bwd p-steps/s':>18} "
           f"{'warm-up s':>9} {'B/p/substep state':>17} {'+ctrl&Adam':>10}")
    print(hdr)
    print("-" * len(hdr))
    for r in sorted(rows, key=lambda r: (r["res"], r["n"], r["threads"])):
        print(f"{r['n']:>7} {r['res']:>4}^3 {r['threads']:>3} {r['ppc']:>5.1f} {r['fwd_ps']:>14,.0f} "
              f"{r['fb_ps']:>18,.0f} {r['warmup_s']:>9.1f} {r['state_bytes']:>17} "
              f"{r['state_bytes'] + r['ctrl_bytes']:>10.0f}")


if __name__ == "__main__":
    main()
