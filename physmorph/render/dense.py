"""Dense reference rasterizer: every pixel against every Gaussian, plain torch autograd.

Obviously-correct twin of the tile rasterizer (rasterizer.py), same equations and the same
thresholds, used by the tests (forward and backward) and by the benchmark. Memory grows with
pixels x Gaussians: only for tiny scenes (or pixel chunks).
"""

from __future__ import annotations

import torch

from physmorph.settings.render import RenderConfig


def dense_composite(params: torch.Tensor, visible: torch.Tensor, height: int, width: int,
                    cfg: RenderConfig, pixel_chunk: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """params: [V, N, 6] (mean_u, mean_v, A, B, C, z), visible: [V, N] bool.

    Returns alpha [V, H, W] and accumulated depth D = sum_k a_k T_k z_k [V, H, W]; each view's
    Gaussians are composited in increasing z, as the tile rasterizer does.
    """
    n_views = params.shape[0]
    jj, ii = torch.meshgrid(torch.arange(height, device=params.device), torch.arange(width, device=params.device),
                            indexing="ij")
    centres = torch.stack([ii.reshape(-1), jj.reshape(-1)], dim=1).to(params.dtype) + 0.5  # [H*W, 2]
    chunk = pixel_chunk or centres.shape[0]
    alphas, depths = [], []
    for v in range(n_views):
        order = torch.argsort(params[v, :, 5].detach(), stable=True)
        g = params[v, order]  # [N, 6] front to back
        vis = visible[v, order]
        a_parts, d_parts = [], []
        for s in range(0, centres.shape[0], chunk):
            a, d = _dense_pixels(g, vis, centres[s:s + chunk], cfg)
            a_parts.append(a)
            d_parts.append(d)
        alphas.append(torch.cat(a_parts).reshape(height, width))
        depths.append(torch.cat(d_parts).reshape(height, width))
    return torch.stack(alphas), torch.stack(depths)


def _dense_pixels(g: torch.Tensor, vis: torch.Tensor, centres: torch.Tensor, cfg: RenderConfig):
    if g.shape[0] == 0:
        zero = centres[:, 0] * 0.0
        return zero, zero
    du = g[None, :, 0] - centres[:, 0:1]  # [P, N]
    dv = g[None, :, 1] - centres[:, 1:2]
    power = -0.5 * (g[None, :, 2] * du * du + g[None, :, 4] * dv * dv) - g[None, :, 3] * du * dv
    a = torch.clamp(cfg.opacity * torch.exp(power), max=cfg.alpha_max)
    keep = vis[None, :] & (power >= -0.5 * cfg.cutoff_sigma ** 2) & (a >= cfg.alpha_min)
    a = torch.where(keep, a, torch.zeros_like(a))
    one_minus = 1.0 - a
    t_excl = torch.cumprod(torch.cat([torch.ones_like(a[:, :1]), one_minus[:, :-1]], dim=1), dim=1)
    # Early termination: an entry contributes only while the transmittance in front of it is >= t_min.
    a = torch.where(t_excl.detach() >= cfg.transmittance_min, a, torch.zeros_like(a))
    one_minus = 1.0 - a
    t_excl = torch.cumprod(torch.cat([torch.ones_like(a[:, :1]), one_minus[:, :-1]], dim=1), dim=1)
    t_final = t_excl[:, -1] * one_minus[:, -1]
    depth_acc = (a * t_excl * g[None, :, 5]).sum(dim=1)
    return 1.0 - t_final, depth_acc
