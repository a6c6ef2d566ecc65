"""The plasticity's and the mask's per-frame work on a device against their CPU reference paths.

:func:`device_deviations` runs each piece on a torch device and its reference on the CPU, and
:func:`check_deviations` holds them to these tolerances:

- nearest target points (physmorph.plasticity.nearest against the KD tree): the same indices, distances to
  1e-12 (coordinates of order 10). The search is exhaustive in float64; its matrix-product form
  rounds the squared distances by ~1e-16 of the coordinates' squared extent, so only a near-tie
  that close could pick another point, and the winner's distance is computed directly.
- the surface mask (search_device against the KD trees): identical. Its distances are those above,
  so a particle could flip only within ~1e-12 of a band's edge; the jittered test cloud has none.
- the plasticity step with its own nearest-target search: the same Fp, to 1e-12.
- the transport plan's destinations (torch on the device against torch on the CPU, both float32):
  1e-5 of a cell. The same operations run on both; they differ by float32 rounding alone (another
  summation order, another exp), whose whole effect on this problem is measured here as the float32
  plan's distance from the float64 one (~1.4e-6 of a cell) and checked to be at most a quarter of
  the tolerance. On the CPU device the plan is the CPU path itself: equal bit for bit.
- the neighbourhoods (physmorph.plasticity.neighbourhood's Taichi kernels, on the Taichi runtime's arch:
  CUDA in the GPU check) against the KD tree and NumPy references: the same neighbour sets, the
  smoothed displacements to 1e-12 and the Jacobians to 1e-10 of their largest entry (float64; a
  GPU may fuse multiply-adds).

Here on the CPU device (CI); tests/test_gpu.py runs the same on CUDA (`make gpu-check`), skipping,
saying why, where no CUDA device is usable.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from physmorph.base.grid import Grid, splat_mass
from physmorph.plasticity.nearest import DevicePoints
from physmorph.plasticity.neighbourhood import displacement_jacobian_pairs, k_nearest, smooth_displacement
from physmorph.settings.plasticity import PlasticityConfig
from physmorph.plasticity.step import chamfer_plasticity_step, displacement_jacobian, knn_smooth, nearest_neighbours
from physmorph.settings.surface import SurfaceMaskConfig
from physmorph.morph.surface_mask import update_surface_mask
from physmorph.plasticity.transport import destinations_in_grid_mass, transport_destinations

TOLERANCES = {"nearest_index": 0, "nearest_distance": 1e-12, "mask": 0, "plasticity_Fp": 1e-12,
              "transport_cells": 1e-5, "neighbour_sets": 0, "smoothing": 1e-12, "jacobian": 1e-10}


def _sphere(rng, n: int, radius: float) -> np.ndarray:  # -> [n, 3]
    t = rng.standard_normal((n, 3))
    return radius * t / np.linalg.norm(t, axis=1, keepdims=True)


def _ball(rng, n: int, radius: float) -> np.ndarray:  # -> [n, 3] uniform in the ball
    return _sphere(rng, n, radius) * rng.uniform(0, 1, (n, 1)) ** (1 / 3)


def _searches(device: str, rng) -> dict:
    """Nearest target points, the surface mask and the plasticity step: device against KD tree."""
    out = {}
    target = _sphere(rng, 3000, 4.0) + rng.normal(0, 0.05, (3000, 3))  # a noisy shell
    x = np.concatenate([_ball(rng, 4000, 7.0), rng.uniform(-15, 15, (500, 3)), target[:7]])  # inside, far, on it
    d_ref, i_ref = cKDTree(target).query(x, k=1)
    d, i = DevicePoints(target, device).query(x, block_entries=50_000)  # blocks smaller than the problem
    out["nearest_index"] = int((i != i_ref).sum())
    out["nearest_distance"] = float(np.abs(d - d_ref).max())
    # the mask: a ball of particles, its shell and the particles near a target sphere inside it
    p = _ball(rng, 6000, 6.0)
    vol = np.full(len(p), 4.0 / 3.0 * np.pi * 6.0 ** 3 / len(p))
    tree = cKDTree(_sphere(rng, 2000, 2.0))
    cfg = SurfaceMaskConfig(voxels=48)
    ref = update_surface_mask(p, vol, tree, cfg, -16.0, 16.0)
    got = update_surface_mask(p, vol, tree, cfg, -16.0, 16.0, search_device=device)
    assert 0.1 < ref.mean() < 0.9, "the test mask must keep some particles and drop others"
    out["mask"] = int((got != ref).sum())
    # the plasticity step finding its own nearest target points
    pcfg = PlasticityConfig(eta=0.3, k_neighbors=16, smooth_iters=2, correspondence="nearest")
    xs = _ball(rng, 1500, 3.0)
    Fp = np.tile(np.eye(3), (len(xs), 1, 1))
    a = chamfer_plasticity_step(xs, Fp, target, pcfg)
    b = chamfer_plasticity_step(xs, Fp, target, pcfg, search_device=device)
    out["plasticity_Fp"] = float(np.abs(a.Fp - b.Fp).max())
    return out


def _transport(device: str, rng) -> dict:
    """The plan's destinations on the device against the CPU (and the CPU's float32 rounding)."""
    grid = Grid(16)
    src = rng.uniform(-3, 3, size=(500, 3)) + [-4.0, 0.0, 0.0]
    tgt = rng.uniform(-2, 2, size=(500, 3)) * [2.0, 1.0, 1.0] + [5.0, 0.0, 0.0]
    gm = splat_mass(tgt, np.ones(500), grid)
    T_cpu = destinations_in_grid_mass(src, np.ones(500), gm, grid, device="cpu")
    T_dev = destinations_in_grid_mass(src, np.ones(500), gm, grid, device=device)
    a = splat_mass(src, np.ones(500), grid)
    y, z = grid.lo + grid.dx * np.argwhere(a > 0), grid.lo + grid.dx * np.argwhere(gm > 0)
    plan = {dt: transport_destinations(y, a[a > 0], z, gm[gm > 0], blur=grid.dx, dtype=dt)
            for dt in (torch.float32, torch.float64)}
    return {"transport_cells": float(np.abs(T_dev - T_cpu).max() / grid.dx),
            "transport_equal": bool(np.array_equal(T_dev, T_cpu)),
            "transport_f32_rounding_cells": float(np.abs(plan[torch.float32] - plan[torch.float64]).max() / grid.dx)}


def _neighbourhoods(rng) -> dict:
    """The Taichi neighbourhood kernels (on the runtime's arch) against their references."""
    g = np.stack(np.meshgrid(*[np.arange(12)] * 3, indexing="ij"), -1).reshape(-1, 3).astype(float)
    x = 0.5 * (g + rng.uniform(-0.3, 0.3, g.shape))
    pool = np.flatnonzero((g % 2 == 0).all(axis=1))
    ref_nb, _ = nearest_neighbours(x, pool, 32)
    nb, _ = k_nearest(x, pool, 32, with_r2=False)
    d = np.sin(x) + 0.1 * x ** 2
    full, _ = nearest_neighbours(x, np.arange(len(x)), 16)
    J_ref = displacement_jacobian(x, d, full)
    J = displacement_jacobian_pairs(x, d, full, None)
    return {"neighbour_sets": int((np.sort(nb, axis=1) != np.sort(ref_nb, axis=1)).any(axis=1).sum()),
            "smoothing": float(np.abs(smooth_displacement(d, full, 3) - knn_smooth(d, full, 3)).max()),
            "jacobian": float(np.abs(J - J_ref).max() / np.abs(J_ref).max())}


def device_deviations(device: str) -> dict:
    """Every comparison of the module docstring run with the torch ``device`` ("cpu" or "cuda")."""
    rng = np.random.default_rng(7)
    return {"device": device, **_searches(device, rng), **_transport(device, rng), **_neighbourhoods(rng)}


def check_deviations(dev: dict) -> None:
    """The module docstring's tolerances."""
    for key, tol in TOLERANCES.items():
        assert dev[key] <= tol, f"{key} on {dev['device']}: {dev[key]:.3g} > {tol:.3g} ({dev})"
    assert dev["transport_f32_rounding_cells"] <= TOLERANCES["transport_cells"] / 4, dev
    if dev["device"] == "cpu":  # the transport's device path on the CPU is the CPU path
        assert dev["transport_equal"], dev


def test_device_paths_on_the_cpu_equal_the_cpu_references():
    check_deviations(device_deviations("cpu"))
