"""Differentiable Gaussian splatting renderer and rendering losses (paper sections 3.2, 3.5).

Each surface particle is a 3D Gaussian with mean x_i and covariance Sigma_i = sigma0^2 F_i F_i^T.
Runs on CPU (Taichi tile rasterizer + torch) or CUDA (``RenderConfig(device="cuda")``).
"""

from .api import render_and_grad, render_views, shade, splat
from .config import RenderConfig, RenderResult, RenderTarget
from .dense import dense_composite
from .losses import alpha_mse, match_gradients, render_losses
from .projection import CameraTensors, covariance_from_F, project_gaussians
from .rasterizer import composite

__all__ = [
    "RenderConfig", "RenderTarget", "RenderResult", "render_and_grad", "render_views", "shade", "splat",
    "composite", "dense_composite", "covariance_from_F", "project_gaussians", "CameraTensors",
    "render_losses", "match_gradients", "alpha_mse",
]
