"""Tile rasterizer: front-to-back alpha compositing with a hand-written backward (Taichi).

Paper section 3.2/3.5; the compositing of 3DGS (Kerbl et al. 2023, eqs. 2-3). For pixel p with
the Gaussians of its tile sorted front to back (k = 1..K):

    a_k   = min(alpha_max, opacity * exp(power_k)),   power_k = -1/2 d_k^T Sigma2D_k^-1 d_k,
            d_k = mean_k - pixel centre; skipped if a_k < alpha_min or power_k < -cutoff^2/2
    T_k   = prod_{j<k} (1 - a_j)      (compositing stops once T_k < transmittance_min)
    alpha = 1 - T_final,   D = sum_k a_k T_k z_k   (accumulated depth; expected depth = D / alpha)

Backward (walked back to front, T_k recovered as T_{k+1} / (1 - a_k)):

    d alpha / d a_k = T_final / (1 - a_k)
    d D / d a_k     = T_k z_k - S_k / (1 - a_k),   S_k = sum_{j>k} a_j T_j z_j
    d D / d z_k     = a_k T_k
    d a_k / d power_k = a_k (0 where clamped at alpha_max), and power_k's derivatives w.r.t.
    the mean and the conic (A, B, C) follow from power = -(A dx^2 + 2 B dx dy + C dy^2) / 2.

The backward takes C channels of upstream gradients at once (one per loss), so adaptive
gradient matching costs a single pass over the pixel lists. Memory: O(pixels + pairs).
"""

# No "from __future__ import annotations": Taichi needs the kernel annotations as objects.

import taichi as ti
import torch

from physmorph.base.taichi_runtime import init_taichi, resolve_device

from physmorph.settings.render import RenderConfig
from .tiles import TileBins


@ti.kernel
def _composite_forward(
    gauss: ti.types.ndarray(),  # [V*N, 6] mean_u, mean_v, A, B, C, z
    point_list: ti.types.ndarray(),  # [M] int32
    tile_ranges: ti.types.ndarray(),  # [V*ty*tx, 2] int32
    t_final: ti.types.ndarray(),  # [V, H, W] out
    depth_acc: ti.types.ndarray(),  # [V, H, W] out
    last: ti.types.ndarray(),  # [V, H, W] int32 out: one past the last contributing list entry
    tile: ti.i32, tiles_x: ti.i32, tiles_y: ti.i32,
    opacity: ti.f64, alpha_min: ti.f64, alpha_max: ti.f64, power_min: ti.f64, t_min: ti.f64,
    dtype: ti.template(),
    behind: ti.template(),  # True: t_final holds the transmittance the Gaussians are composited behind
):
    n_views, height, width = t_final.shape[0], t_final.shape[1], t_final.shape[2]
    for v, t, p in ti.ndrange(n_views, tiles_x * tiles_y, tile * tile):
        ty = t // tiles_x
        tx = t - ty * tiles_x
        py = ty * tile + p // tile
        px = tx * tile + p % tile
        if py < height and px < width:
            gid = (v * tiles_y + ty) * tiles_x + tx
            start = tile_ranges[gid, 0]
            end = tile_ranges[gid, 1]
            cu = ti.cast(px, dtype) + ti.cast(0.5, dtype)
            cv = ti.cast(py, dtype) + ti.cast(0.5, dtype)
            trans = ti.cast(1.0, dtype)
            if ti.static(behind):
                trans = t_final[v, py, px]
            dacc = ti.cast(0.0, dtype)
            stop = start
            for k in range(start, end):
                g = point_list[k]
                du = gauss[g, 0] - cu
                dv = gauss[g, 1] - cv
                power = -ti.cast(0.5, dtype) * (gauss[g, 2] * du * du + gauss[g, 4] * dv * dv) \
                    - gauss[g, 3] * du * dv
                if power >= ti.cast(power_min, dtype):
                    a = ti.min(ti.cast(alpha_max, dtype), ti.cast(opacity, dtype) * ti.exp(power))
                    if a >= ti.cast(alpha_min, dtype):
                        if trans < ti.cast(t_min, dtype):
                            break
                        dacc += a * trans * gauss[g, 5]
                        trans *= ti.cast(1.0, dtype) - a
                        stop = k + 1
            t_final[v, py, px] = trans
            depth_acc[v, py, px] = dacc
            last[v, py, px] = stop


@ti.kernel
def _composite_backward(
    gauss: ti.types.ndarray(),  # [V*N, 6]
    point_list: ti.types.ndarray(),  # [M]
    tile_ranges: ti.types.ndarray(),  # [V*ty*tx, 2]
    t_final: ti.types.ndarray(),  # [V, H, W]
    last: ti.types.ndarray(),  # [V, H, W]
    grad_alpha: ti.types.ndarray(),  # [C, V, H, W] dL_c/d alpha
    grad_depth_acc: ti.types.ndarray(),  # [C, V, H, W] dL_c/dD
    grad_gauss: ti.types.ndarray(),  # [C, V*N, 6] out (accumulated, must start at zero)
    tile: ti.i32, tiles_x: ti.i32, tiles_y: ti.i32,
    opacity: ti.f64, alpha_min: ti.f64, alpha_max: ti.f64, power_min: ti.f64,
    dtype: ti.template(),
):
    n_channels = grad_alpha.shape[0]
    n_views, height, width = t_final.shape[0], t_final.shape[1], t_final.shape[2]
    for v, t, p in ti.ndrange(n_views, tiles_x * tiles_y, tile * tile):
        ty = t // tiles_x
        tx = t - ty * tiles_x
        py = ty * tile + p // tile
        px = tx * tile + p % tile
        if py < height and px < width:
            gid = (v * tiles_y + ty) * tiles_x + tx
            start = tile_ranges[gid, 0]
            stop = last[v, py, px]
            cu = ti.cast(px, dtype) + ti.cast(0.5, dtype)
            cv = ti.cast(py, dtype) + ti.cast(0.5, dtype)
            tf = t_final[v, py, px]
            trans = tf  # transmittance behind the current entry, walking back to front
            suffix = ti.cast(0.0, dtype)  # S_k = sum_{j>k} a_j T_j z_j
            for kk in range(stop - start):
                k = stop - 1 - kk
                g = point_list[k]
                du = gauss[g, 0] - cu
                dv = gauss[g, 1] - cv
                power = -ti.cast(0.5, dtype) * (gauss[g, 2] * du * du + gauss[g, 4] * dv * dv) \
                    - gauss[g, 3] * du * dv
                if power >= ti.cast(power_min, dtype):
                    raw = ti.cast(opacity, dtype) * ti.exp(power)
                    a = ti.min(ti.cast(alpha_max, dtype), raw)
                    if a >= ti.cast(alpha_min, dtype):
                        one_minus = ti.cast(1.0, dtype) - a
                        trans = trans / one_minus  # T_k, in front of entry k
                        z = gauss[g, 5]
                        da_alpha = tf / one_minus
                        da_depth = trans * z - suffix / one_minus
                        dz_depth = a * trans
                        dpower_da = a if raw < ti.cast(alpha_max, dtype) else ti.cast(0.0, dtype)
                        for c in range(n_channels):
                            ga = grad_alpha[c, v, py, px]
                            gd = grad_depth_acc[c, v, py, px]
                            gp = (ga * da_alpha + gd * da_depth) * dpower_da
                            grad_gauss[c, g, 0] += -gp * (gauss[g, 2] * du + gauss[g, 3] * dv)
                            grad_gauss[c, g, 1] += -gp * (gauss[g, 3] * du + gauss[g, 4] * dv)
                            grad_gauss[c, g, 2] += -ti.cast(0.5, dtype) * gp * du * du
                            grad_gauss[c, g, 3] += -gp * du * dv
                            grad_gauss[c, g, 4] += -ti.cast(0.5, dtype) * gp * dv * dv
                            grad_gauss[c, g, 5] += gd * dz_depth
                        suffix += a * trans * z


@ti.func
def _box_range(centre, half, lo: ti.i32, hi: ti.i32, dtype: ti.template()):
    """Pixels [first, last] of [lo, hi] whose centres may lie within centre +- half (one pixel of
    slack so rounding can never drop a pixel the exact cutoff test would keep)."""
    first = ti.cast(ti.floor(ti.max(centre - half - ti.cast(1.5, dtype), ti.cast(lo, dtype))), ti.i32)
    last = ti.cast(ti.floor(ti.min(centre + half + ti.cast(0.5, dtype), ti.cast(hi, dtype))), ti.i32)
    return first, last


@ti.kernel
def _composite_forward_tiles(
    gauss: ti.types.ndarray(),  # [V*N, 6]
    half: ti.types.ndarray(),  # [V*N, 2] half extent of the cutoff box (pixels)
    point_list: ti.types.ndarray(),
    tile_ranges: ti.types.ndarray(),
    t_final: ti.types.ndarray(),  # [V, H, W] out
    depth_acc: ti.types.ndarray(),  # [V, H, W] out
    last: ti.types.ndarray(),  # [V, H, W] out
    tile: ti.template(), tiles_x: ti.i32, tiles_y: ti.i32,
    opacity: ti.f64, alpha_min: ti.f64, alpha_max: ti.f64, power_min: ti.f64, t_min: ti.f64,
    dtype: ti.template(),
    behind: ti.template(),  # True: t_final holds the transmittance the Gaussians are composited behind
):
    """Same compositing as _composite_forward, Gaussian-major inside a tile (CPU): one thread
    per tile walks the tile's list front to back and only visits the pixels inside each
    Gaussian's cutoff box, keeping per-pixel T and D in the output arrays. Each row of the tile
    counts its pixels not yet terminated: a row with none is passed over (in an opaque body most
    of the pixels a Gaussian's box holds have terminated before it comes)."""
    n_views, height, width = t_final.shape[0], t_final.shape[1], t_final.shape[2]
    for v, t in ti.ndrange(n_views, tiles_x * tiles_y):
        ty = t // tiles_x
        tx = t - ty * tiles_x
        x0 = tx * tile
        y0 = ty * tile
        x1 = ti.min(x0 + tile, width) - 1
        y1 = ti.min(y0 + tile, height) - 1
        gid = (v * tiles_y + ty) * tiles_x + tx
        start = tile_ranges[gid, 0]
        end = tile_ranges[gid, 1]
        for py, px in ti.ndrange((y0, y1 + 1), (x0, x1 + 1)):
            if ti.static(not behind):
                t_final[v, py, px] = ti.cast(1.0, dtype)
            depth_acc[v, py, px] = ti.cast(0.0, dtype)
            last[v, py, px] = start
        remaining = (x1 - x0 + 1) * (y1 - y0 + 1)  # pixels not yet terminated
        alive = ti.Vector.zero(ti.i32, tile)  # per row of the tile
        for r in range(y1 - y0 + 1):
            alive[r] = x1 - x0 + 1
        if ti.static(behind):  # a pixel terminated in front of these Gaussians is not visited
            remaining = 0
            for r in range(y1 - y0 + 1):
                alive[r] = 0
                for px in range(x0, x1 + 1):
                    if t_final[v, y0 + r, px] >= ti.cast(t_min, dtype):
                        alive[r] += 1
                remaining += alive[r]
        for k in range(start, end):
            if remaining == 0:
                break
            g = point_list[k]
            mu_u = gauss[g, 0]
            mu_v = gauss[g, 1]
            qa = gauss[g, 2]
            qb = gauss[g, 3]
            qc = gauss[g, 4]
            z = gauss[g, 5]
            u_first, u_last = _box_range(mu_u, half[g, 0], x0, x1, dtype)
            v_first, v_last = _box_range(mu_v, half[g, 1], y0, y1, dtype)
            for py in range(v_first, v_last + 1):
                if alive[py - y0] == 0:
                    continue
                dv = mu_v - (ti.cast(py, dtype) + ti.cast(0.5, dtype))
                for px in range(u_first, u_last + 1):
                    trans = t_final[v, py, px]
                    if trans >= ti.cast(t_min, dtype):  # terminated pixels cost one load
                        du = mu_u - (ti.cast(px, dtype) + ti.cast(0.5, dtype))
                        power = -ti.cast(0.5, dtype) * (qa * du * du + qc * dv * dv) - qb * du * dv
                        if power >= ti.cast(power_min, dtype):
                            a = ti.min(ti.cast(alpha_max, dtype), ti.cast(opacity, dtype) * ti.exp(power))
                            if a >= ti.cast(alpha_min, dtype):
                                # the tile is this thread's alone: a plain store, not the atomic add += makes
                                depth_acc[v, py, px] = depth_acc[v, py, px] + a * trans * z
                                trans *= ti.cast(1.0, dtype) - a
                                t_final[v, py, px] = trans
                                last[v, py, px] = k + 1
                                if trans < ti.cast(t_min, dtype):
                                    remaining -= 1
                                    alive[py - y0] -= 1


@ti.func
def _add_pixel_adjoint(acc, grad_alpha: ti.template(), grad_depth_acc: ti.template(), v, py, px,
                       da_alpha, da_depth, dz_depth, dpower_da, du, dv, qa, qb, qc,
                       n_channels: ti.template(), dtype: ti.template()):
    """acc [C, 6] plus pixel (py, px)'s share of an entry's gradient for each channel c: d/d(mean_u,
    mean_v, A, B, C, z) of its alpha and D (module docstring), from d alpha / d a_k, d D / d a_k,
    d D / d z_k and d a_k / d power_k."""
    d_mu_u = -(qa * du + qb * dv)
    d_mu_v = -(qb * du + qc * dv)
    for c in ti.static(range(n_channels)):
        ga = grad_alpha[c, v, py, px]
        gd = grad_depth_acc[c, v, py, px]
        gp = (ga * da_alpha + gd * da_depth) * dpower_da
        acc[c, 0] += gp * d_mu_u
        acc[c, 1] += gp * d_mu_v
        acc[c, 2] += -ti.cast(0.5, dtype) * gp * du * du
        acc[c, 3] += -gp * du * dv
        acc[c, 4] += -ti.cast(0.5, dtype) * gp * dv * dv
        acc[c, 5] += gd * dz_depth
    return acc


@ti.kernel
def _composite_backward_tiles(
    gauss: ti.types.ndarray(),  # [V*N, 6]
    half: ti.types.ndarray(),  # [V*N, 2]
    point_list: ti.types.ndarray(),
    tile_ranges: ti.types.ndarray(),
    t_final: ti.types.ndarray(),  # [V, H, W]
    last: ti.types.ndarray(),  # [V, H, W]
    grad_alpha: ti.types.ndarray(),  # [C, V, H, W]
    grad_depth_acc: ti.types.ndarray(),  # [C, V, H, W]
    trans_scratch: ti.types.ndarray(),  # [V, H, W] per-pixel T while walking back
    suffix_scratch: ti.types.ndarray(),  # [V, H, W] per-pixel S while walking back
    grad_gauss: ti.types.ndarray(),  # [C, V*N, 6] out (accumulated)
    tile: ti.i32, tiles_x: ti.i32, tiles_y: ti.i32,
    opacity: ti.f64, alpha_min: ti.f64, alpha_max: ti.f64, power_min: ti.f64,
    n_channels: ti.template(), dtype: ti.template(),
):
    """Same backward as _composite_backward, Gaussian-major inside a tile (CPU): the tile's list
    is walked back to front once; each entry's gradient is summed over the tile's pixels in
    registers and added to the Gaussian once per tile (atomic adds per entry, not per pixel), where
    the entry composited any of them."""
    n_views, height, width = t_final.shape[0], t_final.shape[1], t_final.shape[2]
    for v, t in ti.ndrange(n_views, tiles_x * tiles_y):
        ty = t // tiles_x
        tx = t - ty * tiles_x
        x0 = tx * tile
        y0 = ty * tile
        x1 = ti.min(x0 + tile, width) - 1
        y1 = ti.min(y0 + tile, height) - 1
        gid = (v * tiles_y + ty) * tiles_x + tx
        start = tile_ranges[gid, 0]
        stop = start
        for py, px in ti.ndrange((y0, y1 + 1), (x0, x1 + 1)):
            trans_scratch[v, py, px] = t_final[v, py, px]
            suffix_scratch[v, py, px] = ti.cast(0.0, dtype)
            stop = ti.max(stop, last[v, py, px])
        for kk in range(stop - start):
            k = stop - 1 - kk
            g = point_list[k]
            mu_u = gauss[g, 0]
            mu_v = gauss[g, 1]
            qa = gauss[g, 2]
            qb = gauss[g, 3]
            qc = gauss[g, 4]
            z = gauss[g, 5]
            acc = ti.Matrix.zero(dtype, n_channels, 6)
            touched = 0  # the tile's pixels this entry composited
            u_first, u_last = _box_range(mu_u, half[g, 0], x0, x1, dtype)
            v_first, v_last = _box_range(mu_v, half[g, 1], y0, y1, dtype)
            for py in range(v_first, v_last + 1):
                dv = mu_v - (ti.cast(py, dtype) + ti.cast(0.5, dtype))
                for px in range(u_first, u_last + 1):
                    if k < last[v, py, px]:
                        du = mu_u - (ti.cast(px, dtype) + ti.cast(0.5, dtype))
                        power = -ti.cast(0.5, dtype) * (qa * du * du + qc * dv * dv) - qb * du * dv
                        if power >= ti.cast(power_min, dtype):
                            raw = ti.cast(opacity, dtype) * ti.exp(power)
                            a = ti.min(ti.cast(alpha_max, dtype), raw)
                            if a >= ti.cast(alpha_min, dtype):
                                one_minus = ti.cast(1.0, dtype) - a
                                trans = trans_scratch[v, py, px] / one_minus  # T_k
                                suffix = suffix_scratch[v, py, px]
                                dpower_da = a if raw < ti.cast(alpha_max, dtype) else ti.cast(0.0, dtype)
                                acc = _add_pixel_adjoint(acc, grad_alpha, grad_depth_acc, v, py, px,
                                                         t_final[v, py, px] / one_minus,
                                                         trans * z - suffix / one_minus, a * trans, dpower_da,
                                                         du, dv, qa, qb, qc, n_channels, dtype)
                                trans_scratch[v, py, px] = trans
                                suffix_scratch[v, py, px] = suffix + a * trans * z
                                touched += 1
            # an entry that composited none of the tile's pixels (half of those a tile walks, in an
            # opaque body) adds zeros: its 18 atomic adds are passed over
            if touched > 0:
                for c in ti.static(range(n_channels)):
                    for j in ti.static(range(6)):
                        grad_gauss[c, g, j] += acc[c, j]


def _ti_dtype(dtype: torch.dtype):
    return ti.f64 if dtype == torch.float64 else ti.f32


def _kernel_constants(cfg: RenderConfig) -> dict:
    return dict(opacity=float(cfg.opacity), alpha_min=float(cfg.alpha_min), alpha_max=float(cfg.alpha_max),
                power_min=-0.5 * float(cfg.cutoff_sigma) ** 2)


def ensure_runtime(cfg: RenderConfig) -> str:
    """Start (or join) the shared Taichi runtime on the configured device."""
    return init_taichi(resolve_device(cfg.device))


def use_tile_kernels(cfg: RenderConfig) -> bool:
    """Gaussian-major tile kernels on CPU (few threads, no atomics per pixel); pixel-parallel
    kernels on CUDA (many threads), unless RenderConfig.kernel names one."""
    if cfg.kernel != "auto":
        return cfg.kernel == "tile"
    return ensure_runtime(cfg) == "cpu"


def composite_forward(params: torch.Tensor, bins: TileBins, n_views: int, height: int, width: int,
                      cfg: RenderConfig,
                      behind: torch.Tensor | None = None,  # [V, H, W] transmittance in front of the Gaussians
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """params: [V*N, 6] (detached). Returns final transmittance, accumulated depth D [V, H, W]
    and the per-pixel end of the contributing list [V, H, W] (int32). With ``behind`` the Gaussians
    are composited behind that transmittance (what other Gaussians in front left): the final
    transmittance is the product of both, to within the early stop (a pixel stops once the product
    is under transmittance_min, so pixels already opaque cost nothing), and D the Gaussians' own
    contributions, each weighted by the transmittance in front of it."""
    ensure_runtime(cfg)
    params = params.detach().contiguous()
    opts = dict(dtype=params.dtype, device=params.device)
    t_final = (torch.ones(n_views, height, width, **opts) if behind is None
               else behind.to(**opts).contiguous().clone())
    depth_acc = torch.zeros(n_views, height, width, **opts)
    last = torch.zeros(n_views, height, width, dtype=torch.int32, device=params.device)
    if bins.pair_count > 0:
        c = _kernel_constants(cfg)
        if use_tile_kernels(cfg):
            _composite_forward_tiles(params, bins.half_extent, bins.point_list, bins.tile_ranges, t_final, depth_acc,
                                     last, bins.tile_size, bins.tiles_x, bins.tiles_y, c["opacity"], c["alpha_min"],
                                     c["alpha_max"], c["power_min"], float(cfg.transmittance_min),
                                     _ti_dtype(params.dtype), behind is not None)
            return t_final, depth_acc, last
        _composite_forward(params, bins.point_list, bins.tile_ranges, t_final, depth_acc, last,
                           bins.tile_size, bins.tiles_x, bins.tiles_y, c["opacity"], c["alpha_min"],
                           c["alpha_max"], c["power_min"], float(cfg.transmittance_min), _ti_dtype(params.dtype),
                           behind is not None)
    return t_final, depth_acc, last


def composite_backward(params: torch.Tensor, bins: TileBins, t_final: torch.Tensor, last: torch.Tensor,
                       grad_alpha: torch.Tensor, grad_depth_acc: torch.Tensor, cfg: RenderConfig) -> torch.Tensor:
    """grad_alpha, grad_depth_acc: [C, V, H, W]. Returns dL_c/dparams: [C, V*N, 6]."""
    ensure_runtime(cfg)
    params = params.detach().contiguous()
    grad = torch.zeros(grad_alpha.shape[0], params.shape[0], 6, dtype=params.dtype, device=params.device)
    if bins.pair_count > 0:
        c = _kernel_constants(cfg)
        if use_tile_kernels(cfg):
            _composite_backward_tiles(params, bins.half_extent, bins.point_list, bins.tile_ranges,
                                      t_final.contiguous(), last.contiguous(),
                                      grad_alpha.to(params.dtype).contiguous(),
                                      grad_depth_acc.to(params.dtype).contiguous(),
                                      torch.empty_like(t_final), torch.empty_like(t_final), grad,
                                      bins.tile_size, bins.tiles_x, bins.tiles_y, c["opacity"], c["alpha_min"],
                                      c["alpha_max"], c["power_min"], int(grad_alpha.shape[0]),
                                      _ti_dtype(params.dtype))
            return grad
        _composite_backward(params, bins.point_list, bins.tile_ranges, t_final.contiguous(), last.contiguous(),
                            grad_alpha.to(params.dtype).contiguous(), grad_depth_acc.to(params.dtype).contiguous(),
                            grad, bins.tile_size, bins.tiles_x, bins.tiles_y, c["opacity"], c["alpha_min"],
                            c["alpha_max"], c["power_min"], _ti_dtype(params.dtype))
    return grad


class _Composite(torch.autograd.Function):
    """Autograd wrapper: params [V*N, 6] -> (alpha, D) [V, H, W]; backward by the Taichi kernel."""

    @staticmethod
    def forward(ctx, params, bins, n_views, height, width, cfg):  # noqa: D401
        t_final, depth_acc, last = composite_forward(params, bins, n_views, height, width, cfg)
        ctx.bins, ctx.cfg = bins, cfg
        ctx.save_for_backward(params.detach(), t_final, last)
        return 1.0 - t_final, depth_acc

    @staticmethod
    def backward(ctx, grad_alpha, grad_depth_acc):
        params, t_final, last = ctx.saved_tensors
        if grad_alpha is None:
            grad_alpha = torch.zeros_like(t_final)
        if grad_depth_acc is None:
            grad_depth_acc = torch.zeros_like(t_final)
        grad = composite_backward(params, ctx.bins, t_final, last, grad_alpha[None], grad_depth_acc[None], ctx.cfg)
        return grad[0], None, None, None, None, None


def composite(params: torch.Tensor, bins: TileBins, n_views: int, height: int, width: int,
              cfg: RenderConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Differentiable tile compositing: alpha [V, H, W] and accumulated depth D [V, H, W]."""
    return _Composite.apply(params, bins, n_views, height, width, cfg)
