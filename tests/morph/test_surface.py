"""Surface mask: keeps the shell of a solid ball of particles, drops the core, never shrinks."""

import numpy as np
from scipy.spatial import cKDTree

from physmorph.settings.surface import SurfaceMaskConfig
from physmorph.morph.surface_mask import density_surface_mask, update_surface_mask


def _ball(radius=6.0, h=0.5):
    g = np.arange(-radius, radius + h, h)
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    x = x[np.linalg.norm(x, axis=1) <= radius]
    return x, np.full(len(x), h**3)


def test_density_mask_keeps_shell_drops_core():
    x, vol = _ball()
    cfg = SurfaceMaskConfig(voxels=64)
    mask = density_surface_mask(x, vol, cfg, -16.0, 16.0)
    r = np.linalg.norm(x, axis=1)
    assert mask[r > 5.6].mean() > 0.95  # the outer shell is kept
    assert mask[r < 3.5].sum() == 0  # the core is dropped
    assert 0.15 < mask.mean() < 0.7  # a real reduction of what gets rendered


def test_target_proximity_and_union_never_shrink():
    x, vol = _ball()
    cfg = SurfaceMaskConfig(voxels=64)
    # A target surface inside the ball: particles near it join the mask.
    t = np.random.default_rng(0).standard_normal((2000, 3))
    t = 2.0 * t / np.linalg.norm(t, axis=1, keepdims=True)
    tree = cKDTree(t)
    m1 = update_surface_mask(x, vol, tree, cfg, -16.0, 16.0)
    r = np.linalg.norm(x, axis=1)
    assert m1[np.abs(r - 2.0) < 0.3].all()
    prev = np.zeros(len(x), bool)
    prev[np.argmin(r)] = True  # the centre particle was in the mask before
    m2 = update_surface_mask(x, vol, tree, cfg, -16.0, 16.0, previous=prev)
    assert m2[np.argmin(r)] and np.all(m2 >= m1)


def test_disabled_mask_renders_everything():
    x, vol = _ball(3.0)
    m = update_surface_mask(x, vol, cKDTree(x), SurfaceMaskConfig(enabled=False), -16, 16)
    assert m.all()
