"""Rendering losses, adaptive gradient matching and the alpha-MSE metric (paper section 3.5).

All losses are plain torch functions of the rendered alpha [V, H, W] and accumulated depth
D = sum_k a_k T_k z_k [V, H, W]; targets are tensors of the same shape.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from physmorph.settings.render import LOSS_TERMS, RenderConfig

# Smoothing of the soft IoU ratio in pixel units: an empty render against an empty target scores 0.
_IOU_EPS = 1e-6


def expected_depth(alpha: torch.Tensor, depth_acc: torch.Tensor, min_alpha: float) -> torch.Tensor:  # [V, H, W]
    """Expected depth of the visible surface, D / alpha; 0 where alpha <= min_alpha."""
    covered = alpha.detach() > min_alpha
    safe = torch.where(covered, alpha, 1.0)
    return torch.where(covered, depth_acc / safe, 0.0)


def dt_loss(alpha: torch.Tensor, target_sdt: torch.Tensor) -> torch.Tensor:
    """L_DT = mean_p alpha_p * DT(p) / H (paper eq. 5).

    DT is the target's signed distance in pixels (> 0 outside); dividing by the image height H
    makes the loss, and the pull it exerts, independent of the image resolution.
    """
    return (alpha * target_sdt).mean() / alpha.shape[-2]


def soft_iou_loss(alpha: torch.Tensor, target_alpha: torch.Tensor) -> torch.Tensor:
    """L_IoU = mean over views of 1 - (I + eps) / (U + eps), I = sum alpha t, U = sum alpha + t - alpha t."""
    inter = (alpha * target_alpha).sum(dim=(-2, -1))
    union = (alpha + target_alpha - alpha * target_alpha).sum(dim=(-2, -1))
    return (1.0 - (inter + _IOU_EPS) / (union + _IOU_EPS)).mean()


def depth_loss(alpha: torch.Tensor, depth_acc: torch.Tensor, target_depth: torch.Tensor,
               min_alpha: float) -> torch.Tensor:
    """Mean squared error of the expected depth over pixels the target covers (target depth > 0)
    where the render is not transparent (alpha > min_alpha); 0 when there are no such pixels.
    The pixel set is held fixed under differentiation."""
    depth = expected_depth(alpha, depth_acc, min_alpha)
    mask = (target_depth > 0) & (alpha.detach() > min_alpha)
    count = mask.sum().clamp(min=1)
    return torch.where(mask, (depth - target_depth) ** 2, torch.zeros_like(depth)).sum() / count


def render_losses(alpha: torch.Tensor, depth_acc: torch.Tensor, target_alpha: torch.Tensor,
                  target_depth: torch.Tensor, target_sdt: torch.Tensor, cfg: RenderConfig) -> dict[str, torch.Tensor]:
    """The three rendering losses: {"dt", "iou", "depth"} (scalars), differentiable by autograd: the
    reference of LossGradients, which the renderer runs."""
    return {
        "dt": dt_loss(alpha, target_sdt),
        "iou": soft_iou_loss(alpha, target_alpha),
        "depth": depth_loss(alpha, depth_acc, target_depth, cfg.depth_min_alpha),
    }


@dataclass
class LossGradients:
    """render_losses' values and each loss's gradient images of alpha and D, in closed form, one
    view's at a time (paper section 3.5):

        dL_DT/dalpha  = DT / (V H W H)
        dL_IoU/dalpha = (I (1 - t) / U^2 - t / U) / V,  I = sum alpha t + eps, U = sum alpha + t - alpha t + eps (per view)
        dL_depth/dD   = 2 r / (alpha n),  dL_depth/dalpha = -2 r D / (alpha^2 n)  on the depth loss's pixels, 0 elsewhere,
                        r = D / alpha - target depth, n = max(their count, 1)

    Autograd of render_losses (the reference the tests compare) gives the same, but holds its
    graph's pixel buffers over every view until its third backward and the gradients of every
    view after it: at the paper's scale (8 x 960x540) the render's largest transients. Here the
    values take one pass over the views (their sums in float64) and a view's gradients are made
    when the rasterizer's backward of that view asks for them."""

    alpha: torch.Tensor  # [V, H, W] rendered alpha
    depth_acc: torch.Tensor  # [V, H, W] accumulated depth D
    target_alpha: torch.Tensor  # [V, H, W]
    target_depth: torch.Tensor  # [V, H, W]
    target_sdt: torch.Tensor  # [V, H, W]
    min_alpha: float  # RenderConfig.depth_min_alpha
    values: dict[str, float] = field(init=False)
    _iou: list[tuple[float, float]] = field(init=False)  # per view (I, U)
    _depth_pixels: int = field(init=False)  # n

    def __post_init__(self) -> None:
        n_views, height, _ = self.alpha.shape
        sums = {"dt": 0.0, "iou": 0.0, "depth": 0.0}
        self._iou, count = [], 0
        for v in range(n_views):
            a, t = self.alpha[v], self.target_alpha[v]
            sums["dt"] += float((a * self.target_sdt[v]).sum(dtype=torch.float64))
            inter = float((a * t).sum(dtype=torch.float64))
            union = float(a.sum(dtype=torch.float64)) + float(t.sum(dtype=torch.float64)) - inter + _IOU_EPS
            self._iou.append((inter + _IOU_EPS, union))
            sums["iou"] += 1.0 - (inter + _IOU_EPS) / union
            pixels, safe, residual = self._depth_residual(v)
            count += int(pixels.sum())
            sums["depth"] += float((residual * residual).sum(dtype=torch.float64))
        self._depth_pixels = max(count, 1)
        self.values = {"dt": sums["dt"] / self.alpha.numel() / height, "iou": sums["iou"] / n_views,
                       "depth": sums["depth"] / self._depth_pixels}

    def _depth_residual(self, v: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # [H, W] each
        """View v's depth-loss pixels, alpha there (1 elsewhere) and D / alpha - target depth there (0 elsewhere)."""
        a = self.alpha[v]
        pixels = (self.target_depth[v] > 0) & (a > self.min_alpha)
        safe = torch.where(pixels, a, 1.0)
        return pixels, safe, torch.where(pixels, self.depth_acc[v] / safe - self.target_depth[v], 0.0)

    def view(self, v: int) -> tuple[torch.Tensor, torch.Tensor]:  # [L, 1, H, W] twice
        """View v's gradients of each loss (LOSS_TERMS' order) with respect to alpha and to D."""
        n_views, height, width = self.alpha.shape
        a, t = self.alpha[v], self.target_alpha[v]
        g_alpha = torch.zeros((len(LOSS_TERMS), 1, height, width), dtype=a.dtype, device=a.device)
        g_depth = torch.zeros_like(g_alpha)
        dt, iou, depth = (LOSS_TERMS.index(term) for term in ("dt", "iou", "depth"))
        torch.mul(self.target_sdt[v], 1.0 / (self.alpha.numel() * height), out=g_alpha[dt, 0])
        inter, union = self._iou[v]
        torch.mul(t, -(inter / union ** 2 + 1.0 / union) / n_views, out=g_alpha[iou, 0]).add_(inter / union ** 2 / n_views)
        # recomputed, not kept from the values' pass: kept, every view's would be alive at once
        _, safe, residual = self._depth_residual(v)
        torch.div(residual, safe, out=g_depth[depth, 0]).mul_(2.0 / self._depth_pixels)
        torch.mul(g_depth[depth, 0], self.depth_acc[v], out=g_alpha[depth, 0]).div_(safe).neg_()
        return g_alpha, g_depth


def alpha_mse(alpha: torch.Tensor, target_alpha: torch.Tensor) -> torch.Tensor:  # [V]
    """The paper's headline metric: per-view mean over pixels of (alpha - target alpha)^2."""
    return ((alpha - target_alpha) ** 2).mean(dim=(-2, -1))


def matching_weight(grad_dt: torch.Tensor, grad_aux: torch.Tensor, fraction: float) -> float:
    """Adaptive gradient matching (paper section 3.5, after Yu et al. 2020): the weight w with
    ||w grad_aux|| = fraction ||grad_dt||; 0 when either gradient is zero or fraction is 0."""
    norm_aux = float(torch.linalg.vector_norm(grad_aux))
    norm_dt = float(torch.linalg.vector_norm(grad_dt))
    if fraction == 0.0 or norm_aux == 0.0 or not torch.isfinite(torch.tensor(norm_aux)):
        return 0.0
    return fraction * norm_dt / norm_aux


def match_gradients(grads: dict[str, torch.Tensor], cfg: RenderConfig) -> tuple[torch.Tensor, dict[str, float]]:
    """Combine per-loss gradients of one variable (F or x):

        g = g_DT + w_IoU g_IoU + w_depth g_depth,  w_aux = fraction_aux ||g_DT|| / ||g_aux||

    so each auxiliary term's norm is its configured fraction of the DT gradient's norm.
    Returns the combined gradient and the weights."""
    weights = {
        "dt": 1.0,
        "iou": matching_weight(grads["dt"], grads["iou"], cfg.iou_fraction),
        "depth": matching_weight(grads["dt"], grads["depth"], cfg.depth_fraction),
    }
    total = grads["dt"] + weights["iou"] * grads["iou"] + weights["depth"] * grads["depth"]
    return total, weights
