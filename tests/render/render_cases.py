"""Scenes, cameras and targets the render tests share."""

from __future__ import annotations

import numpy as np
import torch

from physmorph.base.cameras import Cameras, look_at, ring_cameras
from physmorph.render.containers import RenderTarget
from physmorph.render.projection import CameraTensors, covariance_from_F, project_gaussians

# Smooth settings for finite differences: no cutoffs or thresholds that switch terms on and off.
SMOOTH = dict(cutoff_sigma=12.0, alpha_min=0.0, transmittance_min=0.0, dtype="float64", tile_size=8)


def random_scene(n: int, seed: int, spread: float = 1.5, aniso: float = 0.3):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-spread, spread, size=(n, 3))
    F = np.eye(3) + aniso * rng.normal(size=(n, 3, 3))
    return x, F


def small_cameras(views: int = 2, width: int = 24, height: int = 20) -> Cameras:
    return ring_cameras(views, width=width, height=height, distance=10.0, fov_y_deg=30.0)


def disk_target(cams: Cameras, radius_frac: float = 0.3, depth: float = 10.0) -> RenderTarget:
    """A disk silhouette at the image centre in every view, with its analytic signed distance."""
    h, w = cams.height, cams.width
    jj, ii = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    r = np.hypot(ii - 0.5 * w, jj - 0.5 * h)
    sdt = r - radius_frac * h
    alpha = np.clip(0.5 - sdt, 0.0, 1.0)
    shape = (cams.count, h, w)
    return RenderTarget(alpha=np.broadcast_to(alpha, shape).copy(),
                        depth=np.broadcast_to(np.where(alpha > 0, depth, 0.0), shape).copy(),
                        sdt=np.broadcast_to(sdt, shape).copy())


def torch_scene(x, F, sigma0, cams, cfg, requires_grad=True):
    dt = torch.float64 if cfg.dtype == "float64" else torch.float32
    xt = torch.tensor(x, dtype=dt, requires_grad=requires_grad)
    Ft = torch.tensor(F, dtype=dt, requires_grad=requires_grad)
    ct = CameraTensors.from_cameras(cams, dt, "cpu")
    proj = project_gaussians(xt, covariance_from_F(Ft, sigma0), ct, cfg)
    return xt, Ft, ct, proj


def front_camera(width: int, height: int, f: float, distance: float) -> Cameras:
    w2c = look_at(np.array([0.0, 0.0, distance]), np.zeros(3), np.array([0.0, 1.0, 0.0]))
    return Cameras(w2c[None], np.array([[f, f, 0.5 * width, 0.5 * height]]), width, height)


def fibonacci_sphere(n: int, radius: float) -> np.ndarray:
    k = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * k / n)
    theta = np.pi * (1 + 5 ** 0.5) * k
    return radius * np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1)
