"""Where the physics' time goes, against what this machine can do: a script, not a test.

Prints this machine's measured limits, written here in Taichi on the same threads the solver uses:
the memory bandwidth of a STREAM-like triad (a[i] = b[i] + s c[i] over arrays far larger than the
caches: 12 bytes per element moved) and the floating-point rate of a register-bound kernel (eight
independent chains of fused multiply-adds per element). Then one MPM frame's rollout, forward and
backward, with Taichi's kernel profiler on: per kernel its launches, its time, its share of the
physics, and, for the kernels whose traffic is modelled below, the bytes it moves per launch, the
rate that makes, and that rate as a share of the triad's (the roofline's memory roof). Last, P2G's
two halves apart: its per-particle stress (the polar decomposition warm-started from the last
substep) and its scatter into the grid (27 nodes, 108 float atomic adds), each as a kernel.

Traffic model (float32, per particle per substep, each array read or written once; the grid's
scattered traffic counted at one 16-byte node (mass + momentum) per stencil point, 27 points):
  p2g          reads x v C F Fp^-1 m V0 (3+3+9+9+9+1+1 floats) and the control dFc (9),
               adds to 27 nodes                                    = 44*4 + 27*16 = 608 B
  grid_update  reads and writes every node once (16 B each, twice) = 32 B per node
  g2p          reads x v C F (24 floats) and 27 nodes (12 B each), writes x v C F = 24*4*2 + 27*12 = 516 B
Kernels outside the model (the adjoints, the loss, the control's updates) get their time only. A
kernel whose data stay in the caches (the 33^3 grid's 0.6 MB) can pass the triad's rate, which is
memory's: above 100 % it is not bound by memory at all.

    .venv/bin/python benchmarks/bench_roofline.py [--n 20000] [--res 32] [--threads 2] [--reps 2]
"""


import argparse
import os
import sys
import time

import numpy as np

# bytes per particle per launch (per node for grid kernels), as the docstring derives them
PARTICLE_BYTES = {"p2g": 608, "g2p": 516}
NODE_BYTES = {"grid_update": 32}
TRIAD_ELEMENTS = 1 << 25  # 3 arrays of 128 MB: far past any cache
FLOP_ELEMENTS = 1 << 18
FLOP_ITERS = 256  # fused multiply-adds per chain per element (8 chains)


def machine_limits(reps: int = 5) -> dict:
    """Measured triad bandwidth (bytes/s) and fused-multiply-add rate (FLOP/s), best of ``reps``."""
    import taichi as ti

    n = TRIAD_ELEMENTS
    a, b, c = (ti.field(ti.f32, shape=n) for _ in range(3))

    @ti.kernel
    def fill():
        for i in range(n):
            b[i], c[i] = ti.cast(i % 7, ti.f32), ti.cast(i % 5, ti.f32)

    @ti.kernel
    def triad(s: ti.f32):
        for i in range(n):
            a[i] = b[i] + s * c[i]

    m = FLOP_ELEMENTS
    out = ti.field(ti.f32, shape=m)

    @ti.kernel
    def fma_chains(x: ti.f32):
        for i in range(m):
            v = ti.Vector([x + i * 1e-7 + k for k in ti.static(range(8))])
            for _ in range(FLOP_ITERS):
                v = v * 0.999999 + 1e-6
            out[i] = v.sum()

    fill()
    triad(1.5)
    fma_chains(0.5)
    ti.sync()
    best_t, best_f = np.inf, np.inf
    for _ in range(reps):
        t0 = time.perf_counter()
        triad(1.5)
        ti.sync()
        best_t = min(best_t, time.perf_counter() - t0)
        t0 = time.perf_counter()
        fma_chains(0.5)
        ti.sync()
        best_f = min(best_f, time.perf_counter() - t0)
    return {"bandwidth": 12.0 * n / best_t, "flops": 2.0 * 8 * FLOP_ITERS * m / best_f}


def kernel_times() -> dict:
    """name -> (launches, total seconds) from Taichi's kernel profiler since its last clear."""
    from taichi.profiler.kernel_profiler import get_default_kernel_profiler

    profiler = get_default_kernel_profiler()
    profiler._update_records()  # Taichi's own collection and aggregation of its launch records (no public accessor)
    profiler._count_statistics()
    return {name: (int(r.counter), float(r.total_time) / 1e3) for name, r in profiler._statistical_results.items()}


def physics_profile(n: int, res: int, reps: int) -> tuple:
    """Per-kernel (launches, seconds) of ``reps`` forward+backward rollouts, their wall time, the
    grid's nodes and the solver."""
    import taichi as ti

    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from bench_mpm import BALL_RADIUS, lattice_ball
    from physmorph.base.grid import Grid, splat_mass
    from physmorph.mpm.solver import MPMSolver
    from physmorph.mpm.state import ParticleState
    from physmorph.settings.mpm import MPMConfig

    cfg = MPMConfig(grid_res=res)
    x = lattice_ball(n)
    spacing = BALL_RADIUS * (4.0 * np.pi / (3.0 * n)) ** (1.0 / 3.0)
    st = ParticleState.at_rest(x, np.full(n, cfg.density * spacing ** 3), np.full(n, spacing ** 3))
    solver = MPMSolver(cfg, n)
    solver.set_target_grid_mass(splat_mass(x * np.array([1.1, 0.95, 0.95]), st.mass, Grid(res)))
    solver.load_state(st)
    solver.forward()
    solver.backward()  # compiled and warm
    ti.sync()
    ti.profiler.clear_kernel_profiler_info()
    t0 = time.perf_counter()
    for _ in range(reps):
        solver.forward()
        solver.backward()
    ti.sync()
    return kernel_times(), time.perf_counter() - t0, (res + 1) ** 3, solver


def p2g_parts(solver, reps: int = 5) -> dict:
    """P2G's two halves timed apart, best of ``reps`` over every substep of the last rollout: its
    per-particle stress (Fe, the warm-started polar decomposition, P, the affine A) and its scatter
    (the 27 nodes' 108 float atomic adds), each a kernel of the library's own functions."""
    import taichi as ti

    model, traj, ctrl, n = solver.model, solver.trajectory, solver.control_field, solver.model.n
    sink = ti.field(model.dtype, shape=n)
    T = solver.cfg.substeps

    @ti.kernel
    def stress_only(t: ti.i32):
        for q in range(n):
            Fe = (traj.F[t, q] + ctrl.ctrl[t, q]) @ model.Fp_inv[q]
            R, S, gap = model.stress.polar_from(Fe, traj.R_prev[q])
            P = model.stress.stress_from_polar(Fe, R)
            sink[q] = (P @ Fe.transpose()).sum() + gap

    @ti.kernel
    def scatter_only(t: ti.i32):
        for q in range(n):
            base, fx, w, dw = model.stencil(traj.x[t, q])
            mom = model.mass[q] * traj.v[t, q]
            for i, j, k in ti.ndrange(3, 3, 3):
                off, dpos, wt = model.node(fx, w, i, j, k)
                traj.grid_mv[base + off] += wt * (mom + traj.C[t, q] @ dpos)
                traj.grid_m[base + off] += wt * model.mass[q]

    out = {}
    for name, kernel in (("p2g: stress", stress_only), ("p2g: scatter", scatter_only)):
        kernel(0)
        ti.sync()
        best = np.inf
        for _ in range(reps):
            t0 = time.perf_counter()
            for t in range(T):
                kernel(t)
            ti.sync()
            best = min(best, time.perf_counter() - t0)
        out[name] = best / T
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=20000)
    ap.add_argument("--res", type=int, default=32)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=2)
    args = ap.parse_args()
    os.environ["PHYSMORPH_KERNEL_PROFILER"] = "1"
    from physmorph.base.taichi_runtime import init_taichi

    init_taichi("cpu", threads=args.threads)
    limits = machine_limits()
    times, wall, nodes, solver = physics_profile(args.n, args.res, args.reps)
    total = sum(t for _, t in times.values())
    print(f"machine ({args.threads} threads): triad {limits['bandwidth'] / 1e9:.1f} GB/s, "
          f"fused multiply-add {limits['flops'] / 1e9:.1f} GFLOP/s")
    print(f"physics: N={args.n}, grid {args.res}^3, {args.reps} forward+backward rollouts in {wall:.2f} s wall "
          f"({total:.2f} s in kernels)")
    hdr = f"{'kernel':<44} {'launches':>8} {'s':>7} {'share':>6} {'B/launch':>10} {'GB/s':>6} {'of triad':>8}"
    print(hdr + "\n" + "-" * len(hdr))
    by_kernel: dict = {}
    for name, (count, seconds) in times.items():
        short = name.rsplit("_c", 1)[0]  # Taichi appends _c<k>_<id> to each compiled kernel's name
        launches, spent = by_kernel.get(short, (0, 0.0))
        by_kernel[short] = (launches + count, spent + seconds)
    for short, (count, seconds) in sorted(by_kernel.items(), key=lambda kv: -kv[1][1]):
        if seconds < 0.002 * total:
            continue
        key = short if short in PARTICLE_BYTES or short in NODE_BYTES else None
        per = PARTICLE_BYTES.get(key, 0) * args.n + NODE_BYTES.get(key, 0) * nodes if key else None
        rate = per * count / seconds if per else None
        print(f"{short[:44]:<44} {count:>8} {seconds:>7.3f} {100 * seconds / total:>5.1f}% "
              + (f"{per:>10,} {rate / 1e9:>6.1f} {100 * rate / limits['bandwidth']:>7.0f}%" if per else ""))
    p2g_launch = by_kernel.get("p2g", (1, 0.0))
    parts = p2g_parts(solver)
    print(f"p2g, {1e3 * p2g_launch[1] / max(p2g_launch[0], 1):.2f} ms a launch, apart: "
          + ", ".join(f"{name.split(': ')[1]} {1e3 * sec:.2f} ms" for name, sec in parts.items()))


if __name__ == "__main__":
    main()
