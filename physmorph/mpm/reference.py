"""Small, obviously-correct dense torch (float64) reference of the MPM substep and the mass loss.

Used by the tests only: it evaluates the same equations as physmorph.mpm.solver with plain tensor
ops (index_add_ P2G, gather G2P, torch.linalg.svd for the rotation) so torch autograd provides
an independent backward. Not meant to be fast.
"""

from __future__ import annotations

import numpy as np
import torch

from physmorph.base.grid import BOUNDARY_CELLS, blur_weights
from physmorph.settings.mpm import MPMConfig

_OFFSETS = torch.tensor([[i, j, k] for i in range(3) for j in range(3) for k in range(3)],
                        dtype=torch.int64)  # [27, 3]


def rotation_torch(F: torch.Tensor) -> torch.Tensor:  # [N, 3, 3] -> [N, 3, 3]
    """R of F = R S with det R = +1 (reflection moved into the smallest singular value)."""
    U, S, Vh = torch.linalg.svd(F)
    d = torch.sign(torch.linalg.det(U @ Vh))
    fix = torch.ones_like(S)
    fix = torch.stack([fix[:, 0], fix[:, 1], d], dim=1)
    return (U * fix[:, None, :]) @ Vh


def cofactor_torch(F: torch.Tensor) -> torch.Tensor:  # [N, 3, 3]
    """cof(F) = J F^-T via column cross products."""
    f0, f1, f2 = F[:, :, 0], F[:, :, 1], F[:, :, 2]
    return torch.stack([torch.cross(f1, f2, dim=1), torch.cross(f2, f0, dim=1),
                        torch.cross(f0, f1, dim=1)], dim=2)


def stress_torch(Fe: torch.Tensor, mu: float, lam: float) -> torch.Tensor:  # [N, 3, 3] -> [N, 3, 3]
    """Fixed corotated first Piola-Kirchhoff stress P = 2 mu (Fe - R) + lam (J - 1) J Fe^-T."""
    J = torch.linalg.det(Fe)
    return 2.0 * mu * (Fe - rotation_torch(Fe)) + (lam * (J - 1.0))[:, None, None] * cofactor_torch(Fe)


def _stencil(x: torch.Tensor, cfg: MPMConfig):
    xg = (x - cfg.domain_lo) / cfg.dx
    base = torch.floor(xg - 0.5).to(torch.int64)  # [N, 3]
    fx = xg - base
    w = torch.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2], dim=1)
    # w: [N, 3 (offset), 3 (axis)] -> weights of the 27 nodes [N, 27]
    W = w[:, _OFFSETS[:, 0], 0] * w[:, _OFFSETS[:, 1], 1] * w[:, _OFFSETS[:, 2], 2]
    nodes = base[:, None, :] + _OFFSETS[None]  # [N, 27, 3]
    dpos = (_OFFSETS[None].to(x.dtype) - fx[:, None, :]) * cfg.dx  # [N, 27, 3]
    R = cfg.grid_res
    flat = (nodes[..., 0] * R + nodes[..., 1]) * R + nodes[..., 2]  # [N, 27]
    return W, flat, dpos, nodes


def grid_mass_torch(x: torch.Tensor, mass: torch.Tensor, cfg: MPMConfig) -> torch.Tensor:  # [R^3]
    W, flat, _, _ = _stencil(x, cfg)
    out = torch.zeros(cfg.grid_res ** 3, dtype=x.dtype)
    return out.index_add(0, flat.reshape(-1), (W * mass[:, None]).reshape(-1))


def substep_torch(x, v, C, F, dFc, Fp_inv, mass, vol, cfg: MPMConfig):
    """One MLS-MPM substep (see physmorph.mpm.solver's module docstring); all [N, ...] float64."""
    R, dt = cfg.grid_res, cfg.dt
    kq = 4.0 / cfg.dx ** 2
    W, flat, dpos, nodes = _stencil(x, cfg)
    Fe = (F + dFc) @ Fp_inv
    tau = stress_torch(Fe, cfg.mu, cfg.lam) @ Fe.transpose(1, 2)
    A = -dt * kq * vol[:, None, None] * tau + mass[:, None, None] * C
    mom = (mass * (1.0 - dt * cfg.drag))[:, None] * v
    contrib = W[..., None] * (mom[:, None, :] + torch.einsum("pab,pnb->pna", A, dpos))  # [N,27,3]
    mv = torch.zeros(R ** 3, 3, dtype=x.dtype).index_add(0, flat.reshape(-1), contrib.reshape(-1, 3))
    m = torch.zeros(R ** 3, dtype=x.dtype).index_add(0, flat.reshape(-1), (W * mass[:, None]).reshape(-1))
    occupied = m > 0
    vg = torch.where(occupied[:, None], mv / torch.where(occupied, m, torch.ones_like(m))[:, None],
                     torch.zeros_like(mv))
    idx = torch.stack(torch.meshgrid(*(torch.arange(R),) * 3, indexing="ij"), -1).reshape(-1, 3)
    low = (idx < BOUNDARY_CELLS) & (vg < 0)
    high = (idx >= R - BOUNDARY_CELLS) & (vg > 0)
    vg = torch.where(low | high, torch.zeros_like(vg), vg)
    gv = vg[flat]  # [N, 27, 3]
    nv = (W[..., None] * gv).sum(1)
    nC = kq * torch.einsum("pn,pna,pnb->pab", W, gv, dpos)
    x_min = cfg.domain_lo + cfg.dx
    x_max = cfg.domain_lo + (R - 2.0) * cfg.dx
    nx = torch.clamp(x + dt * nv, x_min, x_max)
    Fn = (torch.eye(3, dtype=x.dtype) + dt * nC) @ F
    nF = (1.0 - cfg.smoothing) * Fn + cfg.smoothing * F
    if cfg.smoothing_mode == "isochoric":
        Jn = torch.linalg.det(Fn)
        if cfg.min_volume_ratio > 0:
            Jn = torch.clamp(Jn, min=cfg.min_volume_ratio)
        nF = (Jn / torch.linalg.det(nF))[:, None, None] ** (1.0 / 3.0) * nF
    return nx, nv, nC, nF


def rollout_torch(x, v, C, F, ctrl, Fp, mass, vol, cfg: MPMConfig):
    """T substeps; ctrl: [T, N, 3, 3]. Returns the list of states [(x, v, C, F)] for t = 0..T."""
    Fp_inv = torch.linalg.inv(Fp)
    states = [(x, v, C, F)]
    for t in range(cfg.substeps):
        x, v, C, F = substep_torch(x, v, C, F, ctrl[t], Fp_inv, mass, vol, cfg)
        states.append((x, v, C, F))
    return states


def blur_torch(a: torch.Tensor, sigma: float) -> torch.Tensor:
    """a [R, R, R] convolved with the 3D kernel w x w x w of blur_weights, zero outside the grid
    (one dense conv3d: the solver's separable passes must give the same)."""
    w = torch.tensor(blur_weights(sigma), dtype=a.dtype)
    r = (len(w) - 1) // 2
    kernel = w[:, None, None] * w[None, :, None] * w[None, None, :]
    return torch.nn.functional.conv3d(a[None, None], kernel[None, None], padding=r)[0, 0]


def mass_loss_torch(x, mass, target, cfg: MPMConfig, log_eps: float = 0.0) -> torch.Tensor:
    """squared: sum (m - m*)^2; log: sum (log(m + e) - log(m* + e))^2; plus, where
    mass_loss_blur > 0, mass_loss_blur_weight times the same form on the blurred grids (blur_torch)
    with eps; plus, where overfill_weight > 0, w sum_I max(0, log(m_I + e) - log(max(c density dx^3,
    m*_I) + e))^2."""
    R = cfg.grid_res
    m = grid_mass_torch(x, mass, cfg).reshape(R, R, R)
    t = target.reshape(R, R, R)

    def form(ml, tl, e):
        if cfg.mass_loss == "squared":
            return ((ml - tl) ** 2).sum()
        return ((torch.log(ml + e) - torch.log(tl + e)) ** 2).sum()

    total = form(m, t, log_eps)
    if cfg.mass_loss_blur > 0:
        total = total + cfg.mass_loss_blur_weight * form(blur_torch(m, cfg.mass_loss_blur),
                                                         blur_torch(t, cfg.mass_loss_blur), log_eps)
    if cfg.overfill_weight > 0:  # the packing term
        cap = torch.clamp(t, min=cfg.overfill_ratio * cfg.density * cfg.dx ** 3)
        term = torch.clamp(torch.log(m + log_eps) - torch.log(cap + log_eps), min=0.0) ** 2
        total = total + cfg.overfill_weight * term.sum()
    return total


def as_torch(a: np.ndarray, requires_grad: bool = False) -> torch.Tensor:
    return torch.tensor(np.asarray(a, dtype=np.float64), requires_grad=requires_grad)
