"""Chamfer-guided plasticity: Jacobian estimate, zero-displacement invariance, projection bounds."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from physmorph.plasticity import (
    PlasticityConfig,
    chamfer_plasticity_step,
    displacement_jacobian,
    knn_smooth,
    project_plastic,
)


def _lattice(n=8, h=0.5):
    g = np.arange(n) * h
    return np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)


def test_jacobian_recovers_affine_map():
    rng = np.random.default_rng(1)
    x = _lattice() + 0.05 * rng.standard_normal((512, 3))
    A = np.array([[0.1, 0.02, -0.03], [0.05, -0.2, 0.01], [0.0, 0.04, 0.15]])
    d = x @ A.T + np.array([1.0, -2.0, 0.5])
    _, nb = cKDTree(x).query(x, k=27)
    J = displacement_jacobian(x, d, nb, "least_squares")
    assert np.allclose(J, A, atol=1e-8)
    # The printed eq. 4 returns A M_i (about A/3 in the bulk of an isotropic lattice).
    Jp = displacement_jacobian(x, d, nb, "paper")
    e = x[nb] - x[:, None]
    r2 = (e**2).sum(-1)
    w = np.where(r2 > 0, 1 / np.where(r2 > 0, r2, 1), 0)
    M = np.einsum("nk,nki,nkj->nij", w, e, e) / (r2 > 0).sum(1)[:, None, None]
    assert np.allclose(Jp, A @ M, atol=1e-10)


def test_knn_smoothing_keeps_constant_fields():
    x = _lattice(5)
    d = np.tile([0.3, -0.1, 0.2], (len(x), 1))
    _, nb = cKDTree(x).query(x, k=10)
    assert np.allclose(knn_smooth(d, nb, 3), d)


def test_zero_displacement_leaves_identity_fp_unchanged():
    x = _lattice(6)
    Fp = np.tile(np.eye(3), (len(x), 1, 1))
    cfg = PlasticityConfig(k_neighbors=16)
    res = chamfer_plasticity_step(x, Fp, target_points=x.copy(), cfg=cfg)
    assert np.allclose(res.Fp, Fp, atol=1e-12)
    assert res.mean_distance == 0.0


def test_uniform_translation_changes_nothing_but_damping():
    """A pure translation has zero Jacobian: only damping toward I acts on Fp."""
    x = _lattice(6)
    Fp = np.tile(np.diag([1.2, 1.0, 1 / 1.2]), (len(x), 1, 1))
    # Dense target: the same lattice shifted by a sub-spacing offset, so every NN displacement is equal.
    target = x + np.array([0.1, 0.0, 0.0])
    cfg = PlasticityConfig(k_neighbors=16, det_bounds=(0.1, 10.0), max_anisotropy=10.0)
    res = chamfer_plasticity_step(x, Fp, target, cfg)
    expected = 0.95 * Fp + 0.05 * np.eye(3)
    assert np.allclose(res.Fp, expected, atol=1e-9)


def test_stretch_toward_larger_target_grows_fp():
    x = _lattice(8) - 1.75
    # The same lattice scaled by 1.05: every displacement (<= 0.15) is under half the spacing,
    # so each particle's nearest target point is its own image and d = 0.05 x exactly.
    target = 1.05 * x
    Fp = np.tile(np.eye(3), (len(x), 1, 1))
    res = chamfer_plasticity_step(x, Fp, target, PlasticityConfig(k_neighbors=27, smooth_iters=0))
    det = np.linalg.det(res.Fp)
    assert np.median(det) > 1.0
    assert np.all(np.isfinite(res.Fp))


def test_projection_bounds_det_and_anisotropy():
    rng = np.random.default_rng(0)
    Fp = rng.standard_normal((200, 3, 3)) * 3  # includes inverted and wildly anisotropic ones
    Fp[0] = np.diag([1e-9, 1.0, 1.0])  # near-singular
    out = project_plastic(Fp, (0.5, 2.0), 4.0)
    det = np.linalg.det(out)
    s = np.linalg.svd(out, compute_uv=False)
    assert np.all(np.isfinite(out))
    assert np.all(det >= 0.5 - 1e-9) and np.all(det <= 2.0 + 1e-9)
    assert np.all(s[:, 0] / s[:, 2] <= 4.0 + 1e-9)


def test_projection_keeps_admissible_fp():
    Fp = np.tile(np.diag([1.1, 1.0, 0.95]), (3, 1, 1))
    R = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    Fp[1] = R @ Fp[1]
    assert np.allclose(project_plastic(Fp, (0.5, 2.0), 4.0), Fp, atol=1e-12)


def test_config_validation():
    with pytest.raises(ValueError, match="det_bounds"):
        PlasticityConfig(det_bounds=(1.2, 2.0))
    with pytest.raises(ValueError, match="jacobian"):
        PlasticityConfig(jacobian="magic")
