"""Benchmark of the differentiable Gaussian splatting renderer (physmorph.render).

Forward and forward+backward (render_and_grad: three losses, adaptive gradient matching, dL/dF)
time for 8 ring views at 320x180 and 960x540 with 5K, 20K and 100K Gaussians on a sphere shell
(the shape of a surface-masked particle set), on 1 and 2 threads; and the dense reference's
forward+backward time (every pixel x every Gaussian, torch autograd). The dense reference cannot
hold pixels x Gaussians in memory at these sizes, so it runs on pixel chunks (chunks are
independent): a few chunks are timed and the time is scaled to all pixels ("extrapolated").

Every configuration runs in its own process (Taichi's thread count is fixed at start-up) and
reports its peak RSS above the post-import baseline. Usage:

    .venv/bin/python benchmarks/bench_render.py                 # full table
    .venv/bin/python benchmarks/bench_render.py --quick         # 320x180, 5K and 20K only
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np

RESOLUTIONS = {"320x180": (320, 180), "960x540": (960, 540)}
COUNTS = (5_000, 20_000, 100_000)
VIEWS = 8
RADIUS = 8.0  # sphere shell radius (world units; the ring cameras sit at distance 48)


def make_scene(n: int, width: int, height: int, seed: int = 0):
    from physmorph.base.cameras import ring_cameras
    from physmorph.render.containers import RenderTarget

    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    x = RADIUS * d * (1.0 + 0.01 * rng.normal(size=(n, 1)))
    F = np.eye(3) + 0.1 * rng.normal(size=(n, 3, 3))
    sigma0 = 0.7 * np.sqrt(4 * np.pi * RADIUS ** 2 / n)  # c * nearest-neighbour spacing
    cams = ring_cameras(VIEWS, width=width, height=height)
    # Target: a smaller sphere (radius 0.85 R) seen from the ring: an exact disk per view.
    f = cams.intrinsics[0, 1]
    dist = np.linalg.norm(cams.centers[0])
    r_t = 0.85 * RADIUS
    r_px = f * r_t / np.sqrt(dist ** 2 - r_t ** 2)
    jj, ii = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    sdt = np.hypot(ii - width / 2, jj - height / 2) - r_px
    alpha = np.clip(0.5 - sdt, 0, 1)
    shape = (VIEWS, height, width)
    target = RenderTarget(np.broadcast_to(alpha, shape).copy(),
                          np.broadcast_to(np.where(alpha > 0, dist - r_t, 0.0), shape).copy(),
                          np.broadcast_to(sdt, shape).copy())
    return x, F, sigma0, cams, target


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_fast(n: int, res: str, reps: int) -> dict:
    import torch

    from physmorph.settings.render import RenderConfig
    from physmorph.render.api import render_and_grad, render_views
    from physmorph.render.api import _to_tensors, splat

    width, height = RESOLUTIONS[res]
    base = _rss_mb()  # after imports and Taichi start-up: growth = scene + renderer
    x, F, sigma0, cams, target = make_scene(n, width, height)
    cfg = RenderConfig()
    render_and_grad(x, F, sigma0, cams, target, cfg)  # warm-up: Taichi compile / offline cache
    fwd, both = [], []
    for _ in range(reps):
        t = time.perf_counter()
        render_views(x, F, sigma0, cams, cfg)
        fwd.append(time.perf_counter() - t)
        t = time.perf_counter()
        r = render_and_grad(x, F, sigma0, cams, target, cfg)
        both.append(time.perf_counter() - t)
    xt, Ft, st, ct = _to_tensors(x, F, np.asarray(sigma0), cams, cfg)
    with torch.no_grad():
        pairs = splat(xt, Ft, st, ct, cfg).bins.pair_count
    return dict(fwd_s=float(np.median(fwd)), fwdbwd_s=float(np.median(both)), pairs=pairs,
                peak_rss_mb=_rss_mb(), rss_growth_mb=_rss_mb() - base, alpha_mse=r.alpha_mse)


def run_dense(n: int, res: str, chunk: int, chunks: int) -> dict:
    import torch

    from physmorph.settings.render import RenderConfig
    from physmorph.render.api import _to_tensors
    from physmorph.render.dense import _dense_pixels
    from physmorph.render.projection import covariance_from_F, project_gaussians

    width, height = RESOLUTIONS[res]
    x, F, sigma0, cams, _ = make_scene(n, width, height)
    cfg = RenderConfig()
    xt, Ft, st, ct = _to_tensors(x, F, np.asarray(sigma0), cams, cfg)
    Ft.requires_grad_(True)
    rng = np.random.default_rng(1)
    times = []
    for _ in range(chunks + 1):  # the first chunk is a warm-up
        t = time.perf_counter()
        proj = project_gaussians(xt, covariance_from_F(Ft, st), ct, cfg)
        v = int(rng.integers(VIEWS))
        order = torch.argsort(proj.params[v, :, 5].detach())
        p0 = int(rng.integers(width * height - chunk))
        pix = torch.arange(p0, p0 + chunk)
        centres = torch.stack([pix % width, pix // width], 1).float() + 0.5
        a, d = _dense_pixels(proj.params[v, order], proj.visible[v, order], centres, cfg)
        (a.sum() + d.sum()).backward()
        times.append(time.perf_counter() - t)
    per_pixel = float(np.mean(times[1:])) / chunk
    return dict(dense_fwdbwd_s=per_pixel * VIEWS * width * height, dense_pixels_timed=chunk * chunks,
                dense_full_memory_gb=VIEWS * width * height * n * 4 * 12 / 1e9)


def child(args) -> None:
    import torch

    torch.set_num_threads(args.threads)
    from physmorph.base.taichi_runtime import init_taichi

    init_taichi("cpu", args.threads)
    out = run_dense(args.n, args.res, args.chunk, args.chunks) if args.dense else run_fast(args.n, args.res, args.reps)
    print("RESULT " + json.dumps(out))


def spawn(threads: int, n: int, res: str, dense: bool, reps: int, chunk: int, chunks: int) -> dict:
    cmd = [sys.executable, __file__, "--child", "--threads", str(threads), "--n", str(n), "--res", res,
           "--reps", str(reps), "--chunk", str(chunk), "--chunks", str(chunks)] + (["--dense"] if dense else [])
    env = dict(os.environ, PHYSMORPH_THREADS=str(threads), OMP_NUM_THREADS=str(threads))
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    for line in out.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    raise RuntimeError(f"benchmark child failed:\n{out.stdout}\n{out.stderr}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--dense", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--n", type=int, default=20_000, help=argparse.SUPPRESS)
    ap.add_argument("--res", default="320x180", help=argparse.SUPPRESS)
    ap.add_argument("--threads", type=int, default=1, help=argparse.SUPPRESS)
    ap.add_argument("--reps", type=int, default=3, help="timed repetitions (median reported)")
    ap.add_argument("--chunk", type=int, default=256, help="dense reference: pixels per timed chunk")
    ap.add_argument("--chunks", type=int, default=3, help="dense reference: timed chunks")
    ap.add_argument("--quick", action="store_true", help="320x180 with 5K and 20K Gaussians only")
    ap.add_argument("--thread-list", default="1,2")
    ap.add_argument("--resolutions", default=",".join(RESOLUTIONS), help="comma list of 320x180,960x540")
    ap.add_argument("--counts", default=",".join(str(c) for c in COUNTS), help="comma list of Gaussian counts")
    args = ap.parse_args()
    if args.child:
        child(args)
        return
    resolutions = ["320x180"] if args.quick else args.resolutions.split(",")
    counts = COUNTS[:2] if args.quick else tuple(int(c) for c in args.counts.split(","))
    header = (f"{'image':>8} {'N':>7} {'thr':>3} {'pairs':>9} {'fwd s':>7} {'fwd+bwd s':>9} {'RSS MB':>7} {'+MB':>5} "
              f"{'dense fwd+bwd s (extrap.)':>25} {'speed-up':>8}")
    print(f"8 views; dense reference extrapolated from {args.chunks} x {args.chunk} timed pixels")
    print(header)
    for res in resolutions:
        for n in counts:
            for threads in (int(t) for t in args.thread_list.split(",")):
                fast = spawn(threads, n, res, False, args.reps, args.chunk, args.chunks)
                dense_txt, speed = "-", "-"
                if res == "320x180" and n <= 20_000:
                    dense = spawn(threads, n, res, True, 1, args.chunk, args.chunks)
                    dense_txt = f"{dense['dense_fwdbwd_s']:.1f} (full: {dense['dense_full_memory_gb']:.0f} GB)"
                    speed = f"{dense['dense_fwdbwd_s'] / fast['fwdbwd_s']:.0f}x"
                print(f"{res:>8} {n:>7} {threads:>3} {fast['pairs']:>9} {fast['fwd_s']:>7.3f} {fast['fwdbwd_s']:>9.3f} "
                      f"{fast['peak_rss_mb']:>7.0f} {fast['rss_growth_mb']:>5.0f} {dense_txt:>25} {speed:>8}", flush=True)


if __name__ == "__main__":
    main()
