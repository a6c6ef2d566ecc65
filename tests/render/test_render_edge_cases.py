"""Edge cases of physmorph.render: no Gaussian in view or behind the camera, empty particle sets,
degenerate and huge covariances, empty or full targets, invalid inputs, shading, the automatic
device and per-particle sizes."""

from __future__ import annotations

import numpy as np
import pytest

from physmorph.render.api import render_and_grad, render_views, shade
from physmorph.render.containers import RenderTarget
from physmorph.settings.render import RenderConfig

from render_cases import disk_target, fibonacci_sphere, front_camera, random_scene, small_cameras

def _assert_finite(res):
    for v in (res.alpha, res.depth, res.grad_F, res.alpha_mse_per_view):
        assert np.all(np.isfinite(v))
    assert all(np.isfinite(v) for v in res.losses.values())
    if res.grad_x is not None:
        assert np.all(np.isfinite(res.grad_x))


def test_no_gaussian_in_view_and_behind_camera():
    cams = small_cameras(2)
    target = disk_target(cams)
    centres = cams.centers
    x = np.array([[100.0, 100.0, 100.0],  # far outside every frustum
                  centres[0] * 1.05,  # behind camera 0
                  centres[1] + 0.01])  # behind the near plane of camera 1
    F = np.broadcast_to(np.eye(3), (3, 3, 3)).copy()
    res = render_and_grad(x[:2], F[:2], 0.3, cams.subset([0]), RenderTarget(
        target.alpha[:1], target.depth[:1], target.sdt[:1]), RenderConfig(), want_grad_x=True)
    _assert_finite(res)
    assert res.alpha.max() == 0.0 and res.depth.max() == 0.0
    assert np.abs(res.grad_F).max() == 0.0 and np.abs(res.grad_x).max() == 0.0
    res = render_and_grad(x, F, 0.3, cams, target, RenderConfig(), want_grad_x=True)
    _assert_finite(res)
    # In view 0, the particle right in front of camera 1 (behind camera 1's near plane) is seen.
    assert res.alpha[1].max() == 0.0


def test_empty_particle_set():
    cams = small_cameras(2)
    res = render_and_grad(np.zeros((0, 3)), np.zeros((0, 3, 3)), 0.3, cams, disk_target(cams), RenderConfig(),
                          want_grad_x=True)
    _assert_finite(res)
    assert res.grad_F.shape == (0, 3, 3) and res.grad_x.shape == (0, 3)
    assert res.alpha.max() == 0.0


def test_degenerate_and_huge_covariances():
    cams = small_cameras(2)
    target = disk_target(cams)
    x, _ = random_scene(4, 9, spread=0.5)
    F = np.stack([np.zeros((3, 3)),  # collapsed to a point
                  np.diag([1.0, 1e-9, 1e-9]),  # near-singular (a needle)
                  -np.eye(3),  # inverted
                  np.eye(3) * 1e3])  # huge: covers every pixel
    res = render_and_grad(x, F, 0.3, cams, target, RenderConfig(), want_grad_x=True)
    _assert_finite(res)
    assert res.alpha.min() > 0.5  # the huge Gaussian covers the whole image
    # The collapsed Gaussian is the low-pass footprint (about a pixel): still rendered alone.
    alone, _ = render_views(x[:1], F[:1], 0.3, cams, RenderConfig())
    assert 0.5 < alone.max() <= RenderConfig().alpha_max and np.count_nonzero(alone[0] > 0.01) < 30


@pytest.mark.parametrize("kind", ["empty", "full"])
def test_empty_or_full_target_silhouette(kind):
    cams = small_cameras(2)
    shape = (2, cams.height, cams.width)
    if kind == "empty":
        target = RenderTarget(np.zeros(shape), np.zeros(shape), np.full(shape, 5.0))
    else:
        target = RenderTarget(np.ones(shape), np.full(shape, 10.0), np.full(shape, -5.0))
    x = fibonacci_sphere(150, 1.2)
    F = np.broadcast_to(np.eye(3), (150, 3, 3)).copy()
    cfg = RenderConfig(iou_fraction=0.0, depth_fraction=0.0)
    res = render_and_grad(x, F, 0.2, cams, target, cfg, want_grad_x=True)
    _assert_finite(res)
    assert np.abs(res.grad_F).max() > 0
    # Sensible direction: the DT loss shrinks the render on an empty target and grows it on a full one.
    after = render_and_grad(x, F - 0.05 / np.abs(res.grad_F).max() * res.grad_F, 0.2, cams, target, cfg)
    assert after.alpha.sum() < res.alpha.sum() if kind == "empty" else after.alpha.sum() > res.alpha.sum()
    full = render_and_grad(x, F, 0.2, cams, target, RenderConfig())  # with IoU and depth terms
    _assert_finite(full)


def test_invalid_inputs_raise():
    cams = small_cameras(1)
    with pytest.raises(ValueError, match="NaN"):
        render_views(np.full((1, 3), np.nan), np.eye(3)[None], 0.3, cams)
    with pytest.raises(ValueError, match="F must be"):
        render_views(np.zeros((2, 3)), np.eye(3)[None], 0.3, cams)
    with pytest.raises(ValueError):
        RenderConfig(alpha_max=1.0)


def test_shade_produces_an_image():
    cams = front_camera(40, 40, f=60.0, distance=12.0)
    x = fibonacci_sphere(800, 2.0)
    rgb = shade(x, np.broadcast_to(np.eye(3), (800, 3, 3)), 0.15, cams, 0, RenderConfig())
    assert rgb.shape == (40, 40, 3) and np.all(np.isfinite(rgb))
    assert rgb.min() >= 0.0 and rgb.max() <= 1.0
    np.testing.assert_allclose(rgb[0, 0], 1.0)  # background corner
    # Head light from the upper left: the upper-left of the sphere is brighter than the lower right.
    assert rgb[14, 14].sum() > rgb[26, 26].sum()


def test_auto_device_and_per_particle_sigma0():
    """device="auto" falls back to what is available; sigma0 may be given per particle."""
    cams = small_cameras(1)
    x, F = random_scene(6, 12, spread=0.5)
    a_scalar, _ = render_views(x, F, 0.3, cams, RenderConfig(device="auto"))
    a_array, _ = render_views(x, F, np.full(6, 0.3), cams, RenderConfig(device="auto"))
    np.testing.assert_allclose(a_scalar, a_array, atol=1e-6)
    a_small, _ = render_views(x, F, np.full(6, 0.1), cams, RenderConfig(device="auto"))
    assert a_small.sum() < a_scalar.sum()
