"""The reachable-gap measure (physmorph.morph.quality): share of the gap closed and silhouette IoU."""

import numpy as np
import pytest

from physmorph.morph.quality import gap_closed, silhouette_iou


def test_gap_closed_is_the_plain_ratio_when_there_is_a_gap():
    assert gap_closed(0.06, 0.06, 0.01) == pytest.approx(0.0)
    assert gap_closed(0.06, 0.035, 0.01) == pytest.approx(0.5)
    assert gap_closed(0.06, 0.01, 0.01) == pytest.approx(1.0)
    assert gap_closed(0.06, 0.085, 0.01) == pytest.approx(-0.5)
    np.testing.assert_allclose(gap_closed(0.06, np.array([0.06, 0.035, 0.01]), 0.01), [0.0, 0.5, 1.0])


def test_gap_closed_stays_bounded_when_the_source_is_at_the_ceiling():
    """Source == target: a0 ~ ceiling; staying there counts as ~1, drifting away is bounded."""
    c = 0.01
    for a0 in (c, c * 1.0001, c * 0.999):
        assert 0.85 < gap_closed(a0, a0, c) < 1.05  # above 1 only when a0 is below the ceiling
        worse = gap_closed(a0, a0 + 0.005, c)
        assert np.isfinite(worse) and -10 < worse < 0
    # continuous in a0 across the point where the plain ratio takes over (gap = 0.1 x ceiling)
    assert gap_closed(c * 1.1 - 1e-12, c * 1.05, c) == pytest.approx(gap_closed(c * 1.1 + 1e-12, c * 1.05, c), abs=1e-6)


def test_silhouette_iou():
    a = np.zeros((2, 4, 4))
    t = np.zeros((2, 4, 4))
    a[0, :2, :] = 1.0  # 8 pixels
    t[0, :, :2] = 1.0  # 8 pixels, 4 shared
    np.testing.assert_allclose(silhouette_iou(a, t), [4 / 12, 1.0])  # view 1: both empty
    assert silhouette_iou(t, t)[0] == 1.0
    assert silhouette_iou(0.4 * t, t)[0] == 0.0  # below the 0.5 threshold


def test_ceiling_metrics_compares_particles_at_rest_with_the_target():
    """Particles against their own rendering: MSE 0, IoU 1; moved sideways: worse on both."""
    from physmorph.base.cameras import ring_cameras
    from physmorph.morph.quality import ceiling_metrics
    from physmorph.settings.render import RenderConfig
    from physmorph.render.api import render_views

    rng = np.random.default_rng(0)
    x = rng.normal(scale=3.0, size=(400, 3))
    cams = ring_cameras(count=2, elevation_deg=21.0, fov_y_deg=40.0, width=32, height=24, distance=36.0)
    F = np.broadcast_to(np.eye(3), (len(x), 3, 3))
    own, _ = render_views(x, F, 0.8, cams, RenderConfig())
    same = ceiling_metrics(x, 0.8, cams, own)
    np.testing.assert_allclose(same["alpha_mse_views"], 0.0, atol=1e-12)
    np.testing.assert_allclose(same["iou_views"], 1.0)
    assert same["alpha_mse"] == pytest.approx(0.0, abs=1e-12) and same["iou"] == 1.0
    moved = ceiling_metrics(x + np.array([0.0, 4.0, 0.0]), 0.8, cams, own)
    assert moved["alpha_mse_views"].shape == (2,) and np.all(moved["alpha_mse_views"] > 1e-3)
    assert np.all(moved["iou_views"] < 0.9)
    assert moved["alpha_mse"] == pytest.approx(moved["alpha_mse_views"].mean())


def _ball(n_side: int, radius: float, centre=(0.0, 0.0, 0.0)):
    """Particles on a lattice inside a ball (spacing 2 radius / n_side), unit mass each."""
    t = np.linspace(-radius, radius, n_side)
    x = np.stack(np.meshgrid(t, t, t, indexing="ij"), axis=-1).reshape(-1, 3)
    x = x[np.linalg.norm(x, axis=1) <= radius] + np.asarray(centre)
    return x, np.ones(len(x))


def test_volume_checks_score_the_targets_own_sampling_and_see_moved_spread_and_collapsed_bodies():
    from physmorph.base.grid import Grid, splat_mass
    from physmorph.morph.quality import volume_metrics

    def volume_iou(*args):
        return volume_metrics(*args)["volume_iou"]

    grid = Grid(res=32)  # dx = 1
    x, m = _ball(25, 6.0)  # 4 particles per dx along each axis
    target = splat_mass(x, 75.0 * m, grid)  # another density and total mass: rescaled, same cells
    assert volume_iou(x, m, target, grid) == pytest.approx(1.0)
    # moved by d = 3 cells: the IoU of two balls of radius R = 6 whose centres are d apart,
    # lens / (2 V - lens) with lens = pi (4 R + d)(2 R - d)^2 / 12 and V = 4/3 pi R^3 (0.463)
    R, d = 6.0, 3.0
    lens = np.pi * (4 * R + d) * (2 * R - d) ** 2 / 12
    exact = lens / (2 * 4 / 3 * np.pi * R ** 3 - lens)
    assert volume_iou(x + np.array([d, 0.0, 0.0]), m, target, grid) == pytest.approx(exact, abs=0.03)
    # the same particles spread to twice the radius: 1/8 of the density, no cell counts as filled
    assert volume_iou(2.0 * x, m, target, grid) < 0.05
    # ... and collapsed to half the radius: 8 times the density, (nearly) all of it overfilled
    assert volume_metrics(x, m, target, grid)["overfilled_mass"] == 0.0
    assert volume_metrics(0.5 * x, m, target, grid)["overfilled_mass"] > 0.85  # all but its rim
    core = np.linalg.norm(x, axis=1) < 3.0  # the core alone collapsed (to 0.9 cells): its share of the mass
    clumped = np.where(core[:, None], 0.3 * x, x)
    assert volume_metrics(clumped, m, target, grid)["overfilled_mass"] == pytest.approx(core.mean(), abs=0.03)
    # a flattened body with the target's silhouette along z only (squashed in z): fills less
    squashed = volume_iou(x * np.array([1.0, 1.0, 0.5]), m, target, grid)
    assert squashed < 0.7
    with pytest.raises(ValueError, match="shape"):
        volume_iou(x, m, target[:-1], grid)
