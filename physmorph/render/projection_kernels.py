"""The EWA projection and its reverse as Taichi kernels, one pass over the Gaussians each.

Paper section 3.2 (MPM-Gaussian duality) and the EWA splatting of 3DGS (Zwicker et al. 2002,
Kerbl et al. 2023). For Gaussian n seen from view v (rotation R, translation t, intrinsics fx,
fy, cx, cy), with Sigma = sigma0^2 F F^T (eq. 1):

    x_c = R x + t,  z = x_c[2],  tx = x_c[0] / z,  ty = x_c[1] / z,  u = fx tx + cx,  v = fy ty + cy
    m0 = (fx / z)(r0 - tx_c r2),  m1 = (fy / z)(r1 - ty_c r2)   (rows of J W; tx_c, ty_c clamped
                                                                  to 15 % past the image)
    a = m0^T Sigma m0 + low_pass,  b = m0^T Sigma m1,  c = m1^T Sigma m1 + low_pass
    params = (u, v, c / det, -b / det, a / det, z),  det = max(a c - b^2, tiny^(1/2))

and the reverse, for L upstream gradients of the params at once (A, B, C the conic's entries,
bars the gradients; the conic is (c, -b, a) / det):

    det_bar = -(A_bar c - B_bar b + C_bar a) / det^2,  a_bar = C_bar / det + det_bar c,
    c_bar = A_bar / det + det_bar a,  b_bar = -B_bar / det - 2 b det_bar
    Sigma_bar = a_bar m0 m0^T + b_bar sym(m0 m1^T) + c_bar m1 m1^T,  dL/dF = 2 sigma0^2 Sigma_bar F
    m0_bar = 2 a_bar Sigma m0 + b_bar Sigma m1,  m1_bar = b_bar Sigma m0 + 2 c_bar Sigma m1

and m0 = (fx / z)(r0 - tx_c r2), tx = x_c / z, u = fx tx + cx (likewise m1, ty, v) back to the
camera-space mean and x = R^T (x_c - t). An entry behind the near plane uses z = 1 (a finite
placeholder), is not visible, and passes no gradient through z; the clamp passes none where it
acts. Each Gaussian's thread loops over the views, so the reverse sums without atomics. Float
constants reach the kernels as f64 arguments (a Python float in a kernel is an f32 literal).

The torch forms in physmorph.render.projection are the reference (autograd through
project_gaussians and covariance_from_F); at the paper's scale (8 views x 424K Gaussians) they
took ~1 s for the forward and ~0.5 s for the reverse of a render.
"""

# No "from __future__ import annotations": Taichi needs the kernel annotations as objects.

import taichi as ti
import torch

from physmorph.base.taichi_runtime import ensure_taichi

from physmorph.settings.render import RenderConfig
from .projection import _JACOBIAN_MARGIN, CameraTensors
from .rasterizer import _ti_dtype


_SYM = ((0, 0, 0), (1, 0, 1), (2, 0, 2), (3, 1, 1), (4, 1, 2), (5, 2, 2))  # (k, i, j): a symmetric 3x3's entries


@ti.func
def _camera_terms(x, rot: ti.template(), trans: ti.template(), intr: ti.template(), v, width, height, near, margin,
                  dtype: ti.template()):
    """x_c's depth, (u, v), the rows m0, m1 of J W, the in-front flag and the clamp's free flags."""
    R = ti.Matrix.zero(dtype, 3, 3)
    t = ti.Vector.zero(dtype, 3)
    for i in ti.static(range(3)):
        t[i] = trans[v, i]
        for j in ti.static(range(3)):
            R[i, j] = rot[v, i, j]
    fx, fy, cx, cy = intr[v, 0], intr[v, 1], intr[v, 2], intr[v, 3]
    xc = R @ x + t
    z = xc[2]
    in_front = z > ti.cast(near, dtype)
    z_safe = z if in_front else ti.cast(1.0, dtype)
    tx = xc[0] / z_safe
    ty = xc[1] / z_safe
    w = ti.cast(width, dtype)
    h = ti.cast(height, dtype)
    m = ti.cast(margin, dtype)
    lo_x = (-m * w - cx) / fx
    hi_x = ((1 + m) * w - cx) / fx
    lo_y = (-m * h - cy) / fy
    hi_y = ((1 + m) * h - cy) / fy
    tx_c = ti.min(ti.max(tx, lo_x), hi_x)
    ty_c = ti.min(ti.max(ty, lo_y), hi_y)
    r0 = ti.Vector([R[0, 0], R[0, 1], R[0, 2]])
    r1 = ti.Vector([R[1, 0], R[1, 1], R[1, 2]])
    r2 = ti.Vector([R[2, 0], R[2, 1], R[2, 2]])
    m0 = (fx / z_safe) * (r0 - tx_c * r2)
    m1 = (fy / z_safe) * (r1 - ty_c * r2)
    free_x = (tx > lo_x) and (tx < hi_x)
    free_y = (ty > lo_y) and (ty < hi_y)
    return z, z_safe, tx, ty, fx * tx + cx, fy * ty + cy, m0, m1, r2, in_front, free_x, free_y, fx, fy


@ti.func
def _load(a: ti.template(), n, dtype: ti.template()):
    return ti.Vector([a[n, 0], a[n, 1], a[n, 2]], dt=dtype)


@ti.func
def _load33(a: ti.template(), n, dtype: ti.template()):
    M = ti.Matrix.zero(dtype, 3, 3)
    for i, j in ti.static(ti.ndrange(3, 3)):
        M[i, j] = a[n, i, j]
    return M


@ti.kernel
def _project_forward(x: ti.types.ndarray(), F: ti.types.ndarray(), s2: ti.types.ndarray(),  # [N, 3], [N, 3, 3], [N]
                     rot: ti.types.ndarray(), trans: ti.types.ndarray(), intr: ti.types.ndarray(),  # [V, 3, 3], [V, 3], [V, 4]
                     params: ti.types.ndarray(), half: ti.types.ndarray(),  # out [V, N, 6], [V, N, 2]
                     visible: ti.types.ndarray(),  # out [V, N] uint8
                     width: ti.i32, height: ti.i32, near: ti.f64, margin: ti.f64, low_pass: ti.f64,
                     cutoff: ti.f64, det_floor: ti.f64, dtype: ti.template()):
    n_views = rot.shape[0]
    for v, n in ti.ndrange(n_views, x.shape[0]):
        xn = _load(x, n, dtype)
        Fn = _load33(F, n, dtype)
        Sigma = s2[n] * (Fn @ Fn.transpose())
        z, z_safe, tx, ty, u, vv, m0, m1, r2, in_front, free_x, free_y, fx, fy = _camera_terms(
            xn, rot, trans, intr, v, width, height, near, margin, dtype)
        lp = ti.cast(low_pass, dtype)
        a = m0.dot(Sigma @ m0) + lp
        b = m0.dot(Sigma @ m1)
        c = m1.dot(Sigma @ m1) + lp
        det = ti.max(a * c - b * b, ti.cast(det_floor, dtype))
        out = ti.Vector([u, vv, c / det, -b / det, a / det, z], dt=dtype)
        hx = ti.cast(cutoff, dtype) * ti.sqrt(a)
        hy = ti.cast(cutoff, dtype) * ti.sqrt(c)
        finite = not (ti.math.isnan(hx) or ti.math.isinf(hx) or ti.math.isnan(hy) or ti.math.isinf(hy))
        for k in ti.static(range(6)):
            params[v, n, k] = out[k]
            finite = finite and not (ti.math.isnan(out[k]) or ti.math.isinf(out[k]))
        half[v, n, 0] = hx
        half[v, n, 1] = hy
        w = ti.cast(width, dtype)
        h = ti.cast(height, dtype)
        on_screen = (u + hx > 0) and (u - hx < w) and (vv + hy > 0) and (vv - hy < h)
        visible[v, n] = ti.u8(1) if (in_front and on_screen and finite) else ti.u8(0)


@ti.kernel
def _project_backward_add(x: ti.types.ndarray(), F: ti.types.ndarray(), s2: ti.types.ndarray(),
                          rot: ti.types.ndarray(), trans: ti.types.ndarray(), intr: ti.types.ndarray(),
                          grad_params: ti.types.ndarray(),  # [L, V, N, 6] of the V views in rot
                          sigma_bar: ti.types.ndarray(),  # [L, N, 6] in/out: Sigma_bar (00 01 02 11 12 22)
                          grad_x: ti.types.ndarray(),  # [L, N, 3] in/out (when want_x)
                          width: ti.i32, height: ti.i32, near: ti.f64, margin: ti.f64, low_pass: ti.f64,
                          det_floor: ti.f64,
                          n_losses: ti.template(), want_x: ti.template(), dtype: ti.template()):
    """Each loss's Sigma_bar and x_bar of the views in rot, added to what sigma_bar and grad_x hold
    (the views before, in order: the same sums as one call over all of them)."""
    n_views = rot.shape[0]
    for n in range(x.shape[0]):
        xn = _load(x, n, dtype)
        Fn = _load33(F, n, dtype)
        Sigma = s2[n] * (Fn @ Fn.transpose())
        G = ti.Matrix.zero(dtype, n_losses, 6)  # each loss's Sigma_bar: entries 00 01 02 11 12 22
        gx = ti.Matrix.zero(dtype, n_losses, 3)
        for l, k in ti.static(ti.ndrange(n_losses, 6)):
            G[l, k] = sigma_bar[l, n, k]
        if ti.static(want_x):
            for l, k in ti.static(ti.ndrange(n_losses, 3)):
                gx[l, k] = grad_x[l, n, k]
        for v in range(n_views):
            # a view where the Gaussian has no gradient (occluded, off screen: most of an opaque
            # body's) adds zeros: it is passed over
            seen = False
            for l, k in ti.static(ti.ndrange(n_losses, 6)):
                if grad_params[l, v, n, k] != 0:
                    seen = True
            if seen:
                z, z_safe, tx, ty, u, vv, m0, m1, r2, in_front, free_x, free_y, fx, fy = _camera_terms(
                    xn, rot, trans, intr, v, width, height, near, margin, dtype)
                s_m0 = Sigma @ m0
                s_m1 = Sigma @ m1
                lp = ti.cast(low_pass, dtype)
                a = m0.dot(s_m0) + lp
                b = m0.dot(s_m1)
                c = m1.dot(s_m1) + lp
                det_raw = a * c - b * b
                floor = ti.cast(det_floor, dtype)
                inv = 1 / ti.max(det_raw, floor)
                for l in ti.static(range(n_losses)):
                    gu = grad_params[l, v, n, 0]
                    gv = grad_params[l, v, n, 1]
                    gA = grad_params[l, v, n, 2]
                    gB = grad_params[l, v, n, 3]
                    gC = grad_params[l, v, n, 4]
                    gz = grad_params[l, v, n, 5]
                    det_bar = (-gA * c + gB * b - gC * a) * (inv * inv) if det_raw >= floor else ti.cast(0.0, dtype)
                    a_bar = gC * inv + det_bar * c
                    c_bar = gA * inv + det_bar * a
                    b_bar = -gB * inv - (2 * b) * det_bar
                    for k, i, j in ti.static(_SYM):
                        G[l, k] += (a_bar * m0[i] * m0[j] + c_bar * m1[i] * m1[j]
                                    + b_bar * ti.cast(0.5, dtype) * (m0[i] * m1[j] + m1[i] * m0[j]))
                    if ti.static(want_x):
                        m0_bar = 2 * a_bar * s_m0 + b_bar * s_m1
                        m1_bar = b_bar * s_m0 + 2 * c_bar * s_m1
                        zs_bar = -(m0_bar.dot(m0) + m1_bar.dot(m1)) / z_safe
                        tx_bar = fx * gu - (fx / z_safe if free_x else ti.cast(0.0, dtype)) * m0_bar.dot(r2)
                        ty_bar = fy * gv - (fy / z_safe if free_y else ti.cast(0.0, dtype)) * m1_bar.dot(r2)
                        zs_bar = zs_bar - (tx_bar * tx + ty_bar * ty) / z_safe
                        xc_bar = ti.Vector([tx_bar / z_safe, ty_bar / z_safe,
                                            gz + (zs_bar if in_front else ti.cast(0.0, dtype))])
                        for kk in ti.static(range(3)):  # x_c = R x + t: x_bar = R^T x_c_bar
                            gx[l, kk] += (xc_bar[0] * rot[v, 0, kk] + xc_bar[1] * rot[v, 1, kk]
                                          + xc_bar[2] * rot[v, 2, kk])
        for l, k in ti.static(ti.ndrange(n_losses, 6)):
            sigma_bar[l, n, k] = G[l, k]
        if ti.static(want_x):
            for l, k in ti.static(ti.ndrange(n_losses, 3)):
                grad_x[l, n, k] = gx[l, k]


@ti.kernel
def _project_backward_F(F: ti.types.ndarray(), s2: ti.types.ndarray(),
                        sigma_bar: ti.types.ndarray(),  # [L, N, 6] the views' summed Sigma_bar
                        grad_F: ti.types.ndarray(),  # out [L, N, 3, 3]
                        n_losses: ti.template(), dtype: ti.template()):
    """dL/dF = 2 sigma0^2 Sigma_bar F (Sigma = sigma0^2 F F^T, Sigma_bar symmetric)."""
    for n in range(F.shape[0]):
        Fn = _load33(F, n, dtype)
        for l in ti.static(range(n_losses)):
            Gl = ti.Matrix([[sigma_bar[l, n, 0], sigma_bar[l, n, 1], sigma_bar[l, n, 2]],
                            [sigma_bar[l, n, 1], sigma_bar[l, n, 3], sigma_bar[l, n, 4]],
                            [sigma_bar[l, n, 2], sigma_bar[l, n, 4], sigma_bar[l, n, 5]]])
            gF = 2 * s2[n] * (Gl @ Fn)
            for i, j in ti.static(ti.ndrange(3, 3)):
                grad_F[l, n, i, j] = gF[i, j]


def _inputs(x: torch.Tensor, F: torch.Tensor, sigma0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    s = torch.as_tensor(sigma0, dtype=x.dtype, device=x.device)
    s2 = (s * s).expand(x.shape[0]).contiguous()
    return x.detach().contiguous(), F.detach().contiguous(), s2


def project_forward(x: torch.Tensor,  # [N, 3]
                    F: torch.Tensor,  # [N, 3, 3]
                    sigma0,  # scalar or [N]
                    cams: CameraTensors,
                    cfg: RenderConfig) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """projection.project_gaussians(x, covariance_from_F(F, sigma0)) without a graph: params
    [V, N, 6], half extents [V, N, 2] and visible [V, N] (bool)."""
    ensure_taichi()
    x, F, s2 = _inputs(x, F, sigma0)
    V, N = cams.count, x.shape[0]
    opts = dict(dtype=x.dtype, device=x.device)
    params = torch.empty((V, N, 6), **opts)
    half = torch.empty((V, N, 2), **opts)
    visible = torch.empty((V, N), dtype=torch.uint8, device=x.device)
    if N:
        _project_forward(x, F, s2, cams.rotation.contiguous(), cams.translation.contiguous(),
                         cams.intrinsics.contiguous(), params, half, visible, cams.width, cams.height,
                         float(cams.near), _JACOBIAN_MARGIN, float(cfg.low_pass), float(cfg.cutoff_sigma),
                         float(torch.finfo(x.dtype).tiny ** 0.5), _ti_dtype(x.dtype))
    return params, half, visible.bool()


class ProjectionReverse:
    """The projection's reverse taken a few views at a time (the render's reverse runs view by
    view, so that the rasterizer's [L, V N, 6] gradients never exist at once): each loss's
    Sigma_bar and x_bar summed over the views added so far, in the order added; ``result`` then
    gives dL_l/dx [L, N, 3] (or None) and dL_l/dF [L, N, 3, 3]. Views added one by one give the
    numbers one call over all of them gives."""

    def __init__(self, x: torch.Tensor,  # [N, 3]
                 F: torch.Tensor,  # [N, 3, 3]
                 sigma0,  # scalar or [N]
                 n_losses: int, want_grad_x: bool = True):
        ensure_taichi()
        self.x, self.F, self.s2 = _inputs(x, F, sigma0)
        self.n_losses, self.want_grad_x = int(n_losses), bool(want_grad_x)
        opts = dict(dtype=self.x.dtype, device=self.x.device)
        n = self.x.shape[0]
        self.sigma_bar = torch.zeros((self.n_losses, n, 6), **opts)
        self.grad_x = torch.zeros((self.n_losses, n, 3) if self.want_grad_x else (1, 1, 3), **opts)

    def add(self, cams: CameraTensors, cfg: RenderConfig,
            grad_params: torch.Tensor) -> None:  # [L, V, N, 6] of the V views of cams
        if grad_params.shape != (self.n_losses, cams.count, self.x.shape[0], 6):
            raise ValueError(f"grad_params is {tuple(grad_params.shape)}, expected "
                             f"{(self.n_losses, cams.count, self.x.shape[0], 6)}")
        if self.x.shape[0]:
            _project_backward_add(self.x, self.F, self.s2, cams.rotation.contiguous(), cams.translation.contiguous(),
                                  cams.intrinsics.contiguous(), grad_params.to(self.x.dtype).contiguous(),
                                  self.sigma_bar, self.grad_x, cams.width, cams.height, float(cams.near),
                                  _JACOBIAN_MARGIN, float(cfg.low_pass), float(torch.finfo(self.x.dtype).tiny ** 0.5),
                                  self.n_losses, self.want_grad_x, _ti_dtype(self.x.dtype))

    def result(self) -> tuple[torch.Tensor | None, torch.Tensor]:
        grad_F = torch.zeros((self.n_losses,) + tuple(self.F.shape), dtype=self.x.dtype, device=self.x.device)
        if self.x.shape[0]:
            _project_backward_F(self.F, self.s2, self.sigma_bar, grad_F, self.n_losses, _ti_dtype(self.x.dtype))
        return (self.grad_x if self.want_grad_x else None), grad_F


def project_backward(x: torch.Tensor,  # [N, 3]
                     F: torch.Tensor,  # [N, 3, 3]
                     sigma0,  # scalar or [N]
                     cams: CameraTensors, cfg: RenderConfig,
                     grad_params: torch.Tensor,  # [L, V, N, 6]
                     want_grad_x: bool = True) -> tuple[torch.Tensor | None, torch.Tensor]:
    """dL_l/dx [L, N, 3] (or None) and dL_l/dF [L, N, 3, 3] from the params' gradients of every view."""
    reverse = ProjectionReverse(x, F, sigma0, grad_params.shape[0], want_grad_x)
    reverse.add(cams, cfg, grad_params)
    return reverse.result()
