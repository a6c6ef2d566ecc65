"""Where the physics' time goes, against what this machine can do: a script, not a test.

Prints this machine's measured limits, written here in Taichi on the same threads the solver uses:
the memory bandwidth of a STREAM-like triad (a[i] = b[i] + s c[i] over arrays far larger than the
caches: 12 bytes per element moved) and the floating-point rate of a register-bound kernel (eight
independent chains of fused multiply-adds per element: what Taichi's code reaches, one particle per
lane, not vectorised across particles on a CPU); beside them the machine's vector float32 peak as a
tuned library reaches it (a matrix product in torch). Then one MPM frame's rollout, forward and
backward, with Taichi's kernel profiler on: per kernel its launches, its time, its share of the
physics, and, for the kernels whose traffic is modelled below, the bytes it moves per launch, the
rate that makes, and that rate as a share of the triad's (the roofline's memory roof). Last, P2G's
per-particle stress (the polar decomposition warm-started from the last substep, P and the
affine A) timed apart as a kernel of its own: the rest of P2G's time is its walk over the 27 nodes.
With ``--markdown`` the same tables replace the generated section of docs/performance.md.
``--device cuda`` measures a GPU the same way (its own section of that page): the probes' arrays are
sized for a GPU's caches and rates, and the grid's model has one lane (a GPU's scatters are atomic).

Traffic model (float32, per particle per substep, each array read or written once; the grid's
scattered traffic counted at one 16-byte node (mass + momentum) per stencil point, 27 points):
  p2g          reads x v C F Fp^-1 m V0 (3+3+9+9+9+1+1 floats), the control dFc (9) and the last
               substep's rotation R (9), writes R, its quaternion and the polar gap (9+4+1), adds
               to 27 nodes (of its thread's lane)                  = 67*4 + 27*16 = 700 B
  grid_update  reads and zeroes each thread's lane of a node (16 B each, twice a lane), writes the
               node's m, mv, their copy for the backward and v   = 32 * threads + 44 B per node
  g2p          reads x F (12 floats) and 27 nodes (12 B each), writes x v C F (24) = 36*4 + 27*12 = 468 B
Operation model (per particle, or per node for the grid, counted from the kernels' code: +, -, x,
/ one each, and sqrt, pow, floor, sin, cos, acos one each though they take many cycles; a fused
multiply-add is two, as the peak probe counts them):
  p2g          the stencil's weights 63, Fe 54, the warm-started polar decomposition ~880 (two
               Newton steps of ~370: R^T Fe 45, its symmetric part 18, the largest eigenvalue 54,
               the gap's check 22, the 3x3 solve 90, the step's rotation 140; then S, the
               eigenvalue and the check once more ~140), the quaternion 15, P 83, A 77, the
               momentum and the rows' starts 6 + 27 + 9*19, the 27 nodes 27*12  = ~1,700 FLOP
  g2p          the stencil 63, the rows 9*19 and their 27 nodes 27*13, C 30, F 57, the blend 28
               and its volume scale 39 (isochoric), x 6                       = ~745 FLOP
  grid_update  the lanes' sum 4 (threads - 1) and v = mv / m 3 per node
P2G's stress (everything before its node walk, ~1,110 FLOP) is timed apart, so its rate is given too.
From PACKED_STRESS_MIN_PARTICLES on (the paper's scale on a CPU) that stress runs as a kernel of its
own on packs of particles (p2g_stress, physmorph.mpm.stress_packs) and leaves A for P2G's node walk:
the two count as one P2G here, with A's store and load (+72 B) added to its traffic, and the
stress's time is p2g_stress's own in the rollout, not a kernel timed apart.
Kernels outside the models (the adjoints, the loss, the control's updates) get their time only. A
kernel whose data stay in the caches (the 33^3 grid's 0.6 MB) can pass the triad's rate, which is
memory's: above 100 % it is not bound by memory at all.

    .venv/bin/python benchmarks/bench_roofline.py [--n 20000] [--res 32] [--threads 2] [--reps 2] [--markdown]
    python benchmarks/bench_roofline.py --device cuda --n 471282 --res 64 --markdown   # on a GPU machine
"""


import argparse
import os
import sys
import time

import numpy as np

# bytes per particle per launch (per node for grid kernels), as the docstring derives them
PARTICLE_BYTES = {"p2g": 700, "g2p": 468}
PACKED_AFFINE_BYTES = 72  # p2g_stress's A, stored and read back by P2G (the packed path)
NODE_BYTES = {"grid_update": 44}  # and 32 B per thread (kernel_rows adds it)
# floating-point operations per particle per launch (per node for grid kernels), as the docstring counts them
PARTICLE_FLOPS = {"p2g": 1700, "g2p": 745}
NODE_FLOPS = {"grid_update": 3}  # and 4 per thread after the first (kernel_rows adds it)
P2G_STRESS_FLOPS = 1110
# elements of the probes' arrays by device: the triad's 3 arrays far past any cache (128 MB each on
# a CPU, 1 GB on a GPU), and enough FMA chains to fill a GPU's cores for over a millisecond
TRIAD_ELEMENTS = {"cpu": 1 << 25, "cuda": 1 << 28}
FLOP_ELEMENTS = {"cpu": 1 << 18, "cuda": 1 << 24}
FLOP_ITERS = 256  # fused multiply-adds per chain per element (8 chains)


def machine_limits(device: str = "cpu", reps: int = 5, threads: int = 2) -> dict:
    """Measured triad bandwidth (bytes/s) and fused-multiply-add rate (FLOP/s), best of ``reps``."""
    import taichi as ti

    n = TRIAD_ELEMENTS[device]
    a, b, c = (ti.field(ti.f32, shape=n) for _ in range(3))

    @ti.kernel
    def fill():
        for i in range(n):
            b[i], c[i] = ti.cast(i % 7, ti.f32), ti.cast(i % 5, ti.f32)

    @ti.kernel
    def triad(s: ti.f32):
        for i in range(n):
            a[i] = b[i] + s * c[i]

    m = FLOP_ELEMENTS[device]
    out = ti.field(ti.f32, shape=m)

    # the multiplier and the addend are arguments: as constants, fast math lets the compiler fold
    # two steps a (a v + b) + b into one (a^2 v + c), and a GPU then "passes" its peak 2.4 times
    @ti.kernel
    def fma_chains(x: ti.f32, mul: ti.f32, add: ti.f32):
        for i in range(m):
            v = ti.Vector([x + i * 1e-7 + k for k in ti.static(range(8))])
            for _ in range(FLOP_ITERS):
                v = v * mul + add
            out[i] = v.sum()

    fill()
    triad(1.5)
    fma_chains(0.5, 0.999999, 1e-6)
    ti.sync()
    best_t, best_f = np.inf, np.inf
    for _ in range(reps):
        t0 = time.perf_counter()
        triad(1.5)
        ti.sync()
        best_t = min(best_t, time.perf_counter() - t0)
        t0 = time.perf_counter()
        fma_chains(0.5, 0.999999, 1e-6)
        ti.sync()
        best_f = min(best_f, time.perf_counter() - t0)
    return {"bandwidth": 12.0 * n / best_t, "flops": 2.0 * 8 * FLOP_ITERS * m / best_f, "gemm": gemm_rate(device, reps, threads)}


def gemm_rate(device: str, reps: int, threads: int, size: int = 4096) -> float:
    """The machine's vector float32 peak as a tuned library reaches it: a size x size matrix product
    in torch (FLOP/s, best of ``reps``; on a GPU without TF32's tensor cores). Taichi's own kernels
    do not vectorise across particles, so the FMA chains above are their roof and this the machine's.
    On the CPU on ``threads`` threads, as the solver."""
    import torch

    if device == "cpu":
        torch.set_num_threads(threads)
    torch.backends.cuda.matmul.allow_tf32 = False
    a, b = (torch.randn(size, size, device=device) for _ in range(2))
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    a @ b
    sync()
    best = np.inf
    for _ in range(reps):
        t0 = time.perf_counter()
        a @ b
        sync()
        best = min(best, time.perf_counter() - t0)
    return 2.0 * size ** 3 / best


def kernel_times() -> dict:
    """name -> (launches, total seconds) from Taichi's kernel profiler since its last clear."""
    from taichi.profiler.kernel_profiler import get_default_kernel_profiler

    profiler = get_default_kernel_profiler()
    profiler._update_records()  # Taichi's own collection and aggregation of its launch records (no public accessor)
    profiler._count_statistics()
    return {name: (int(r.counter), float(r.total_time) / 1e3) for name, r in profiler._statistical_results.items()}


def physics_profile(n: int, res: int, reps: int, device: str = "cpu") -> tuple:
    """Per-kernel (launches, seconds) of ``reps`` forward+backward rollouts, their wall time, the
    grid's nodes and the solver."""
    import taichi as ti

    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from bench_mpm import BALL_RADIUS, lattice_ball
    from physmorph.base.grid import Grid, splat_mass
    from physmorph.mpm.solver import MPMSolver
    from physmorph.mpm.state import ParticleState
    from physmorph.settings.mpm import MPMConfig

    cfg = MPMConfig(grid_res=res, device=device)
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


def p2g_stress_seconds(solver, reps: int = 5) -> float:
    """P2G's per-particle stress (Fe, the warm-started polar decomposition, P, the affine A) as a
    kernel of the library's own functions: seconds a launch, best of ``reps`` over every substep
    of the last rollout."""
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

    stress_only(0)
    ti.sync()
    best = np.inf
    for _ in range(reps):
        t0 = time.perf_counter()
        for t in range(T):
            stress_only(t)
        ti.sync()
        best = min(best, time.perf_counter() - t0)
    return best / T


def short_name(name: str) -> str:
    """A kernel's name less the _c<k>_<id> Taichi appends to each compiled kernel's."""
    return name.rsplit("_c", 1)[0]


def p2g_stress_time(times: dict, solver) -> tuple[float, str]:
    """P2G's stress, seconds a launch, and how it was timed: p2g_stress's own launches in the
    rollout where the solver runs it on packs, else the kernel timed apart (p2g_stress_seconds)."""
    if not solver.transfers.packed:
        return p2g_stress_seconds(solver), "timed apart"
    count, seconds = next(v for name, v in times.items() if short_name(name) == "p2g_stress")
    return seconds / count, "p2g_stress on packs, in the rollout"


def kernel_rows(times: dict, n: int, nodes: int, limits: dict, lanes: int, packed: bool = False) -> list:
    """(kernel, launches, seconds, share, bytes a launch or None, GB/s or None, share of the triad
    or None, FLOP/s or None, share of the FMA chains' rate or None, share of the GEMM peak or None)
    for every kernel above 0.2 % of the total, the slowest first. ``lanes``: the grid's scatter
    lanes (the CPU's threads; 1 on a GPU); ``packed``: P2G's stress ran on packs (p2g_stress), its
    A stored and read back."""
    total = sum(t for _, t in times.values())
    by_kernel: dict = {}
    for name, (count, seconds) in times.items():
        short = short_name(name)
        if short == "p2g_stress":
            # P2G's stress on packs (the CPU from 100K particles): the models are P2G's as one
            # step, so its time counts as P2G's, its launches as the same launches
            short, count = "p2g", 0
        launches, spent = by_kernel.get(short, (0, 0.0))
        by_kernel[short] = (launches + count, spent + seconds)
    rows = []
    for short, (count, seconds) in sorted(by_kernel.items(), key=lambda kv: -kv[1][1]):
        if seconds < 0.002 * total:
            continue
        key = short if short in PARTICLE_BYTES or short in NODE_BYTES else None
        node_bytes = NODE_BYTES.get(key, 0) + (32 * lanes if key in NODE_BYTES else 0)
        particle_bytes = PARTICLE_BYTES.get(key, 0) + (PACKED_AFFINE_BYTES if packed and key == "p2g" else 0)
        per = particle_bytes * n + node_bytes * nodes if key else None
        rate = per * count / seconds if per else None
        bandwidth, peak, gemm = limits["bandwidth"], limits["flops"], limits["gemm"]
        ops = PARTICLE_FLOPS.get(key, 0) * n + (NODE_FLOPS.get(key, 0) + 4 * (lanes - 1)) * nodes * (key in NODE_FLOPS)
        flops = ops * count / seconds if key else None
        rows.append((short, count, seconds, seconds / total, per, rate, rate / bandwidth if rate else None,
                     flops, flops / peak if flops else None, flops / gemm if flops else None))
    return rows


def where(args) -> str:
    """The probes' and the rollout's device in words."""
    return f"{args.threads} threads" if args.device == "cpu" else f"{args.device}: {gpu_name()}"


def gpu_name() -> str:
    try:
        import torch

        return torch.cuda.get_device_name(0)
    except Exception:  # a name only: the measures stand without it
        return "GPU"


def command(args) -> str:
    """The command line that makes this section."""
    device = "" if args.device == "cpu" else f"--device {args.device} "
    threads = f"--threads {args.threads} " if args.device == "cpu" else ""
    return f"python benchmarks/bench_roofline.py {device}--n {args.n} --res {args.res} {threads}--reps {args.reps} --markdown"


def print_report(args, limits: dict, wall: float, rows: list, p2g_stress: tuple) -> None:
    total = sum(r[2] for r in rows)
    print(f"machine ({where(args)}): triad {limits['bandwidth'] / 1e9:.1f} GB/s, "
          f"fused multiply-add chains {limits['flops'] / 1e9:.1f} GFLOP/s, float32 GEMM {limits['gemm'] / 1e9:.1f} GFLOP/s")
    print(f"physics: N={args.n}, grid {args.res}^3, {args.reps} forward+backward rollouts in {wall:.2f} s wall "
          f"({total:.2f} s in the kernels listed)")
    hdr = (f"{'kernel':<36} {'launches':>8} {'s':>7} {'share':>6} {'B/launch':>10} {'GB/s':>6} {'of triad':>8} "
           f"{'GFLOP/s':>7} {'of FMA':>6} {'of GEMM':>7}")
    print(hdr + "\n" + "-" * len(hdr))
    for short, count, seconds, share, per, rate, of_triad, flops, of_peak, of_gemm in rows:
        print(f"{short[:36]:<36} {count:>8} {seconds:>7.3f} {100 * share:>5.1f}% "
              + (f"{per:>10,} {rate / 1e9:>6.1f} {100 * of_triad:>7.0f}% {flops / 1e9:>7.1f} {100 * of_peak:>5.1f}% {100 * of_gemm:>6.1f}%"
                 if per else ""))
    p2g = next((r for r in rows if r[0] == "p2g"), None)
    if p2g:
        seconds, how = p2g_stress
        print(f"p2g, {1e3 * p2g[2] / p2g[1]:.2f} ms a launch, of which its stress {1e3 * seconds:.2f} ms "
              f"({how}: {P2G_STRESS_FLOPS * args.n / seconds / 1e9:.1f} GFLOP/s)")


def markdown_section(args, limits: dict, wall: float, rows: list, p2g_stress: tuple) -> str:
    """The generated section of docs/performance.md (between its roofline markers)."""
    total = sum(r[2] for r in rows)
    lines = [f"Generated by `{command(args)}` at commit {args.commit or commit()}: the machine's triad "
             f"{limits['bandwidth'] / 1e9:.1f} GB/s, fused multiply-add chains {limits['flops'] / 1e9:.1f} GFLOP/s "
             f"and float32 GEMM {limits['gemm'] / 1e9:.1f} GFLOP/s "
             f"({where(args)}); {args.reps} forward+backward rollouts of {args.n:,} particles on "
             f"{args.res}³ in {wall:.2f} s ({total:.2f} s in the kernels below).", "",
             "| kernel | launches | s | share | bytes a launch | GB/s | of the triad | GFLOP/s | of the FMA chains | of the GEMM peak |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for short, count, seconds, share, per, rate, of_triad, flops, of_peak, of_gemm in rows:
        lines.append(f"| `{short}` | {count} | {seconds:.3f} | {100 * share:.1f} % | "
                     + (f"{per:,} | {rate / 1e9:.1f} | {100 * of_triad:.0f} % | {flops / 1e9:.1f} | {100 * of_peak:.1f} % | {100 * of_gemm:.1f} % |"
                        if per else " | | | | | |"))
    p2g = next((r for r in rows if r[0] == "p2g"), None)
    if p2g:
        seconds, how = p2g_stress
        lines += ["", f"P2G: {1e3 * p2g[2] / p2g[1]:.2f} ms a launch, of which its stress {1e3 * seconds:.2f} ms "
                      f"({how}: {P2G_STRESS_FLOPS * args.n / seconds / 1e9:.1f} GFLOP/s by the operation "
                      "model); the rest is its walk over the 27 nodes. Bytes and operations are the script's models "
                      "(its docstring), times the kernel profiler's."]
    return "\n".join(lines) + "\n"


def commit() -> str:
    import subprocess

    out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=os.path.dirname(__file__))
    return out.stdout.strip() or "unknown"


def write_section(path: str, text: str, device: str = "cpu") -> None:
    """Replace what lies between the device's roofline markers of ``path`` with ``text``."""
    tag = "roofline" if device == "cpu" else f"roofline {device}"
    begin, end = f"<!-- {tag}: generated by benchmarks/bench_roofline.py --markdown -->", f"<!-- {tag} end -->"
    doc = open(path, encoding="utf-8").read()
    i, j = doc.index(begin) + len(begin), doc.index(end)
    with open(path, "w", encoding="utf-8") as f:
        f.write(doc[:i] + "\n" + text + doc[j:])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=20000)
    ap.add_argument("--res", type=int, default=32)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--markdown", action="store_true", help="also write the tables into docs/performance.md")
    ap.add_argument("--commit", help="the commit the section names (default: git's HEAD here)")
    args = ap.parse_args()
    os.environ["PHYSMORPH_KERNEL_PROFILER"] = "1"
    from physmorph.base.taichi_runtime import init_taichi

    init_taichi(args.device, threads=args.threads)
    import taichi as ti
    from taichi.lang import impl

    if args.device == "cuda" and impl.current_cfg().arch != ti.cuda:  # Taichi falls back to the CPU silently
        sys.exit("bench_roofline: --device cuda, but Taichi found no usable CUDA device")
    limits = machine_limits(args.device, threads=args.threads)
    times, wall, nodes, solver = physics_profile(args.n, args.res, args.reps, args.device)
    lanes = solver.model.lanes.count
    rows = kernel_rows(times, args.n, nodes, limits, lanes, packed=solver.transfers.packed)
    p2g_stress = p2g_stress_time(times, solver)
    print_report(args, limits, wall, rows, p2g_stress)
    if args.markdown:
        doc = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "docs", "performance.md")
        write_section(doc, markdown_section(args, limits, wall, rows, p2g_stress), args.device)


if __name__ == "__main__":
    main()
