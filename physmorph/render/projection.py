"""Per-Gaussian preprocessing in torch: F -> Sigma, EWA projection, 2D conic (the reference).

Paper section 3.2 (MPM-Gaussian duality) and the EWA splatting of 3DGS (Zwicker et al. 2002,
Kerbl et al. 2023). Everything here is O(V N). The forward is differentiable by torch autograd
(the reference); render_and_grad uses the Taichi kernels of projection_kernels, forward and
reverse, which take every loss's gradient in one pass and keep no graph.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from physmorph.base.cameras import Cameras

from physmorph.settings.render import RenderConfig

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

    def view(self, v: int) -> "CameraTensors":
        """View v alone."""
        return CameraTensors(self.rotation[v:v + 1], self.translation[v:v + 1], self.intrinsics[v:v + 1],
                             self.width, self.height, self.near)


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
