"""The render losses' closed-form gradients (LossGradients) against autograd of render_losses,
their reference, and against central differences."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from physmorph.render.losses import LossGradients, render_losses
from physmorph.settings.render import LOSS_TERMS, RenderConfig


def random_images(seed: int, views: int = 3, height: int = 7, width: int = 9, dtype=torch.float64):
    """alpha with transparent, faint and opaque pixels; a target silhouette with depth where it
    covers; a signed distance of both signs; D = alpha x a depth near the target's."""
    g = torch.Generator().manual_seed(seed)
    shape = (views, height, width)
    alpha = torch.rand(shape, generator=g, dtype=dtype)
    alpha[alpha < 0.2] = 0.0
    alpha[(alpha > 0.2) & (alpha < 0.25)] = 1e-4  # below depth_min_alpha
    target_alpha = (torch.rand(shape, generator=g, dtype=dtype) > 0.4).to(dtype)
    target_depth = target_alpha * (5.0 + torch.rand(shape, generator=g, dtype=dtype))
    target_sdt = 10.0 * torch.randn(shape, generator=g, dtype=dtype)
    depth_acc = alpha * (5.0 + torch.rand(shape, generator=g, dtype=dtype))
    return alpha, depth_acc, target_alpha, target_depth, target_sdt


def losses_and_gradients(alpha, depth_acc, target_alpha, target_depth, target_sdt, cfg):
    """LossGradients' values and every view's gradients stacked: [L, V, H, W] twice."""
    losses = LossGradients(alpha, depth_acc, target_alpha, target_depth, target_sdt, cfg.depth_min_alpha)
    views = [losses.view(v) for v in range(alpha.shape[0])]
    for g_alpha, g_depth in views:
        assert g_alpha.shape == g_depth.shape == (len(LOSS_TERMS), 1) + tuple(alpha.shape[1:])
    return losses.values, torch.cat([g for g, _ in views], dim=1), torch.cat([g for _, g in views], dim=1)


def autograd_reference(alpha, depth_acc, target_alpha, target_depth, target_sdt, cfg):
    alpha_leaf = alpha.clone().requires_grad_(True)
    depth_leaf = depth_acc.clone().requires_grad_(True)
    losses = render_losses(alpha_leaf, depth_leaf, target_alpha, target_depth, target_sdt, cfg)
    g_alpha, g_depth = torch.zeros((2, len(LOSS_TERMS)) + tuple(alpha.shape), dtype=alpha.dtype)
    for c, name in enumerate(LOSS_TERMS):
        ga, gd = torch.autograd.grad(losses[name], (alpha_leaf, depth_leaf), allow_unused=True, retain_graph=True)
        g_alpha[c] = 0.0 if ga is None else ga
        g_depth[c] = 0.0 if gd is None else gd
    return {k: float(v.detach()) for k, v in losses.items()}, g_alpha, g_depth


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_closed_form_equals_autograd_of_the_losses(seed):
    cfg = RenderConfig()
    images = random_images(seed)
    values, g_alpha, g_depth = losses_and_gradients(*images, cfg)
    ref_values, ref_alpha, ref_depth = autograd_reference(*images, cfg)
    for name in LOSS_TERMS:
        assert values[name] == pytest.approx(ref_values[name], rel=1e-12, abs=1e-15)
    np.testing.assert_allclose(g_alpha.numpy(), ref_alpha.numpy(), rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(g_depth.numpy(), ref_depth.numpy(), rtol=1e-10, atol=1e-14)
    # every term has a gradient somewhere (the test would pass trivially on zeros otherwise)
    assert all(g_alpha[c].abs().max() > 0 for c in range(len(LOSS_TERMS)))
    assert g_depth[LOSS_TERMS.index("depth")].abs().max() > 0


def test_float32_agrees_with_float64():
    cfg = RenderConfig()
    images64 = random_images(3, views=2, height=40, width=50)
    images32 = tuple(a.float() for a in images64)
    values64, ga64, gd64 = losses_and_gradients(*images64, cfg)
    values32, ga32, gd32 = losses_and_gradients(*images32, cfg)
    assert ga32.dtype == torch.float32 and gd32.dtype == torch.float32
    for name in LOSS_TERMS:
        assert values32[name] == pytest.approx(values64[name], rel=1e-5)
    for got, want in ((ga32, ga64), (gd32, gd64)):
        scale = float(want.abs().max())
        assert float((got.double() - want).abs().max()) <= 1e-5 * scale


def test_central_differences():
    cfg = RenderConfig()
    alpha, depth_acc, *targets = random_images(4, views=2, height=3, width=4)
    _, g_alpha, g_depth = losses_and_gradients(alpha, depth_acc, *targets, cfg)
    h = 1e-6
    for c, name in enumerate(LOSS_TERMS):
        for which, grad in ((0, g_alpha), (1, g_depth)):
            for index in [(0, 0, 0), (0, 1, 2), (1, 2, 3), (1, 0, 1)]:
                images = [alpha.clone(), depth_acc.clone()]
                if which == 0 and abs(float(alpha[index]) - cfg.depth_min_alpha) < 2 * h:
                    continue  # the depth loss's pixel set changes at its alpha threshold
                images[which][index] += h
                up = losses_and_gradients(*images, *targets, cfg)[0][name]
                images[which][index] -= 2 * h
                down = losses_and_gradients(*images, *targets, cfg)[0][name]
                assert float(grad[c][index]) == pytest.approx((up - down) / (2 * h), rel=1e-5, abs=1e-9)


def test_no_depth_pixels_gives_zero_depth_loss_and_gradient():
    cfg = RenderConfig()
    alpha, depth_acc, target_alpha, target_depth, target_sdt = random_images(5)
    values, g_alpha, g_depth = losses_and_gradients(alpha, depth_acc, target_alpha, torch.zeros_like(target_depth),
                                                    target_sdt, cfg)
    c = LOSS_TERMS.index("depth")
    assert values["depth"] == 0.0
    assert float(g_alpha[c].abs().max()) == 0.0 and float(g_depth[c].abs().max()) == 0.0


def test_a_target_in_the_renders_float_type_renders_the_same():
    """RenderTarget.in_float: the morph's target converted once gives the render of the float64 one."""
    from physmorph.base.cameras import ring_cameras
    from physmorph.render.api import render_and_grad
    from physmorph.render.containers import RenderTarget

    cams = ring_cameras(2, width=24, height=20, distance=10.0, fov_y_deg=30.0)
    rng = np.random.default_rng(0)
    x = rng.uniform(-1.0, 1.0, size=(60, 3))
    F = np.eye(3) + 0.2 * rng.normal(size=(60, 3, 3))
    shape = (2, 20, 24)
    target = RenderTarget(alpha=rng.uniform(size=shape), depth=rng.uniform(9.0, 11.0, size=shape),
                          sdt=rng.normal(size=shape) * 5.0)
    for dtype in ("float32", "float64"):
        cfg = RenderConfig(dtype=dtype)
        converted = target.in_float(dtype)
        assert converted.alpha.dtype == np.dtype(dtype) and converted.sdt.flags.c_contiguous
        a, b = render_and_grad(x, F, 0.12, cams, target, cfg), render_and_grad(x, F, 0.12, cams, converted, cfg)
        assert a.losses == b.losses
        np.testing.assert_array_equal(a.grad_F, b.grad_F)
