"""Per-Gaussian preprocessing in torch: F -> Sigma, EWA projection, 2D conic, and their reverse.

Paper section 3.2 (MPM-Gaussian duality) and the EWA splatting of 3DGS (Zwicker et al. 2002,
Kerbl et al. 2023). Everything here is O(V N). The forward is differentiable by torch autograd
(the reference); render_and_grad uses the hand-written reverse (project_gaussians_backward,
covariance_from_F_backward), which takes every loss's gradient in one pass and keeps no graph.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from physmorph.cameras import Cameras

from .config import RenderConfig

# How far off-screen (as a fraction of the image size) the EWA Jacobian is still evaluated at the
# true position; beyond it the Jacobian uses the clamped direction, as 3DGS does (1.3 x fov),
# so Gaussians far outside the frustum cannot produce huge 2D covariances.
_JACOBIAN_MARGIN = 0.15


def covariance_from_F(F: torch.Tensor, sigma0: float | torch.Tensor) -> torch.Tensor:  # [N, 3, 3]
    """Sigma_i = F_i Sigma0 F_i^T with Sigma0 = sigma0^2 I (paper eq. 1, section 3.2).

    F: [N, 3, 3]. sigma0: scalar or [N] per-Gaussian rest size.
    """
    s = torch.as_tensor(sigma0, dtype=F.dtype, device=F.device)
    s2 = (s * s).reshape(-1, 1, 1) if s.ndim > 0 else s * s
    return s2 * (F @ F.transpose(-1, -2))


@dataclass
class CameraTensors:
    """Cameras as torch tensors on the renderer's device and dtype."""

    rotation: torch.Tensor  # [V, 3, 3]
    translation: torch.Tensor  # [V, 3]
    intrinsics: torch.Tensor  # [V, 4] fx, fy, cx, cy
    width: int
    height: int
    near: float

    @classmethod
    def from_cameras(cls, cameras: Cameras, dtype: torch.dtype, device: torch.device | str) -> "CameraTensors":
        as_t = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=dtype, device=device)  # noqa: E731
        return cls(as_t(cameras.rotation), as_t(cameras.translation), as_t(cameras.intrinsics),
                   int(cameras.width), int(cameras.height), float(cameras.near))

    @property
    def count(self) -> int:
        return int(self.rotation.shape[0])


@dataclass
class ProjectedGaussians:
    """Screen-space Gaussians of V views; entry (v, n) is Gaussian n seen from view v."""

    params: torch.Tensor  # [V, N, 6] mean_u, mean_v, conic A, B, C, depth z_cam (differentiable)
    half_extent: torch.Tensor  # [V, N, 2] half width/height (pixels) of the cutoff ellipse's box, detached
    visible: torch.Tensor  # [V, N] bool: in front of the near plane and its box touches the image


def project_gaussians(x: torch.Tensor, cov3d: torch.Tensor, cams: CameraTensors,
                      cfg: RenderConfig) -> ProjectedGaussians:
    """EWA projection: Sigma2D = J W Sigma W^T J^T + low_pass I, conic = Sigma2D^-1.

    x: [N, 3] world means, cov3d: [N, 3, 3]. W is the camera rotation, J the Jacobian of the
    pinhole projection at the Gaussian's centre (3DGS eq. 5). Gaussians behind the near plane
    are marked invisible (their other outputs are finite placeholders).
    """
    rot, trans, k = cams.rotation, cams.translation, cams.intrinsics
    fx, fy, cx, cy = (k[:, i, None] for i in range(4))  # each [V, 1]
    xc = torch.einsum("vij,nj->vni", rot, x) + trans[:, None, :]  # [V, N, 3]
    z = xc[..., 2]
    in_front = z > cams.near
    z_safe = torch.where(in_front, z, torch.ones_like(z))  # placeholder keeps culled entries finite
    tx, ty = xc[..., 0] / z_safe, xc[..., 1] / z_safe
    u = fx * tx + cx
    v = fy * ty + cy
    w, h = float(cams.width), float(cams.height)
    tx_c = torch.minimum(torch.maximum(tx, (-_JACOBIAN_MARGIN * w - cx) / fx), ((1 + _JACOBIAN_MARGIN) * w - cx) / fx)
    ty_c = torch.minimum(torch.maximum(ty, (-_JACOBIAN_MARGIN * h - cy) / fy), ((1 + _JACOBIAN_MARGIN) * h - cy) / fy)
    # Rows of J W (2 x 3 per entry), written out elementwise: batched 2x3 matmuls are slow on CPU.
    r0, r1, r2 = (rot[:, None, i, :] for i in range(3))  # each [V, 1, 3]
    m0 = (fx / z_safe)[..., None] * (r0 - tx_c[..., None] * r2)  # [V, N, 3]
    m1 = (fy / z_safe)[..., None] * (r1 - ty_c[..., None] * r2)
    s00, s01, s02 = cov3d[:, 0, 0], cov3d[:, 0, 1], cov3d[:, 0, 2]
    s11, s12, s22 = cov3d[:, 1, 1], cov3d[:, 1, 2], cov3d[:, 2, 2]

    def quad(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:  # p^T Sigma q, [V, N]
        px, py, pz = p.unbind(-1)
        qx, qy, qz = q.unbind(-1)
        return (px * (s00 * qx + s01 * qy + s02 * qz) + py * (s01 * qx + s11 * qy + s12 * qz)
                + pz * (s02 * qx + s12 * qy + s22 * qz))

    a = quad(m0, m0) + cfg.low_pass  # Sigma2D = (J W) Sigma (J W)^T + low_pass I
    b = quad(m0, m1)
    c = quad(m1, m1) + cfg.low_pass
    det = a * c - b * b
    # det >= low_pass^2 > 0 for any PSD cov2d; the clamp only guards low_pass = 0 with a singular Sigma.
    det = torch.clamp(det, min=torch.finfo(det.dtype).tiny ** 0.5)
    params = torch.stack([u, v, c / det, -b / det, a / det, z], dim=-1)
    with torch.no_grad():
        half = cfg.cutoff_sigma * torch.sqrt(torch.stack([a, c], dim=-1))  # exact box of the cutoff ellipse
        finite = torch.isfinite(params).all(dim=-1) & torch.isfinite(half).all(dim=-1)
        on_screen = (u + half[..., 0] > 0) & (u - half[..., 0] < w) & (v + half[..., 1] > 0) & (v - half[..., 1] < h)
        visible = in_front & on_screen & finite
    return ProjectedGaussians(params=params, half_extent=half, visible=visible)


def covariance_from_F_backward(F: torch.Tensor,  # [N, 3, 3]
                               sigma0: float | torch.Tensor,  # scalar or [N]
                               grad_cov: torch.Tensor) -> torch.Tensor:  # [L, N, 6] symmetric
    """Reverse of :func:`covariance_from_F` for L upstream gradients at once: with G the
    symmetric gradient of Sigma (<G, dSigma> for symmetric dSigma; given by its entries
    00, 01, 02, 11, 12, 22), dL/dF = 2 sigma0^2 G F. Returns [L, N, 3, 3]."""
    g00, g01, g02, g11, g12, g22 = grad_cov.unbind(-1)
    G = torch.stack([torch.stack([g00, g01, g02], -1), torch.stack([g01, g11, g12], -1),
                     torch.stack([g02, g12, g22], -1)], -2)  # [L, N, 3, 3]
    s = torch.as_tensor(sigma0, dtype=F.dtype, device=F.device)
    s2 = (s * s).reshape(1, -1, 1, 1) if s.ndim > 0 else s * s
    return 2.0 * s2 * (G @ F)


_SYM = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))  # a symmetric 3x3's entries, in order


def project_gaussians_backward(x: torch.Tensor,  # [N, 3]
                               cov3d: torch.Tensor,  # [N, 3, 3]
                               cams: CameraTensors, cfg: RenderConfig,
                               grad_params: torch.Tensor,  # [L, V, N, 6]
                               want_grad_x: bool = True) -> tuple[torch.Tensor | None, torch.Tensor]:
    """Hand-written reverse of :func:`project_gaussians`' params for L upstream gradients at once,
    view by view, keeping no graph (autograd held ~1 GB of [V, N] intermediates at 471K particles).

    With m0, m1 the rows of J W, a = m0^T Sigma m0 + low_pass, b = m0^T Sigma m1,
    c = m1^T Sigma m1 + low_pass, det = a c - b^2 and the conic (c, -b, a) / det:
        det_bar = -(A_bar c - B_bar b + C_bar a) / det^2
        a_bar = C_bar / det + det_bar c,  c_bar = A_bar / det + det_bar a,  b_bar = -B_bar / det - 2 b det_bar
        Sigma_bar = a_bar m0 m0^T + b_bar sym(m0 m1^T) + c_bar m1 m1^T     (symmetric)
        m0_bar = 2 a_bar Sigma m0 + b_bar Sigma m1,  m1_bar = b_bar Sigma m0 + 2 c_bar Sigma m1
    and m0 = (fx / z)(r0 - tx_c r2), tx = x_c / z, u = fx tx + cx (likewise m1, ty, v) back to the
    camera-space mean and x. The Jacobian's clamp passes no gradient where it acts, and z only
    where the entry is in front of the near plane (the forward's placeholder elsewhere), as
    autograd does. Returns (dL/dx [L, N, 3] or None, dL/dSigma [L, N, 6]: the symmetric
    gradient's entries 00, 01, 02, 11, 12, 22, for covariance_from_F_backward).
    """
    L, V, N = grad_params.shape[0], grad_params.shape[1], x.shape[0]
    # component-wise on contiguous [N] and [L, N] tensors: strided views and 3x3 bmm are slow on CPU
    zeros = lambda: torch.zeros((L, N), dtype=x.dtype, device=x.device)  # noqa: E731
    grad_cov = [zeros() for _ in _SYM]  # the symmetric gradient's six entries
    grad_xs = [zeros() for _ in range(3)] if want_grad_x else None
    w, h = float(cams.width), float(cams.height)
    det_floor = torch.finfo(x.dtype).tiny ** 0.5
    xs = [x[:, i].contiguous() for i in range(3)]
    cov = {(i, j): cov3d[:, i, j].contiguous() for i, j in _SYM}
    cov.update({(j, i): cov[i, j] for i, j in _SYM})

    def times_cov(m: list) -> list:  # Sigma m
        return [cov[i, 0] * m[0] + cov[i, 1] * m[1] + cov[i, 2] * m[2] for i in range(3)]

    def dot(p: list, q: list) -> torch.Tensor:
        return p[0] * q[0] + p[1] * q[1] + p[2] * q[2]

    for view in range(V):
        rot = [[float(r) for r in row] for row in cams.rotation[view]]
        trans = [float(t) for t in cams.translation[view]]
        fx, fy, cx, cy = (float(k) for k in cams.intrinsics[view])
        xc = [xs[0] * rot[i][0] + xs[1] * rot[i][1] + xs[2] * rot[i][2] + trans[i] for i in range(3)]
        in_front = xc[2] > cams.near
        z_safe = torch.where(in_front, xc[2], 1.0)
        tx, ty = xc[0] / z_safe, xc[1] / z_safe
        lo_x, hi_x = (-_JACOBIAN_MARGIN * w - cx) / fx, ((1 + _JACOBIAN_MARGIN) * w - cx) / fx
        lo_y, hi_y = (-_JACOBIAN_MARGIN * h - cy) / fy, ((1 + _JACOBIAN_MARGIN) * h - cy) / fy
        fx_z, fy_z = fx / z_safe, fy / z_safe
        tx_c, ty_c = tx.clamp(lo_x, hi_x), ty.clamp(lo_y, hi_y)
        m0 = [fx_z * (rot[0][k] - tx_c * rot[2][k]) for k in range(3)]  # rows of J W
        m1 = [fy_z * (rot[1][k] - ty_c * rot[2][k]) for k in range(3)]
        s_m0, s_m1 = times_cov(m0), times_cov(m1)
        a = dot(m0, s_m0) + cfg.low_pass
        b = dot(m0, s_m1)
        c = dot(m1, s_m1) + cfg.low_pass
        det_raw = a * c - b * b
        inv = 1.0 / torch.clamp(det_raw, min=det_floor)
        gu, gv, gA, gB, gC, gz = grad_params[:, view].permute(2, 0, 1).contiguous()  # each [L, N]
        det_bar = torch.where(det_raw >= det_floor, (-gA * c + gB * b - gC * a) * (inv * inv), 0.0)
        a_bar = gC * inv + det_bar * c
        c_bar = gA * inv + det_bar * a
        b_bar = -gB * inv - (2.0 * b) * det_bar
        for k, (i, j) in enumerate(_SYM):
            grad_cov[k].addcmul_(a_bar, m0[i] * m0[j]).addcmul_(c_bar, m1[i] * m1[j])
            grad_cov[k].addcmul_(b_bar, 0.5 * (m0[i] * m1[j] + m1[i] * m0[j]))
        if not want_grad_x:
            continue
        m0_bar = [2.0 * a_bar * s_m0[k] + b_bar * s_m1[k] for k in range(3)]  # each [L, N]
        m1_bar = [b_bar * s_m0[k] + 2.0 * c_bar * s_m1[k] for k in range(3)]
        zs_bar = -(dot(m0_bar, m0) + dot(m1_bar, m1)) / z_safe
        free_x = ((tx > lo_x) & (tx < hi_x)).to(x.dtype)
        free_y = ((ty > lo_y) & (ty < hi_y)).to(x.dtype)
        tx_bar = fx * gu - (free_x * fx_z) * dot(m0_bar, rot[2])
        ty_bar = fy * gv - (free_y * fy_z) * dot(m1_bar, rot[2])
        zs_bar = zs_bar - (tx_bar * tx + ty_bar * ty) / z_safe
        xc_bar = [tx_bar / z_safe, ty_bar / z_safe, gz + torch.where(in_front, zs_bar, 0.0)]
        for k in range(3):  # x_c = R x + t
            grad_xs[k] += xc_bar[0] * rot[0][k] + xc_bar[1] * rot[1][k] + xc_bar[2] * rot[2][k]
    grad_x = torch.stack(grad_xs, -1) if want_grad_x else None
    return grad_x, torch.stack(grad_cov, -1)
