"""Small, obviously-correct dense torch (float64) reference of the MPM substep and the mass loss.

Used by the tests only: it evaluates the same equations as physmorph.mpm.solver with plain tensor
ops (index_add_ P2G, gather G2P, torch.linalg.svd for the rotation) so torch autograd provides
an independent backward. Not meant to be fast.
"""

from __future__ import annotations

import numpy as np
import torch

from ..grid import BOUNDARY_CELLS, blur_weights
from physmorph.settings.mpm import BARRIER_J_LINEAR, MPMConfig

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


def volume_term_torch(J: torch.Tensor, lam: float, volume_law: str = "fixed_corotated") -> torch.Tensor:  # [N]
    """g(J) = dPsi_vol/dJ: lam (J - 1) (fixed_corotated), lam (1 - 1/J) (barrier; its tangent
    below J = BARRIER_J_LINEAR)."""
    if volume_law == "fixed_corotated":
        return lam * (J - 1.0)
    jl = BARRIER_J_LINEAR
    linear = lam * (1.0 - 1.0 / jl) + lam / jl ** 2 * (J - jl)
    return torch.where(J >= jl, lam * (1.0 - 1.0 / torch.clamp(J, min=jl)), linear)


def stress_torch(Fe: torch.Tensor, mu: float, lam: float,  # [N, 3, 3]
                 volume_law: str = "fixed_corotated") -> torch.Tensor:
    """Fixed corotated first Piola-Kirchhoff stress P = 2 mu (Fe - R) + g(J) J Fe^-T, g of volume_law."""
    J = torch.linalg.det(Fe)
    return 2.0 * mu * (Fe - rotation_torch(Fe)) + volume_term_torch(J, lam, volume_law)[:, None, None] * cofactor_torch(Fe)


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


def frame_pressure_torch(x, mass, cfg: MPMConfig) -> torch.Tensor:  # x [N, 3], mass [N] -> [N]
    """K ln(rho_p / (c rho0)) where rho_p = sum_I w_Ip m_I / dx^3 exceeds c rho0, else 0."""
    W, flat, _, _ = _stencil(x, cfg)
    m = grid_mass_torch(x, mass, cfg)
    rho = (W * m[flat]).sum(1) / cfg.dx ** 3
    ratio = rho / (cfg.volume_onset * cfg.density)
    return torch.where(ratio > 1, cfg.volume_stiffness * torch.log(torch.clamp(ratio, min=1.0)), torch.zeros_like(ratio))


def substep_torch(x, v, C, F, dFc, Fp_inv, mass, vol, cfg: MPMConfig, press=None):
    """One MLS-MPM substep (see physmorph.mpm.solver's module docstring); all [N, ...] float64.
    press [N]: the frame's packing pressure (frame_pressure_torch), None = none."""
    R, dt = cfg.grid_res, cfg.dt
    kq = 4.0 / cfg.dx ** 2
    W, flat, dpos, nodes = _stencil(x, cfg)
    Fe = (F + dFc) @ Fp_inv
    tau = stress_torch(Fe, cfg.mu, cfg.lam, cfg.volume_law) @ Fe.transpose(1, 2)
    A = -dt * kq * vol[:, None, None] * tau + mass[:, None, None] * C
    if press is not None:
        A = A + (dt * kq * vol * press)[:, None, None] * torch.eye(3, dtype=x.dtype)
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
    Fn = (torch.eye(3, dtype=x.dtype) + dt * nC) @ (F + dFc if cfg.control_in_F else F)
    nF = (1.0 - cfg.smoothing) * Fn + cfg.smoothing * F
    if cfg.smoothing_mode == "isochoric":
        Jn = torch.linalg.det(Fn)
        if cfg.min_volume_ratio > 0:
            Jn = torch.clamp(Jn, min=cfg.min_volume_ratio)
        nF = (Jn / torch.linalg.det(nF))[:, None, None] ** (1.0 / 3.0) * nF
    return nx, nv, nC, nF


def rollout_torch(x, v, C, F, ctrl, Fp, mass, vol, cfg: MPMConfig):
    """T substeps; ctrl: [Tc, N, 3, 3]. Returns the list of states [(x, v, C, F)] for t = 0..T.
    The packing pressure (volume_stiffness > 0) is measured at x and held, without a gradient."""
    Fp_inv = torch.linalg.inv(Fp)
    press = frame_pressure_torch(x.detach(), mass, cfg) if cfg.volume_stiffness > 0 else None
    states = [(x, v, C, F)]
    for t in range(cfg.substeps):
        slot = t if cfg.control == "per_substep" else 0
        x, v, C, F = substep_torch(x, v, C, F, ctrl[slot], Fp_inv, mass, vol, cfg, press)
        states.append((x, v, C, F))
    return states


def blur_torch(a: torch.Tensor, sigma: float) -> torch.Tensor:
    """a [R, R, R] convolved with the 3D kernel w x w x w of blur_weights, zero outside the grid
    (one dense conv3d: the solver's separable passes must give the same)."""
    w = torch.tensor(blur_weights(sigma), dtype=a.dtype)
    r = (len(w) - 1) // 2
    kernel = w[:, None, None] * w[None, :, None] * w[None, None, :]
    return torch.nn.functional.conv3d(a[None, None], kernel[None, None], padding=r)[0, 0]


def log_convex_torch(m, t, e) -> torch.Tensor:
    """Per node: r^2 with r = log(m + e) - log(t + e) where r <= 1, else the tangent at r = 1,
    1 + 2 (m - m1) / (m1 + e) with m1 = (t + e) exp(1) - e (MPMConfig.mass_loss = "log_convex")."""
    r = torch.log(m + e) - torch.log(t + e)
    m1 = (t + e) * np.e - e
    return torch.where(r <= 1.0, r ** 2, 1.0 + 2.0 * (m - m1) / (m1 + e))


def mass_loss_torch(x, mass, target, cfg: MPMConfig, log_eps: float = 0.0) -> torch.Tensor:
    """squared: sum (m - m*)^2; log: sum (log(m + e) - log(m* + e))^2; sqrt: sum (sqrt(m + e) -
    sqrt(m* + e))^2; log_bounded: log where m <= m*, 4 (sqrt(m + e) - sqrt(m* + e))^2 / (m* + e) above;
    log_convex: log_convex_torch (see MPMConfig), summed
    over the pyramid levels: level l sums blocks of 2^l nodes per axis, with eps x 8^l; plus, where
    mass_loss_blur > 0, mass_loss_blur_weight times the same form on the blurred grids (blur_torch)
    with eps; plus, where overfill_weight > 0, w sum_I max(0, log(m_I + e) - log(max(c density dx^3,
    m*_I) + e))^2."""
    R = cfg.grid_res
    m = grid_mass_torch(x, mass, cfg).reshape(R, R, R)
    t = target.reshape(R, R, R)

    def form(ml, tl, e):
        if cfg.mass_loss == "squared":
            return ((ml - tl) ** 2).sum()
        if cfg.mass_loss == "log_bounded":
            below = (torch.log(ml + e) - torch.log(tl + e)) ** 2
            above = 4.0 / (tl + e) * (torch.sqrt(ml + e) - torch.sqrt(tl + e)) ** 2
            return torch.where(ml <= tl, below, above).sum()
        if cfg.mass_loss == "sqrt":
            return ((torch.sqrt(ml + e) - torch.sqrt(tl + e)) ** 2).sum()
        if cfg.mass_loss == "log_convex":
            return log_convex_torch(ml, tl, e).sum()
        return ((torch.log(ml + e) - torch.log(tl + e)) ** 2).sum()

    total = torch.zeros((), dtype=m.dtype)
    for level in range(cfg.mass_loss_levels):
        b = 2 ** level
        ml = m.reshape(R // b, b, R // b, b, R // b, b).sum(dim=(1, 3, 5))
        tl = t.reshape(R // b, b, R // b, b, R // b, b).sum(dim=(1, 3, 5))
        total = total + form(ml, tl, log_eps * 8.0 ** level)
    if cfg.mass_loss_blur > 0:
        total = total + cfg.mass_loss_blur_weight * form(blur_torch(m, cfg.mass_loss_blur),
                                                         blur_torch(t, cfg.mass_loss_blur), log_eps)
    if cfg.overfill_weight > 0:  # the packing term, on the grid itself (level 0)
        cap = torch.clamp(t, min=cfg.overfill_ratio * cfg.density * cfg.dx ** 3)
        if cfg.mass_loss == "log_convex":
            term = torch.where(m > cap, log_convex_torch(m, cap, log_eps), torch.zeros_like(m))
        else:
            term = torch.clamp(torch.log(m + log_eps) - torch.log(cap + log_eps), min=0.0) ** 2
        total = total + cfg.overfill_weight * term.sum()
    return total


def as_torch(a: np.ndarray, requires_grad: bool = False) -> torch.Tensor:
    return torch.tensor(np.asarray(a, dtype=np.float64), requires_grad=requires_grad)
