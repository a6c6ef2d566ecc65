"""Tests of physmorph.render: tile rasterizer vs dense reference, finite differences in float64,
analytic footprints and silhouettes, occlusion and losses (edge cases: test_render_edge_cases.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from physmorph.base.cameras import ring_cameras
from physmorph.settings.render import RenderConfig
from physmorph.render.rasterizer import composite
from physmorph.render.projection import covariance_from_F
from physmorph.render.dense import dense_composite
from physmorph.render.losses import match_gradients
from physmorph.render.api import coverage_behind, render_and_grad, render_views
from physmorph.render.api import splat
from physmorph.render.losses import alpha_mse, dt_loss, soft_iou_loss
from physmorph.render.projection import CameraTensors, project_gaussians
from physmorph.render.projection_kernels import project_backward, project_forward
from physmorph.render.rasterizer import composite_backward, composite_forward
from physmorph.render.tiles import bin_gaussians

from render_cases import (SMOOTH, disk_target, fibonacci_sphere, front_camera, random_scene, small_cameras,
                          torch_scene)

# ---------------------------------------------------------------------------------------------
# F -> Sigma and projection


def test_covariance_from_F_formula_and_gradcheck():
    rng = np.random.default_rng(0)
    F = torch.tensor(rng.normal(size=(4, 3, 3)), dtype=torch.float64, requires_grad=True)
    sigma = covariance_from_F(F, 0.37)
    ref = 0.37 ** 2 * np.einsum("nij,nkj->nik", F.detach().numpy(), F.detach().numpy())
    np.testing.assert_allclose(sigma.detach().numpy(), ref, rtol=1e-12)
    assert torch.autograd.gradcheck(lambda f: covariance_from_F(f, 0.37), (F,), eps=1e-6, atol=1e-8)


def test_projection_gradcheck():
    cams = small_cameras(2)
    cfg = RenderConfig(**SMOOTH)
    x, F = random_scene(3, 1)
    ct = CameraTensors.from_cameras(cams, torch.float64, "cpu")
    xt = torch.tensor(x, requires_grad=True)
    Ft = torch.tensor(F, requires_grad=True)
    fn = lambda a, b: project_gaussians(a, covariance_from_F(b, 0.3), ct, cfg).params  # noqa: E731
    assert torch.autograd.gradcheck(fn, (xt, Ft), eps=1e-6, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-4)])
def test_projection_kernels_equal_the_torch_projection_and_autograd(dtype, tol):
    """The Taichi projection render_and_grad uses, forward against project_gaussians and its
    reverse (three upstream gradients at once) against autograd through project_gaussians and
    covariance_from_F, on a scene with entries behind the camera, off screen (the Jacobian's
    clamp acting), per-Gaussian sigma0 and low_pass 0; the upstream gradients zero for some
    Gaussians in some views (as for the occluded ones, which the reverse passes over) and in one
    loss only for others."""
    cams = ring_cameras(3, width=32, height=24, distance=4.0, fov_y_deg=40.0)
    rng = np.random.default_rng(11)
    x, F = random_scene(40, 3, spread=5.0, aniso=0.4)  # a spread past the cameras' distance
    sigma0 = torch.tensor(rng.uniform(0.1, 0.5, size=40), dtype=dtype)
    for low_pass in (0.3, 0.0):
        cfg = RenderConfig(low_pass=low_pass)
        ct = CameraTensors.from_cameras(cams, dtype, "cpu")
        xt = torch.tensor(x, dtype=dtype, requires_grad=True)
        Ft = torch.tensor(F, dtype=dtype, requires_grad=True)
        proj = project_gaussians(xt, covariance_from_F(Ft, sigma0), ct, cfg)
        assert not proj.visible.all() and proj.visible.any()
        assert (proj.params[..., 5] < ct.near).any()  # some entries behind the near plane
        params, half, visible = project_forward(xt, Ft, sigma0, ct, cfg)
        assert torch.equal(visible, proj.visible)
        for got, ref in ((params, proj.params.detach()), (half, proj.half_extent)):
            scale = ref.abs().amax(dim=(0, 1))
            assert ((got - ref).abs().amax(dim=(0, 1)) <= tol * scale).all()
        g = torch.tensor(rng.normal(size=(3,) + tuple(proj.params.shape)), dtype=dtype)
        g[:, torch.as_tensor(rng.random(size=proj.params.shape[:2]) < 0.5)] = 0.0  # [V, N] pairs without a gradient
        g[1, torch.as_tensor(rng.random(size=proj.params.shape[:2]) < 0.3)] = 0.0  # one loss's only
        ref_x, ref_F = [], []
        for c in range(3):
            gx, gF = torch.autograd.grad(proj.params, (xt, Ft), grad_outputs=g[c], retain_graph=True)
            ref_x.append(gx)
            ref_F.append(gF)
        gx, gF = project_backward(xt, Ft, sigma0, ct, cfg, g)
        no_x, gF_only = project_backward(xt, Ft, sigma0, ct, cfg, g, want_grad_x=False)
        assert no_x is None
        assert (gF_only - gF).abs().max() <= tol * gF.abs().max()  # float32: the compiler's order
        for c in range(3):
            scale_x, scale_F = ref_x[c].abs().max(), ref_F[c].abs().max()
            assert (gx[c] - ref_x[c]).abs().max() <= tol * scale_x
            assert (gF[c] - ref_F[c]).abs().max() <= tol * scale_F


def test_projection_of_point_matches_cameras_project():
    cams = small_cameras(3)
    x, F = random_scene(10, 2)
    _, _, _, proj = torch_scene(x, F, 0.3, cams, RenderConfig(dtype="float64"), requires_grad=False)
    uv, z = cams.project(x)
    np.testing.assert_allclose(proj.params[..., :2].numpy(), uv, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(proj.params[..., 5].numpy(), z, rtol=1e-12)


# ---------------------------------------------------------------------------------------------
# Tile rasterizer vs dense reference


@pytest.mark.parametrize("kernel", ["tile", "pixel"])
@pytest.mark.parametrize("dtype,tol", [("float64", 1e-10), ("float32", 2e-4)])
def test_tile_rasterizer_matches_dense_forward_and_backward(dtype, tol, kernel):
    """Default thresholds (3-sigma cutoff, 1/255, 0.99 clamp, early stop): tile path == dense path,
    for both loop orders of the rasterizer."""
    cams = small_cameras(3, width=37, height=29)  # not a multiple of the tile size
    cfg = RenderConfig(dtype=dtype, tile_size=8, kernel=kernel)
    x, F = random_scene(40, 3, spread=2.0)
    F[0] *= 4.0  # one big Gaussian spanning many tiles
    x[1] = [0.0, 0.0, 0.0]
    xt, Ft, ct, proj = torch_scene(x, F, 0.35, cams, cfg)
    sp_bins = splat(xt, Ft, torch.tensor(0.35, dtype=xt.dtype), ct, cfg).bins
    assert sp_bins.pair_count > 0
    alpha, dacc = composite(proj.params.reshape(-1, 6), sp_bins, 3, cams.height, cams.width, cfg)
    alpha_ref, dacc_ref = dense_composite(proj.params, proj.visible, cams.height, cams.width, cfg)
    assert alpha.max() > 0.9 and alpha.min() < 0.01  # the scene has opaque and empty pixels
    scale = float(dacc_ref.detach().abs().max())
    np.testing.assert_allclose(alpha.detach().numpy(), alpha_ref.detach().numpy(), atol=tol)
    np.testing.assert_allclose(dacc.detach().numpy() / scale, dacc_ref.detach().numpy() / scale, atol=tol)

    gen = torch.Generator().manual_seed(0)
    wa = torch.rand(alpha.shape, generator=gen, dtype=alpha.dtype) - 0.5
    wd = torch.rand(alpha.shape, generator=gen, dtype=alpha.dtype) - 0.5
    grads = torch.autograd.grad((alpha * wa).sum() + (dacc * wd).sum(), (xt, Ft), retain_graph=True)
    grads_ref = torch.autograd.grad((alpha_ref * wa).sum() + (dacc_ref * wd).sum(), (xt, Ft))
    for g, r in zip(grads, grads_ref):
        assert float(r.abs().max()) > 0
        np.testing.assert_allclose(g.numpy() / float(r.abs().max()), r.numpy() / float(r.abs().max()),
                                   atol=50 * tol)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])  # float32: the radix depth order
def test_tile_bins_equal_a_per_pair_reference(dtype):
    """bin_gaussians (view by view) against listing every (view, Gaussian, tile) pair and sorting
    each tile's list by depth, ties by index: the same list, the same ranges, empty views included."""
    rng = np.random.default_rng(11)
    V, N, W, H, tile = 3, 60, 50, 37, 8
    means = torch.as_tensor(rng.uniform(-10, 60, (V, N, 2)))
    half = torch.as_tensor(rng.uniform(0, 12, (V, N, 2)))
    depth = torch.as_tensor(rng.integers(0, 5, (V, N)).astype(float)).to(dtype)  # ties
    visible = torch.as_tensor(rng.random((V, N)) < 0.7)
    visible[1] = False  # a view with nothing in it
    bins = bin_gaussians(means, half, depth, visible, W, H, tile)
    tx, ty = -(-W // tile), -(-H // tile)
    want = {}
    for v in range(V):
        for i in np.argsort(depth[v].numpy(), kind="stable"):
            if not visible[v, i]:
                continue
            (mu, mv), (hu, hv) = means[v, i].tolist(), half[v, i].tolist()
            for y in range(int(np.clip(np.floor((mv - hv) / tile), 0, ty - 1)), int(np.clip(np.floor((mv + hv) / tile), 0, ty - 1)) + 1):
                for x in range(int(np.clip(np.floor((mu - hu) / tile), 0, tx - 1)), int(np.clip(np.floor((mu + hu) / tile), 0, tx - 1)) + 1):
                    want.setdefault((v * ty + y) * tx + x, []).append(v * N + int(i))
    ranges = bins.tile_ranges.numpy()
    assert ranges.shape == (V * ty * tx, 2) and ranges[0, 0] == 0 and ranges[-1, 1] == bins.pair_count
    for gid in range(V * ty * tx):
        assert bins.point_list[ranges[gid, 0]:ranges[gid, 1]].tolist() == want.get(gid, []), gid


def test_tile_and_pixel_kernels_agree_on_a_dense_scene():
    """Many overlapping Gaussians so early termination (T < 1e-4) is active in most pixels."""
    cams = small_cameras(2, width=64, height=48)
    x = fibonacci_sphere(2000, 2.0)
    F = np.eye(3) + 0.2 * np.random.default_rng(11).normal(size=(2000, 3, 3))
    out = {}
    for kernel in ("tile", "pixel"):
        cfg = RenderConfig(dtype="float64", kernel=kernel)
        xt, Ft, ct, _ = torch_scene(x, F, 0.12, cams, cfg, requires_grad=False)
        sp = splat(xt, Ft, torch.tensor(0.12, dtype=torch.float64), ct, cfg)
        t_final, dacc, last = composite_forward(sp.params, sp.bins, 2, cams.height, cams.width, cfg)
        g = torch.rand(2, 2, 2, cams.height, cams.width, dtype=torch.float64,
                       generator=torch.Generator().manual_seed(2))
        grad = composite_backward(sp.params, sp.bins, t_final, last, g[:, 0], g[:, 1], cfg)
        out[kernel] = (t_final, dacc, last, grad)
    assert float(out["tile"][0].min()) < 1e-4  # early termination happened
    for a, b in zip(out["tile"], out["pixel"]):
        np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("kernel", ["tile", "pixel"])
def test_multichannel_backward_equals_single_channel_calls(kernel):
    cams = small_cameras(2)
    cfg = RenderConfig(dtype="float64", tile_size=8, kernel=kernel)
    x, F = random_scene(15, 4)
    xt, Ft, ct, _ = torch_scene(x, F, 0.3, cams, cfg, requires_grad=False)
    sp = splat(xt, Ft, torch.tensor(0.3, dtype=torch.float64), ct, cfg)
    t_final, _, last = composite_forward(sp.params, sp.bins, 2, cams.height, cams.width, cfg)
    g = torch.rand(2, 2, 2, cams.height, cams.width, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    both = composite_backward(sp.params, sp.bins, t_final, last, g[:, 0], g[:, 1], cfg)
    for c in range(2):
        one = composite_backward(sp.params, sp.bins, t_final, last, g[c:c + 1, 0], g[c:c + 1, 1], cfg)
        np.testing.assert_allclose(both[c].numpy(), one[0].numpy(), rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("kernel", ["tile", "pixel"])
def test_the_reverse_view_by_view_equals_both_passes_over_every_view(kernel):
    """render_and_grad's reverse (api.reverse_by_view: each view's bins, TileBins.view, through the
    rasterizer's backward, then the projection's reverse, ProjectionReverse, its views added one
    by one) against composite_backward and project_backward over all views at once, in float32 on
    a dense scene of three views (entries shared by tiles: the rasterizer's sums are in another
    order only across threads). The projection's sums are per Gaussian: equal to the bit."""
    from physmorph.render.api import reverse_by_view
    from physmorph.render.projection_kernels import ProjectionReverse

    cams = small_cameras(3, width=40, height=32)
    cfg = RenderConfig(kernel=kernel, tile_size=8)
    x, F = random_scene(300, 7)
    xt, Ft, ct, _ = torch_scene(x, F, 0.25, cams, cfg, requires_grad=False)
    s0 = torch.tensor(0.25)
    sp = splat(xt, Ft, s0, ct, cfg)
    t_final, _, last = composite_forward(sp.params, sp.bins, 3, cams.height, cams.width, cfg)
    g = torch.rand(2, 3, 3, cams.height, cams.width, generator=torch.Generator().manual_seed(3))
    every = composite_backward(sp.params, sp.bins, t_final, last, g[0], g[1], cfg)  # [3, 3 N, 6]
    n = len(x)
    for v in range(3):
        bins, first = sp.bins.view(v, n)
        one = composite_backward(sp.params[v * n:(v + 1) * n], bins, t_final[v:v + 1], last[v:v + 1] - first,
                                 g[0][:, v:v + 1], g[1][:, v:v + 1], cfg)
        np.testing.assert_allclose(one.numpy(), every[:, v * n:(v + 1) * n].numpy(), rtol=1e-5,
                                   atol=1e-6 * float(every.abs().max()))
    assert sum(sp.bins.view(v, n)[0].pair_count for v in range(3)) == sp.bins.pair_count
    g_params = every.reshape(3, 3, n, 6)
    ref_x, ref_F = project_backward(xt, Ft, s0, ct, cfg, g_params)
    by_view = ProjectionReverse(xt, Ft, s0, 3)
    for v in range(3):
        by_view.add(ct.view(v), cfg, g_params[:, v:v + 1])
    got_x, got_F = by_view.result()
    assert torch.equal(got_x, ref_x) and torch.equal(got_F, ref_F)
    gx, gF = reverse_by_view(xt, Ft, s0, ct, sp, t_final, last, lambda v: (g[0][:, v:v + 1], g[1][:, v:v + 1]), 3, cfg, True)
    scale = float(ref_F.abs().max())
    assert float((gF - ref_F).abs().max()) <= 1e-5 * scale and gx.shape == ref_x.shape


# ---------------------------------------------------------------------------------------------
# Finite differences in float64 of the full pipeline


def _loss_with_fixed_weights(x, F, sigma0, cams, target, cfg, weights):
    res = render_and_grad(x, F, sigma0, cams, target, cfg)
    return res.losses["dt"] + weights["iou"] * res.losses["iou"] + weights["depth"] * res.losses["depth"]


@pytest.mark.parametrize("fractions", [(0.0, 0.0), (0.5, 0.25)])
def test_render_and_grad_matches_central_differences(fractions):
    cams = small_cameras(2)
    target = disk_target(cams, depth=10.2)
    cfg = RenderConfig(**SMOOTH, iou_fraction=fractions[0], depth_fraction=fractions[1], depth_min_alpha=1e-3)
    x, F = random_scene(5, 5, spread=1.0)
    res = render_and_grad(x, F, 0.4, cams, target, cfg, want_grad_x=True)
    if fractions[0] > 0:
        assert res.weights["F_iou"] > 0 and res.weights["F_depth"] > 0
    assert np.abs(res.grad_F).max() > 0 and np.abs(res.grad_x).max() > 0
    # dL/dF uses the F weights, dL/dx the x weights: check each against its own weighted loss.
    wF = {k: res.weights[f"F_{k}"] for k in ("iou", "depth")}
    wx = {k: res.weights[f"x_{k}"] for k in ("iou", "depth")}
    eps = 1e-6
    rng = np.random.default_rng(0)
    for _ in range(6):
        i, a, b = rng.integers(5), rng.integers(3), rng.integers(3)
        Fp, Fm = F.copy(), F.copy()
        Fp[i, a, b] += eps
        Fm[i, a, b] -= eps
        fd = (_loss_with_fixed_weights(x, Fp, 0.4, cams, target, cfg, wF)
              - _loss_with_fixed_weights(x, Fm, 0.4, cams, target, cfg, wF)) / (2 * eps)
        assert fd == pytest.approx(res.grad_F[i, a, b], rel=1e-5, abs=1e-7 * np.abs(res.grad_F).max())
    for _ in range(6):
        i, a = rng.integers(5), rng.integers(3)
        xp, xm = x.copy(), x.copy()
        xp[i, a] += eps
        xm[i, a] -= eps
        fd = (_loss_with_fixed_weights(xp, F, 0.4, cams, target, cfg, wx)
              - _loss_with_fixed_weights(xm, F, 0.4, cams, target, cfg, wx)) / (2 * eps)
        assert fd == pytest.approx(res.grad_x[i, a], rel=1e-5, abs=1e-7 * np.abs(res.grad_x).max())


def test_adaptive_gradient_matching_sets_the_norm_ratio():
    cams = small_cameras(2)
    target = disk_target(cams)
    x, F = random_scene(8, 6)
    base = dict(dtype="float64", tile_size=8)
    g_dt = render_and_grad(x, F, 0.4, cams, target, RenderConfig(**base, iou_fraction=0, depth_fraction=0)).grad_F
    for frac_iou, frac_depth in ((0.3, 0.0), (0.0, 0.7)):
        res = render_and_grad(x, F, 0.4, cams, target,
                              RenderConfig(**base, iou_fraction=frac_iou, depth_fraction=frac_depth))
        aux = res.grad_F - g_dt
        assert np.linalg.norm(aux) == pytest.approx((frac_iou + frac_depth) * np.linalg.norm(g_dt), rel=1e-9)
    # Unit behaviour: zero auxiliary gradient -> weight 0, no NaN.
    cfg = RenderConfig(iou_fraction=0.5, depth_fraction=0.5)
    g = {"dt": torch.ones(3), "iou": torch.zeros(3), "depth": torch.tensor([0.0, 3.0, 4.0])}
    total, w = match_gradients(g, cfg)
    assert w["iou"] == 0.0 and w["depth"] == pytest.approx(0.5 * np.sqrt(3) / 5)
    assert torch.allclose(total, g["dt"] + w["depth"] * g["depth"])


# ---------------------------------------------------------------------------------------------
# Known cases


def test_isotropic_gaussian_footprint_is_analytic():
    cams = front_camera(48, 40, f=60.0, distance=10.0)
    sigma0 = 0.5
    cfg = RenderConfig(dtype="float64", tile_size=8)
    alpha, depth = render_views(np.zeros((1, 3)), np.eye(3)[None], sigma0, cams, cfg)
    s2 = (60.0 * sigma0 / 10.0) ** 2 + cfg.low_pass  # (f sigma0 / z)^2 + low-pass, pixels^2
    jj, ii = np.meshgrid(np.arange(40) + 0.5, np.arange(48) + 0.5, indexing="ij")
    m2 = ((ii - 24.0) ** 2 + (jj - 20.0) ** 2) / s2
    expect = np.minimum(cfg.opacity * np.exp(-0.5 * m2), cfg.alpha_max)
    expect = np.where((m2 <= cfg.cutoff_sigma ** 2) & (expect >= cfg.alpha_min), expect, 0.0)
    np.testing.assert_allclose(alpha[0], expect, atol=1e-12)
    np.testing.assert_allclose(depth[0][alpha[0] > 0], 10.0, rtol=1e-12)


def test_sphere_silhouette_matches_analytic_disk():
    """A shell of particles on a sphere renders as the disk of radius f R / sqrt(d^2 - R^2)."""
    radius, distance, f, size = 4.0, 30.0, 150.0, 64
    cams = front_camera(size, size, f=f, distance=distance)
    n = 3000
    spacing = np.sqrt(4 * np.pi * radius ** 2 / n)
    sigma0 = 0.7 * spacing
    x = fibonacci_sphere(n, radius)
    alpha, depth = render_views(x, np.broadcast_to(np.eye(3), (n, 3, 3)), sigma0, cams, RenderConfig())
    r_px = f * radius / np.sqrt(distance ** 2 - radius ** 2)
    sigma_px = f * sigma0 / (distance - radius)
    jj, ii = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5, indexing="ij")
    r = np.hypot(ii - size / 2, jj - size / 2)
    inside = alpha[0] > 0.5
    r_eq = np.sqrt(inside.sum() / np.pi)
    assert abs(r_eq - r_px) < 2.0 * sigma_px + 0.5
    assert alpha[0][r < r_px - 3 * sigma_px].min() > 0.99  # opaque interior
    assert alpha[0][r > r_px + 4 * sigma_px].max() < 1e-6  # nothing far outside
    # Depth at the centre is the near surface, distance - R (within a Gaussian's depth spread).
    centre = depth[0][r < 2.0]
    assert np.all(np.abs(centre - (distance - radius)) < 0.3)


def test_occlusion_nearest_surface_wins_and_input_order_is_irrelevant():
    cams = front_camera(32, 32, f=40.0, distance=10.0)
    cfg = RenderConfig(dtype="float64", tile_size=8, opacity=0.99)
    x = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, -2.0]])  # near (z_cam = 8) and far (z_cam = 12)
    F = np.stack([np.eye(3) * 3.0, np.eye(3) * 3.0])
    a1, d1 = render_views(x, F, 0.5, cams, cfg)
    a2, d2 = render_views(x[::-1].copy(), F, 0.5, cams, cfg)
    np.testing.assert_allclose(a1, a2, atol=1e-14)
    np.testing.assert_allclose(d1, d2, atol=1e-12)
    # At the centre pixel both Gaussians have a = alpha_max: D = a z1 + (1 - a) a z2, alpha = 1 - (1-a)^2.
    a = cfg.alpha_max
    centre = (0, 15, 15)
    pa = min(a, 0.99 * np.exp(-0.5 * 0.5 / ((40 * 1.5 / 8) ** 2 + 0.3)))
    pb = min(a, 0.99 * np.exp(-0.5 * 0.5 / ((40 * 1.5 / 12) ** 2 + 0.3)))
    assert a1[centre] == pytest.approx(1 - (1 - pa) * (1 - pb), rel=1e-12)
    assert d1[centre] * a1[centre] == pytest.approx(pa * 8.0 + (1 - pa) * pb * 12.0, rel=1e-12)
    assert d1[centre] < 8.1  # the nearest surface dominates the expected depth


# ---------------------------------------------------------------------------------------------
# Losses and metric


def test_alpha_mse_and_losses_match_numpy():
    rng = np.random.default_rng(7)
    a, t, sdt = rng.uniform(size=(3, 3, 10, 12))
    at, tt, st = (torch.tensor(v) for v in (a, t, sdt))
    np.testing.assert_allclose(alpha_mse(at, tt).numpy(), ((a - t) ** 2).mean(axis=(1, 2)))
    assert float(dt_loss(at, st)) == pytest.approx((a * sdt).mean() / 10)
    inter, union = (a * t).sum((1, 2)), (a + t - a * t).sum((1, 2))
    assert float(soft_iou_loss(at, tt)) == pytest.approx((1 - inter / union).mean(), rel=1e-6)
    # Empty render against an empty target: perfect overlap, loss 0.
    assert float(soft_iou_loss(torch.zeros(1, 4, 4), torch.zeros(1, 4, 4))) == pytest.approx(0.0)


def test_dt_loss_is_resolution_independent():
    x = fibonacci_sphere(1500, 3.0)
    F = np.broadcast_to(np.eye(3), (1500, 3, 3))
    values = []
    for scale in (2, 4):  # without the 1/H normalisation the loss would double
        cams = ring_cameras(2, width=40 * scale, height=30 * scale, distance=30.0, fov_y_deg=30.0)
        target = disk_target(cams, radius_frac=0.2)
        values.append(render_and_grad(x, F, 0.12, cams, target, RenderConfig()).losses["dt"])
    assert values[0] == pytest.approx(values[1], rel=0.05)


def test_render_views_matches_render_and_grad_and_metric():
    cams = small_cameras(2)
    target = disk_target(cams)
    x, F = random_scene(12, 8)
    cfg = RenderConfig(tile_size=8)
    alpha, depth = render_views(x, F, 0.35, cams, cfg)
    res = render_and_grad(x, F, 0.35, cams, target, cfg)
    np.testing.assert_allclose(alpha, res.alpha)
    np.testing.assert_allclose(depth, res.depth)
    per_view = ((alpha - target.alpha) ** 2).mean(axis=(1, 2))
    np.testing.assert_allclose(res.alpha_mse_per_view, per_view, rtol=1e-5)
    assert res.alpha_mse == pytest.approx(per_view.mean(), rel=1e-5)


@pytest.mark.parametrize("t_min", [0.0, 1e-4])
def test_coverage_of_two_subsets_composes(t_min):
    """1 - alpha(all) = (1 - alpha(A)) (1 - alpha(B)) for a split of the particles into A and B (the
    morph loop's metric reuses the masked loss render this way): exact without the compositing's
    early stop (to float32 round-off), within transmittance_min with it."""
    cams = small_cameras(2)
    x, F = random_scene(400, 5, spread=0.6)  # dense: many pixels past the early stop
    cfg = RenderConfig(tile_size=8, transmittance_min=t_min)
    part = np.random.default_rng(1).random(len(x)) < 0.8
    whole = render_views(x, F, 0.35, cams, cfg)[0]
    a, b = (render_views(x[s], F[s], 0.35, cams, cfg)[0] for s in (part, ~part))
    composed = 1.0 - (1.0 - a) * (1.0 - b)
    assert (whole > 0.999).mean() > 0.05
    np.testing.assert_allclose(composed, whole, rtol=0, atol=1e-6 if t_min == 0 else t_min)  # float32 compositing


@pytest.mark.parametrize("kernel", ["tile", "pixel"])
@pytest.mark.parametrize("t_min", [0.0, 1e-4])
def test_coverage_behind_a_transmittance_is_the_composed_coverage(t_min, kernel):
    """coverage_behind(B, T_A) = 1 - T_A T_B, what the morph loop's metric takes for the particles
    outside the mask behind the masked render: to float32 round-off without the early stop, within
    transmittance_min with it (of the two subsets composed and of all particles rendered at once);
    pixels already opaque in front keep their transmittance."""
    cams = small_cameras(2)
    x, F = random_scene(400, 5, spread=0.6)
    cfg = RenderConfig(tile_size=8, transmittance_min=t_min, kernel=kernel)
    part = np.random.default_rng(1).random(len(x)) < 0.8
    whole = render_views(x, F, 0.35, cams, cfg)[0]
    a, b = (render_views(x[s], F[s], 0.35, cams, cfg)[0] for s in (part, ~part))
    behind = coverage_behind(x[~part], F[~part], 0.35, cams, 1.0 - a, cfg)
    tol = 1e-6 if t_min == 0 else t_min
    np.testing.assert_allclose(behind, 1.0 - (1.0 - a) * (1.0 - b), rtol=0, atol=tol)
    np.testing.assert_allclose(behind, whole, rtol=0, atol=tol)
    opaque = (1.0 - a) < t_min
    assert opaque.mean() > 0.02 or t_min == 0
    np.testing.assert_array_equal(behind[opaque], a[opaque].astype(np.float32).astype(np.float64))


def test_descending_the_render_gradient_reduces_the_dt_loss():
    cams = small_cameras(2, width=32, height=24)
    target = disk_target(cams, radius_frac=0.15)
    x = fibonacci_sphere(200, 1.5)
    F = np.broadcast_to(np.eye(3), (200, 3, 3)).copy()
    cfg = RenderConfig(iou_fraction=0.0, depth_fraction=0.0)
    res = render_and_grad(x, F, 0.25, cams, target, cfg)
    step = 0.05 / np.abs(res.grad_F).max()
    after = render_and_grad(x, F - step * res.grad_F, 0.25, cams, target, cfg)
    assert after.losses["dt"] < res.losses["dt"]


# ---------------------------------------------------------------------------------------------
# Edge cases
