"""Public entry points: render_and_grad (losses + dL/dF), render_views and coverage_behind (metrics),
shade (figures).

Pipeline (paper sections 3.2 and 3.5): F, x --> Sigma = sigma0^2 F F^T --> EWA projection -->
screen-space params [V*N, 6] --(Taichi tile rasterizer, hand-written backward)--> alpha, D -->
losses and their gradients of alpha and D (closed form: losses.LossGradients). The projection
and its reverse are Taichi kernels (projection_kernels, no autograd graph); the rasterizer's
backward and the projection's reverse run once per view with one channel per loss, which is what
adaptive gradient matching needs (each loss's gradient norm separately).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from physmorph.base.cameras import Cameras
from physmorph.base.taichi_runtime import resolve_device

from physmorph.settings.render import LOSS_TERMS, RenderConfig
from .containers import RenderResult, RenderTarget
from .losses import LossGradients, alpha_mse, expected_depth, match_gradients
from .projection import CameraTensors, ProjectedGaussians
from .projection_kernels import ProjectionReverse, project_forward
from .rasterizer import composite_backward, composite_forward
from .tiles import TileBins, bin_gaussians

def torch_device(cfg: RenderConfig) -> torch.device:
    return torch.device(resolve_device(cfg.device))


def torch_dtype(cfg: RenderConfig) -> torch.dtype:
    return torch.float64 if cfg.dtype == "float64" else torch.float32


def _check_inputs(x: np.ndarray, F: np.ndarray, sigma0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    x = np.array(x, dtype=np.float64)  # copies: callers may pass read-only or broadcast views
    F = np.array(F, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"x must be [N, 3], got {x.shape}")
    if F.shape != (x.shape[0], 3, 3):
        raise ValueError(f"F must be [N, 3, 3] with N={x.shape[0]}, got {F.shape}")
    s = np.asarray(sigma0, dtype=np.float64)
    if s.ndim not in (0, 1) or (s.ndim == 1 and s.shape[0] != x.shape[0]):
        raise ValueError(f"sigma0 must be a scalar or [N], got shape {s.shape}")
    for name, a in (("x", x), ("F", F), ("sigma0", s)):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"render input {name} contains NaN or Inf")
    if np.any(s <= 0):
        raise ValueError("sigma0 must be > 0")
    return x, F, s


@dataclass
class Splats:
    """One forward pass: the screen-space params and their tile bins."""

    projected: ProjectedGaussians
    params: torch.Tensor  # [V*N, 6], no graph (the reverse is reverse_by_view)
    bins: TileBins


def splat(x: torch.Tensor, F: torch.Tensor, sigma0: torch.Tensor, cams: CameraTensors, cfg: RenderConfig) -> Splats:
    """x: [N, 3], F: [N, 3, 3] tensors; sigma0 scalar or [N] tensor. The projection is the Taichi
    kernel's (projection.project_gaussians, differentiable by autograd, is its reference)."""
    projected = ProjectedGaussians(*project_forward(x, F, sigma0, cams, cfg))
    params = projected.params.reshape(-1, 6)
    bins = bin_gaussians(projected.params[..., :2].detach(), projected.half_extent, projected.params[..., 5].detach(),
                         projected.visible, cams.width, cams.height, cfg.tile_size)
    return Splats(projected, params, bins)


def reverse_by_view(x: torch.Tensor,  # [N, 3]
                    F: torch.Tensor,  # [N, 3, 3]
                    sigma0: torch.Tensor,  # scalar or [N]
                    cams: CameraTensors, sp: Splats,
                    t_final: torch.Tensor,  # [V, H, W]
                    last: torch.Tensor,  # [V, H, W]
                    image_gradients: Callable[[int], tuple[torch.Tensor, torch.Tensor]],
                    n_losses: int, cfg: RenderConfig, want_grad_x: bool) -> tuple[torch.Tensor | None, torch.Tensor]:
    """The rasterizer's backward and the projection's reverse, all losses at once, one view at a
    time: dL_l/dx [L, N, 3] (or None) and dL_l/dF [L, N, 3, 3]. ``image_gradients(v)``: view v's
    gradients of the L losses with respect to alpha and to the accumulated depth ([L, 1, H, W]
    each), asked for when that view's backward runs. The params' gradients of one view ([L, N, 6])
    and its gradient images exist at a time, not all views' (at the paper's scale 35 + 12 MB, not
    276 + 100); the numbers are those of both passes over all views at once."""
    n = x.shape[0]
    reverse = ProjectionReverse(x, F, sigma0, n_losses, want_grad_x)
    for v in range(cams.count):
        bins, first = sp.bins.view(v, n)
        g_alpha, g_depth = image_gradients(v)
        g_params = composite_backward(sp.params[v * n:(v + 1) * n], bins, t_final[v:v + 1], last[v:v + 1] - first,
                                      g_alpha, g_depth, cfg)
        del g_alpha, g_depth
        reverse.add(cams.view(v), cfg, g_params[:, None])
        del g_params
    return reverse.result()


def _to_tensors(x, F, s, cameras: Cameras, cfg: RenderConfig):
    dev, dt = torch_device(cfg), torch_dtype(cfg)
    return (torch.as_tensor(x, dtype=dt, device=dev), torch.as_tensor(F, dtype=dt, device=dev),
            torch.as_tensor(s, dtype=dt, device=dev), CameraTensors.from_cameras(cameras, dt, dev))


def _composited(x: np.ndarray, F: np.ndarray, sigma0, cameras: Cameras, cfg: RenderConfig,
                behind: np.ndarray | None = None) -> tuple[torch.Tensor, torch.Tensor]:  # [V, H, W] twice
    """Forward only: the final transmittance and the accumulated depth D of the particles
    (composited behind the transmittance ``behind`` [V, H, W] where given)."""
    x, F, s = _check_inputs(x, F, sigma0)
    xt, Ft, st, cams = _to_tensors(x, F, s, cameras, cfg)
    with torch.no_grad():
        sp = splat(xt, Ft, st, cams, cfg)
        t_final, depth_acc, _ = composite_forward(sp.params, sp.bins, cams.count, cams.height, cams.width, cfg,
                                                  behind=None if behind is None else torch.as_tensor(behind))
    return t_final, depth_acc


def render_views(x: np.ndarray, F: np.ndarray, sigma0, cameras: Cameras,
                 cfg: RenderConfig = RenderConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Forward only. x: [N, 3], F: [N, 3, 3], sigma0: scalar or [N].
    Returns alpha [V, H, W] and expected depth [V, H, W] (0 where alpha <= alpha_min)."""
    t_final, depth_acc = _composited(x, F, sigma0, cameras, cfg)
    with torch.no_grad():
        alpha = 1.0 - t_final
        depth = expected_depth(alpha, depth_acc, cfg.alpha_min)
    return alpha.double().cpu().numpy(), depth.double().cpu().numpy()


def coverage_behind(x: np.ndarray,  # [N, 3]
                    F: np.ndarray,  # [N, 3, 3]
                    sigma0, cameras: Cameras,
                    transmittance: np.ndarray,  # [V, H, W] what Gaussians in front of these left
                    cfg: RenderConfig = RenderConfig()) -> np.ndarray:  # [V, H, W]
    """Forward only: the alpha of everything, these particles composited behind ``transmittance``,
    1 - T T_these to within the compositing's early stop (a pixel already opaque in front costs
    nothing: the metrics' particles outside the surface mask, behind the loss's render of it)."""
    t_final, _ = _composited(x, F, sigma0, cameras, cfg, behind=transmittance)
    return (1.0 - t_final).double().cpu().numpy()


def render_and_grad(x: np.ndarray, F: np.ndarray, sigma0, cameras: Cameras, target: RenderTarget,
                    cfg: RenderConfig = RenderConfig(), want_grad_x: bool = False) -> RenderResult:
    """Render the (surface-masked) particles, evaluate the losses and dL_render/dF (and dL/dx).

    x: [N, 3], F: [N, 3, 3] float64; sigma0 scalar or [N]; Sigma_i = sigma0^2 F_i F_i^T.
    The returned gradient is g = g_DT + w_IoU g_IoU + w_depth g_depth with the adaptive
    weights of :func:`physmorph.render.losses.match_gradients`, computed separately for F and
    for x; losses["total"] = dt + w_IoU iou + w_depth depth with the F weights.
    """
    x, F, s = _check_inputs(x, F, sigma0)
    n_views, height, width = cameras.count, cameras.height, cameras.width
    if target.alpha.shape != (n_views, height, width):
        raise ValueError(f"target images are {target.alpha.shape}, cameras give {(n_views, height, width)}")
    xt, Ft, st, cams = _to_tensors(x, F, s, cameras, cfg)
    dev, dt = xt.device, xt.dtype
    t_alpha, t_depth, t_sdt = (torch.as_tensor(np.asarray(a), dtype=dt, device=dev)
                               for a in (target.alpha, target.depth, target.sdt))

    # the projection keeps no autograd graph: its reverse is reverse_by_view's
    with torch.no_grad():
        sp = splat(xt, Ft, st, cams, cfg)
    t_final, depth_acc, last = composite_forward(sp.params, sp.bins, n_views, height, width, cfg)
    alpha = 1.0 - t_final
    losses = LossGradients(alpha, depth_acc, t_alpha, t_depth, t_sdt, cfg.depth_min_alpha)
    loss_values = dict(losses.values)
    # one rasterizer backward a view, with a channel per loss
    g_x, g_F = reverse_by_view(xt, Ft, st, cams, sp, t_final, last, losses.view, len(LOSS_TERMS), cfg, want_grad_x)
    del losses, sp
    per_loss_F = {name: g_F[c] for c, name in enumerate(LOSS_TERMS)}
    per_loss_x = {name: g_x[c] for c, name in enumerate(LOSS_TERMS)} if want_grad_x else {}
    grad_F, weights = match_gradients(per_loss_F, cfg)
    grad_x = None
    all_weights = {f"F_{k}": v for k, v in weights.items()}
    if want_grad_x:
        grad_x_t, weights_x = match_gradients(per_loss_x, cfg)
        grad_x = grad_x_t.double().cpu().numpy()
        all_weights.update({f"x_{k}": v for k, v in weights_x.items()})

    with torch.no_grad():
        mse = alpha_mse(alpha, t_alpha)
        depth = expected_depth(alpha, depth_acc, cfg.alpha_min)
    loss_values["total"] = loss_values["dt"] + weights["iou"] * loss_values["iou"] + weights["depth"] * loss_values["depth"]
    return RenderResult(
        alpha=alpha.double().cpu().numpy(),
        depth=depth.double().cpu().numpy(),
        losses=loss_values,
        alpha_mse_per_view=mse.double().cpu().numpy(),
        alpha_mse=float(mse.mean()),
        grad_F=grad_F.double().cpu().numpy(),
        grad_x=grad_x,
        weights=all_weights,
    )


def shade(x: np.ndarray, F: np.ndarray, sigma0, cameras: Cameras, view: int,
          cfg: RenderConfig = RenderConfig(), color=(0.80, 0.62, 0.45), background=(1.0, 1.0, 1.0)) -> np.ndarray:
    """Phong-shaded image [H, W, 3] in [0, 1] of one view, forward only (figures).

    Normals come from the rendered expected-depth map (back-projected to camera space, cross
    product of its image-space derivatives); a head light slightly above-left of the camera,
    ambient 0.25, diffuse 0.65, specular 0.25 with exponent 32; composited over the background
    with the rendered alpha.
    """
    cam = cameras.subset([view])
    alpha, depth = render_views(x, F, sigma0, cam, cfg)
    alpha, depth = alpha[0], depth[0]
    fx, fy, cx, cy = cam.intrinsics[0]
    jj, ii = np.meshgrid(np.arange(cam.height) + 0.5, np.arange(cam.width) + 0.5, indexing="ij")
    valid = alpha > 0.5
    # Fill uncovered pixels with the mean covered depth so derivatives at the rim stay bounded.
    z = np.where(valid, depth, depth[valid].mean() if valid.any() else 1.0)
    p = np.stack([(ii - cx) / fx * z, (jj - cy) / fy * z, z], axis=-1)  # camera-space points [H, W, 3]
    du = np.gradient(p, axis=1)
    dv = np.gradient(p, axis=0)
    n = np.cross(du, dv)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    view_dir = -p / np.maximum(np.linalg.norm(p, axis=-1, keepdims=True), 1e-12)  # towards the camera
    n = np.where((n * view_dir).sum(-1, keepdims=True) < 0, -n, n)
    light = np.array([-0.4, -0.5, -1.0])
    light /= np.linalg.norm(light)
    diffuse = np.clip(n @ light, 0.0, 1.0)
    half = light[None, None, :] + view_dir
    half /= np.maximum(np.linalg.norm(half, axis=-1, keepdims=True), 1e-12)
    specular = np.clip((n * half).sum(-1), 0.0, 1.0) ** 32
    base = np.asarray(color, dtype=np.float64)
    rgb = (0.25 + 0.65 * diffuse)[..., None] * base + 0.25 * specular[..., None]
    rgb = np.clip(rgb, 0.0, 1.0)
    a = alpha[..., None]
    return a * rgb + (1.0 - a) * np.asarray(background, dtype=np.float64)
