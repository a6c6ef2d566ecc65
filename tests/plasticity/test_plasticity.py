"""Chamfer-guided plasticity: Jacobian estimate, zero-displacement invariance, projection bounds."""

import dataclasses

import numpy as np
import pytest
from scipy.spatial import cKDTree

from physmorph.plasticity.neighbourhood import displacement_jacobian_pairs, k_nearest, smooth_displacement
from physmorph.plasticity.step import absorb_control, absorb_shape, absorbed_rest, chamfer_plasticity_step, displacement_jacobian, knn_smooth, nearest_neighbours, project_plastic, rebase_control, rebase_reference
from physmorph.settings.plasticity import PlasticityConfig


def _lattice(n=8, h=0.5):
    g = np.arange(n) * h
    return np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)


def _neighbourhood_moments(x, nb):  # x [N, 3], nb [N, k] -> [N, 3, 3]
    """M_i = mean_j e_j e_j^T / |e_j|^2 over the neighbours j != i (e_j = x_j - x_i)."""
    e = x[nb] - x[:, None]
    r2 = (e**2).sum(-1)
    w = np.where(r2 > 0, 1 / np.where(r2 > 0, r2, 1), 0)
    return np.einsum("nk,nki,nkj->nij", w, e, e) / (r2 > 0).sum(1)[:, None, None]


def test_jacobian_of_an_affine_map_is_its_matrix_times_the_neighbourhood_moments():
    """The printed eq. 4 returns A M_i for d = A x + b (about A/3 in the bulk of an isotropic lattice)."""
    rng = np.random.default_rng(1)
    x = _lattice() + 0.05 * rng.standard_normal((512, 3))
    A = np.array([[0.1, 0.02, -0.03], [0.05, -0.2, 0.01], [0.0, 0.04, 0.15]])
    d = x @ A.T + np.array([1.0, -2.0, 0.5])
    _, nb = cKDTree(x).query(x, k=27)
    J = displacement_jacobian(x, d, nb)
    M = _neighbourhood_moments(x, nb)
    assert np.allclose(J, A @ M, atol=1e-10)


def test_neighbour_sum_jacobian_and_smoothing_equal_their_gather_references():
    """The fast paths (the chamfer step's Taichi pair sums, physmorph.plasticity.neighbourhood) against the
    per-pair gather references, on an irregular cloud with a non-affine field, a duplicated
    particle and the KD tree's own distances."""
    rng = np.random.default_rng(4)
    x = 10.0 + _lattice() + 0.1 * rng.standard_normal((512, 3))  # off the origin: tests cancellation
    x[7] = x[3]  # a coincident pair carries no weight in either path
    d = np.sin(x) + 0.1 * x ** 2
    dist, nb = cKDTree(x).query(x, k=20)
    ref = displacement_jacobian(x, d, nb)
    r2 = ((x[nb] - x[:, None]) ** 2).sum(-1)
    np.testing.assert_allclose(displacement_jacobian_pairs(x, d, nb, r2), ref, rtol=1e-10, atol=1e-10)
    r2 = dist ** 2
    r2[nb == np.arange(len(x))[:, None]] = 0.0
    np.testing.assert_allclose(displacement_jacobian_pairs(x, d, nb.astype(np.int32), r2), ref,
                               rtol=1e-7, atol=1e-7)
    # r2 left out: each pair's distance from x, as k_nearest computes it
    np.testing.assert_allclose(displacement_jacobian_pairs(x, d, nb, None), ref, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(smooth_displacement(d, nb, 3), knn_smooth(d, nb, 3), rtol=1e-12, atol=1e-12)
    # with neighbourhoods drawn from a pool (its rows alone until the last pass)
    pool = np.arange(0, len(x), 3)
    nbp = pool[cKDTree(x[pool]).query(x, k=9)[1]].astype(np.int32)
    np.testing.assert_allclose(smooth_displacement(d, nbp, 3, sources=pool), knn_smooth(d, nbp, 3),
                               rtol=1e-12, atol=1e-12)
    # the pool's passes leave the other rows alone: one pass of two over the pool only
    one = smooth_displacement(d, nbp, 2, sources=pool)
    first = d.copy()
    first[pool] = d[nbp[pool]].mean(axis=1)
    np.testing.assert_allclose(one, first[nbp].mean(axis=1), rtol=1e-12, atol=1e-12)


def test_nearest_neighbours_by_chunks_equal_a_brute_force_search():
    """nearest_neighbours (the chamfer step's query by chunks of rows, int32 indices) against
    sorting every pairwise distance: the same k neighbours from a subset, the particle itself at
    r2 = 0, and chunks that do not divide the particle count."""
    rng = np.random.default_rng(7)
    x = rng.uniform(0, 3, (301, 3))
    source = np.sort(rng.choice(len(x), 150, replace=False))
    nb, r2 = nearest_neighbours(x, source, 9, chunk=64)
    assert nb.dtype == np.int32 and nb.shape == r2.shape == (301, 9)
    all_r2 = ((x[:, None] - x[source][None]) ** 2).sum(-1)  # [N, P]
    order = np.argsort(all_r2, axis=1, kind="stable")[:, :9]
    np.testing.assert_array_equal(nb, source[order])
    expect = np.take_along_axis(all_r2, order, axis=1)
    expect[nb == np.arange(len(x))[:, None]] = 0.0
    np.testing.assert_allclose(r2, expect, rtol=1e-12, atol=1e-12)
    assert (r2[np.isin(np.arange(len(x)), source), 0] == 0).all()  # a source particle is its own nearest


def _brute_knn(x, source, k):
    all_r2 = ((x[:, None] - x[source][None]) ** 2).sum(-1)  # [N, P]
    order = np.argsort(all_r2, axis=1, kind="stable")[:, :k]
    return source[order], np.take_along_axis(all_r2, order, axis=1)


def _by_distance(nb, r2):
    order = np.argsort(r2, axis=1, kind="stable")
    return np.take_along_axis(nb, order, axis=1), np.take_along_axis(r2, order, axis=1)


@pytest.mark.parametrize("block", [3, 4])
@pytest.mark.parametrize("cell_scale", [0.25, 1.0, 4.0, 100.0])
def test_k_nearest_equals_a_brute_force_search(cell_scale, block):
    """neighbourhood.k_nearest (the cell grid the chamfer step uses) against sorting every
    pairwise distance, whatever the cells' size and the block's (centred on the query's cell, or
    of an even number of cells on the side of its half): small cells send most queries to the ring
    search, large ones settle them in the block, one cell covers the grid. A clustered cloud with a
    far outlier, a coincident pair and a flat sheet; the same neighbour sets and r2 (0 for the
    particle itself), in any order."""
    rng = np.random.default_rng(11)
    x = np.concatenate([rng.normal(0, 0.3, (300, 3)), rng.uniform(2, 3, (200, 3)),
                        np.c_[rng.uniform(0, 1, (100, 2)), np.full(100, -1.0)], [[9.0, 9.0, 9.0]]])
    x[5] = x[17]
    source = np.sort(rng.choice(len(x), 240, replace=False))
    source = np.union1d(source, [5, 17, 600])
    for k in (1, 9, 64):
        nb, r2 = k_nearest(x, source, k, cell_scale=cell_scale, block=block)
        assert nb.dtype == np.int32 and nb.shape == r2.shape == (len(x), k)
        ref_nb, ref_r2 = _brute_knn(x, source, k)
        np.testing.assert_allclose(np.sort(r2, axis=1), ref_r2, rtol=0, atol=1e-12)
        # the sets agree wherever the k-th distance is not tied with the next
        all_r2 = np.sort(((x[:, None] - x[source][None]) ** 2).sum(-1), axis=1)
        untied = all_r2[:, k] > all_r2[:, k - 1] + 1e-12 if k < len(source) else np.ones(len(x), bool)
        assert untied.mean() > 0.95  # the coincident pair and its neighbours tie
        np.testing.assert_array_equal(np.sort(nb[untied], axis=1), np.sort(ref_nb[untied], axis=1))
        mine = np.isin(np.arange(len(x)), source)
        assert (r2[mine] == 0).any(axis=1).all()  # a source particle is among its own neighbours at r2 = 0
        # by chunks of rows, without the distances: the same rows
        nb_c, none = k_nearest(x, source, k, cell_scale=cell_scale, block=block, with_r2=False, chunk=97)
        assert none is None
        np.testing.assert_array_equal(np.sort(nb_c, axis=1), np.sort(nb, axis=1))
        # the block's second pass from its kept candidates (above) or, where a row has more than
        # it keeps, by scanning its block again (with one or five kept, nearly every row): the
        # same rows, in the same order
        for kept in (1, 5):
            nb_k, r2_k = k_nearest(x, source, k, cell_scale=cell_scale, block=block, chunk=97, candidates=kept)
            np.testing.assert_array_equal(nb_k, nb)
            np.testing.assert_array_equal(r2_k, r2)
    nb, r2 = k_nearest(x, source, len(source), cell_scale=cell_scale, block=block)  # k = the whole pool
    assert (np.sort(nb, axis=1) == source[None]).all()
    with pytest.raises(ValueError, match="k must be"):
        k_nearest(x, source, len(source) + 1)


def test_k_nearest_keeps_every_candidate_whatever_the_count_kept():
    """The block's first scan keeps up to ``candidates`` points within the reach (each point
    written to the next free slot); with every count from 1 to past what a block holds, some rows'
    candidates fill the kept slots exactly and points past the reach come after the last: the same
    rows as with room for all (the KD tree's distances)."""
    rng = np.random.default_rng(4)
    x = rng.uniform(0.0, 1.0, (1500, 3))
    source = np.arange(len(x))
    for k in (1, 4, 9):
        ref_r2 = _brute_knn(x, source, k)[1]
        nb, r2 = k_nearest(x, source, k)
        np.testing.assert_allclose(np.sort(r2, axis=1), ref_r2, rtol=0, atol=1e-12)
        for kept in range(1, 61):
            nb_k, r2_k = k_nearest(x, source, k, candidates=kept)
            np.testing.assert_array_equal(r2_k, r2, err_msg=f"k = {k}, {kept} kept")
            np.testing.assert_array_equal(nb_k, nb, err_msg=f"k = {k}, {kept} kept")


def test_k_nearest_matches_the_kd_tree_reference_on_a_jittered_lattice():
    """On the sampling's own kind of cloud (a jittered lattice, neighbourhoods from a pool, k = 64)
    the cell grid returns the KD tree's neighbours (plasticity.nearest_neighbours)."""
    rng = np.random.default_rng(2)
    g = np.stack(np.meshgrid(*[np.arange(14)] * 3, indexing="ij"), -1).reshape(-1, 3).astype(float)
    x = 0.5 * (g + rng.uniform(-0.3, 0.3, g.shape))
    pool = np.flatnonzero((g % 2 == 0).all(axis=1))
    ref_nb, ref_r2 = nearest_neighbours(x, pool, 64)
    nb, r2 = k_nearest(x, pool, 64)
    nb_s, r2_s = _by_distance(nb, r2)
    np.testing.assert_array_equal(nb_s, ref_nb)
    np.testing.assert_allclose(r2_s, ref_r2, rtol=1e-12, atol=1e-15)


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


def test_projection_skips_only_what_its_svd_would_rebuild():
    """project_plastic returns an Fp inside both bounds as it is and projects the rest: on a mix
    of admissible, barely admissible and inadmissible Fp it equals the batched SVD of every one."""
    from physmorph.plasticity.step import _project_plastic_svd

    rng = np.random.default_rng(3)
    inside = np.eye(3) + 0.1 * rng.standard_normal((300, 3, 3))
    outside = rng.standard_normal((100, 3, 3)) * 3
    edge = np.tile(np.diag([2.0, 1.0, 0.5]), (4, 1, 1)) * np.array([1.0, 1.0 + 1e-9, 1.0 - 1e-9, 1.0 + 1e-3])[:, None, None]
    Fp = np.concatenate([inside, outside, edge])[rng.permutation(404)]
    out = project_plastic(Fp, (0.5, 2.0), 4.0)
    np.testing.assert_allclose(out, _project_plastic_svd(Fp, (0.5, 2.0), 4.0), rtol=0, atol=1e-12)
    assert (out == Fp).all(axis=(1, 2)).sum() >= 250  # most of the near-identity ones were skipped


@pytest.mark.parametrize("scale_from", [1.0, 1.07])
def test_fp_update_kernel_equals_its_numpy_reference(scale_from):
    """plasticity.fp_update (steps 4-5 and the projection's bounds test in one Taichi pass)
    against step.fp_update_reference: the same Fp' to round-off and the same rows inside the
    bounds, on Fp near the identity, far outside, inverted, singular, and near the bounds' edges,
    with the rest volume ratio's scale and without; the projection of
    the rows outside then gives project_plastic's result."""
    from physmorph.plasticity.fp_update import fp_update
    from physmorph.plasticity.step import INSIDE_MARGIN, fp_update_reference, project_outside

    rng = np.random.default_rng(5)
    n = 600
    Fp = np.eye(3) + 0.15 * rng.standard_normal((n, 3, 3))
    Fp[:60] = 3.0 * rng.standard_normal((60, 3, 3))  # far outside, some inverted
    Fp[60] = np.diag([1.0, 1.0, 0.0])  # singular
    Fp[61:65] = np.diag([2.0, 1.0, 0.5]) * np.array([1.0, 1.0 + 1e-9, 1.0 - 1e-9, 1.0 + 1e-3])[:, None, None]
    J = 0.3 * rng.standard_normal((n, 3, 3))
    J[61:65] = 0.0
    eta = rng.uniform(0.0, 0.05, n)
    damping, bounds, aniso = 0.05, (0.5, 2.0), 4.0
    out, inside = fp_update(J, eta, Fp, damping, bounds, aniso, INSIDE_MARGIN, scale_from)
    ref, ref_inside = fp_update_reference(J, eta, Fp, damping, bounds, aniso, scale_from)
    np.testing.assert_allclose(out, ref, rtol=1e-13, atol=1e-14)
    np.testing.assert_array_equal(inside, ref_inside)
    assert 0 < inside.sum() < n  # both kinds of row
    np.testing.assert_allclose(project_outside(out, inside, bounds, aniso), project_plastic(ref, bounds, aniso),
                               rtol=0, atol=1e-12)


def test_config_validation():
    with pytest.raises(ValueError, match="det_bounds"):
        PlasticityConfig(det_bounds=(1.2, 2.0))


def test_rebase_control_leaves_the_elastic_deformation_unchanged():
    """(F + dFc') Fp_new^-1 == (F + dFc) Fp_old^-1 for every control slot, and dFc' = dFc when Fp
    does not change."""
    rng = np.random.default_rng(1)
    N, T = 7, 3
    F = np.eye(3) + 0.2 * rng.standard_normal((N, 3, 3))
    ctrl = 0.1 * rng.standard_normal((T, N, 3, 3))
    Fp_old = np.eye(3) + 0.1 * rng.standard_normal((N, 3, 3))
    Fp_new = np.eye(3) + 0.1 * rng.standard_normal((N, 3, 3))
    new = rebase_control(F, ctrl, Fp_old, Fp_new)
    Fe_old = (F[None] + ctrl) @ np.linalg.inv(Fp_old)[None]
    Fe_new = (F[None] + new) @ np.linalg.inv(Fp_new)[None]
    np.testing.assert_allclose(Fe_new, Fe_old, atol=1e-12)
    np.testing.assert_allclose(rebase_control(F, ctrl, Fp_old, Fp_old), ctrl, atol=1e-12)


def test_absorbed_control_becomes_the_rest_state():
    """After absorb_control and the re-base, F alone reproduces the mean elastic deformation the
    control produced, F Fp'^-1 = (F + mean dFc) Fp^-1, the re-based control has zero mean over
    the substeps, and each slot's Fe is unchanged; a near-singular particle keeps its Fp."""
    rng = np.random.default_rng(2)
    N, T = 6, 4
    F = np.eye(3) + 0.2 * rng.standard_normal((N, 3, 3))
    ctrl = 0.1 * rng.standard_normal((T, N, 3, 3))
    ctrl[:, 0] = -F[0][None] / 1.0  # F + dFc = 0 for particle 0: nothing to absorb there
    Fp = np.eye(3) + 0.1 * rng.standard_normal((N, 3, 3))
    Fp_new = absorb_control(F, ctrl.mean(axis=0), Fp)
    np.testing.assert_allclose(Fp_new[0], Fp[0])
    mean = ctrl.mean(axis=0)
    np.testing.assert_allclose(F[1:] @ np.linalg.inv(Fp_new[1:]), (F[1:] + mean[1:]) @ np.linalg.inv(Fp[1:]), atol=1e-12)
    rebased = rebase_control(F, ctrl, Fp, Fp_new)
    np.testing.assert_allclose(rebased[:, 1:].mean(axis=0), 0.0, atol=1e-12)
    Fe_old = (F[None] + ctrl) @ np.linalg.inv(Fp)[None]
    Fe_new = (F[None] + rebased) @ np.linalg.inv(Fp_new)[None]
    np.testing.assert_allclose(Fe_new, Fe_old, atol=1e-12)


def _rotation(rng):
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_absorbed_shape_is_stress_free_and_keeps_the_stress_of_the_running_morph():
    """absorb_shape makes the achieved shape the rest shape: F Fp'^-1 is a rotation (the fixed-
    corotated stress vanishes), Fp' is the symmetric stretch of F (F = R Fp'), and a near-inverted
    particle keeps its Fp. With the control re-based afterwards each
    substep's Fe is unchanged, so only a released body notices."""
    import torch

    from physmorph.mpm.reference import stress_torch

    rng = np.random.default_rng(4)
    N, T = 7, 3
    S_true = np.eye(3) + 0.3 * rng.standard_normal((N, 3, 3))
    S_true = S_true @ S_true.transpose(0, 2, 1) + 0.2 * np.eye(3)  # symmetric positive stretches
    R = np.stack([_rotation(rng) for _ in range(N)])
    F = R @ S_true
    F[0] = np.diag([1.0, 1.0, -0.5])  # inverted: keeps its Fp
    Fp = np.eye(3) + 0.1 * rng.standard_normal((N, 3, 3))
    Fp_new = absorb_shape(F, Fp)
    np.testing.assert_allclose(Fp_new[0], Fp[0])
    np.testing.assert_allclose(Fp_new[1:], S_true[1:], atol=1e-10)
    Fe = F[1:] @ np.linalg.inv(Fp_new[1:])
    np.testing.assert_allclose(Fe @ Fe.transpose(0, 2, 1), np.broadcast_to(np.eye(3), Fe.shape), atol=1e-10)
    np.testing.assert_allclose(np.linalg.det(Fe), 1.0, atol=1e-10)
    P = stress_torch(torch.from_numpy(Fe), mu=1.0, lam=1.0).numpy()
    np.testing.assert_allclose(P, 0.0, atol=1e-8)
    ctrl = 0.05 * rng.standard_normal((T, N, 3, 3))
    rebased = rebase_control(F, ctrl, Fp, Fp_new)
    Fe_old = (F[None] + ctrl) @ np.linalg.inv(Fp)[None]
    Fe_new = (F[None] + rebased) @ np.linalg.inv(Fp_new)[None]
    np.testing.assert_allclose(Fe_new, Fe_old, atol=1e-10)
    with pytest.raises(ValueError, match="absorb_target"):
        PlasticityConfig(absorb_target="velocity")


def test_absorption_starts_at_its_frame_and_picks_what_the_control_is_rebased_onto():
    """absorbs_at: off without absorb_control, from every update without a start frame, from the
    start frame with one. absorbed_rest dispatches on absorb_target. rebase_reference: no re-base
    for the plain update, the whole update with continuous_stress or the control absorbed, only
    the absorption with the shape absorbed; before the start frame the update is the plain one."""
    rng = np.random.default_rng(5)
    N, T = 4, 2
    F = np.eye(3) + 0.1 * rng.standard_normal((N, 3, 3))
    ctrl = 0.05 * rng.standard_normal((T, N, 3, 3))
    Fp = np.eye(3) + 0.05 * rng.standard_normal((N, 3, 3))
    Fp_absorbed, Fp_new = Fp + 0.01, Fp + 0.02
    plain = PlasticityConfig(absorb_control=False)
    assert not plain.absorbs_at(1, 40) and not plain.absorbs_at(40, 40)
    assert rebase_reference(plain, False, Fp_absorbed, Fp_new) is None
    assert rebase_reference(PlasticityConfig(continuous_stress=True, absorb_control=False), False, Fp_absorbed,
                            Fp_new) is Fp_new

    control = PlasticityConfig(absorb_control=True, absorb_target="control", absorb_start_frame=None)
    assert control.absorbs_at(1, 40)
    np.testing.assert_array_equal(absorbed_rest(F, ctrl.mean(axis=0), Fp, control), absorb_control(F, ctrl.mean(axis=0), Fp))
    assert rebase_reference(control, True, Fp_absorbed, Fp_new) is Fp_new

    late = PlasticityConfig(absorb_control=True, absorb_target="shape", absorb_start_frame=30)
    assert [late.absorbs_at(k, 40) for k in (10, 29, 30, 40)] == [False, False, True, True]
    last = PlasticityConfig()  # the default: the shape, at the last update only
    assert last.absorb_target == "shape"
    assert [last.absorbs_at(k, 40) for k in (1, 39, 40)] == [False, False, True]
    assert [PlasticityConfig(absorb_control=True, absorb_start_frame=-3).absorbs_at(k, 12)
            for k in (9, 10, 12)] == [False, True, True]
    np.testing.assert_array_equal(absorbed_rest(F, ctrl.mean(axis=0), Fp, late), absorb_shape(F, Fp))
    assert rebase_reference(late, True, Fp_absorbed, Fp_new) is Fp_absorbed
    assert rebase_reference(late, False, Fp_absorbed, Fp_new) is None
    late_cs = PlasticityConfig(absorb_control=True, absorb_target="shape", absorb_start_frame=30, continuous_stress=True)
    assert rebase_reference(late_cs, True, Fp_absorbed, Fp_new) is Fp_new
    with pytest.raises(ValueError, match="absorb_start_frame"):
        PlasticityConfig(absorb_start_frame=0)


def _sphere_particles(res: int, ppc_surface: int):
    import trimesh

    from physmorph.base.grid import Grid
    from physmorph.meshes.particles import sample_volume

    grid = Grid(res, -4.0, 4.0)
    x, _, _ = sample_volume(trimesh.creation.icosphere(subdivisions=3, radius=2.5), grid, ppc_surface, 1, seed=0)
    return x, grid


def test_neighbour_pool_keeps_a_sampling_of_its_density_whole_and_thins_a_denser_one_to_the_same_cells():
    """neighbour_pool (PlasticityConfig.neighbour_ppc): a sampling of at most ppc particles per cell
    per axis (the default's PPC 2/1) is kept whole, so the update is the same as without a pool; a
    denser one (PPC 5 at the surface, as the paper profile) keeps the particle nearest the centre of
    each sub-cell of dx / ppc, and k neighbours drawn from it span the cells they span at PPC 2."""
    from physmorph.plasticity.step import neighbour_pool

    x2, grid = _sphere_particles(16, 2)
    assert neighbour_pool(x2, grid.lo, grid.dx, 2) is None
    assert neighbour_pool(x2, grid.lo, grid.dx, 0) is None
    x5, _ = _sphere_particles(16, 5)
    pool = neighbour_pool(x5, grid.lo, grid.dx, 2)
    h = grid.dx / 2
    cell = np.floor((x5 - grid.lo) / h).astype(int)
    keys = {tuple(c) for c in cell}
    assert len(pool) == len(keys) and len({tuple(c) for c in cell[pool]}) == len(pool)  # one per sub-cell
    centre_dist = np.linalg.norm(x5 - (grid.lo + (cell + 0.5) * h), axis=1)
    best = {}
    for i, c in enumerate(map(tuple, cell)):
        if c not in best or centre_dist[i] < centre_dist[best[c]]:
            best[c] = i
    assert sorted(best.values()) == pool.tolist()  # the one nearest its sub-cell's centre
    radius = {name: np.median(cKDTree(src).query(x, k=64)[0][:, -1]) / grid.dx
              for name, src, x in (("ppc2", x2, x2), ("ppc5", x5, x5), ("ppc5_pool", x5[pool], x5))}
    assert radius["ppc5"] < 0.6 * radius["ppc2"]  # counted in particles, a neighbourhood shrinks with the density
    assert radius["ppc5_pool"] == pytest.approx(radius["ppc2"], rel=0.15)


def test_plasticity_step_takes_its_neighbours_from_the_pool():
    """With a pool every particle's neighbours come from it: the whole set as the pool is the step
    without one, and with a pool an affine displacement field's Jacobian is A M_i, M_i the moments
    of the particle's neighbours in the pool (not those among every particle)."""
    from physmorph.plasticity.step import neighbour_pool

    x, grid = _sphere_particles(16, 4)
    pool = neighbour_pool(x, grid.lo, grid.dx, 2)
    assert 0 < len(pool) < len(x) / 4
    A = np.array([[0.02, 0.01, -0.01], [0.0, -0.03, 0.01], [0.01, 0.0, 0.02]])
    dest = x + x @ A.T + 0.1
    Fp = np.tile(np.eye(3), (len(x), 1, 1))
    cfg = PlasticityConfig(damping=0.0, smooth_iters=2, k_neighbors=32)
    plain = chamfer_plasticity_step(x, Fp, x[:10], cfg, destination=dest)
    whole = chamfer_plasticity_step(x, Fp, x[:10], cfg, destination=dest, pool=np.arange(len(x)))
    np.testing.assert_array_equal(plain.Fp, whole.Fp)
    # unsmoothed (an average over one-sided neighbours moves an affine field), d_j - d_i = A (x_j - x_i)
    pooled = chamfer_plasticity_step(x, Fp, x[:10], dataclasses.replace(cfg, smooth_iters=0), destination=dest, pool=pool)
    eta = pooled.eta[:, None, None]
    want = {}
    for name, source in (("pool", pool), ("all", np.arange(len(x)))):
        J = A @ _neighbourhood_moments(x, nearest_neighbours(x, source, 32)[0])
        want[name] = np.eye(3) + eta * 0.5 * (J + J.transpose(0, 2, 1))
    np.testing.assert_allclose(pooled.Fp, want["pool"], atol=1e-10)
    assert np.abs(pooled.Fp - want["all"]).max() > 1e-6  # 1.7e-4: the pool's neighbourhoods are wider


def test_a_rest_scale_moves_the_rest_volume_and_damps_toward_the_scaled_identity():
    """rest_scale (s_from, s): the step acts on Fp / s_from and returns s times the result, so a
    translation (zero Jacobian) damps Fp toward s I, det Fp then s³ times the unscaled step's."""
    x = _lattice(6)
    Fp = np.tile(np.diag([1.2, 1.0, 1 / 1.2]), (len(x), 1, 1))
    target = x + np.array([0.1, 0.0, 0.0])
    cfg = PlasticityConfig(k_neighbors=16, det_bounds=(0.1, 10.0), max_anisotropy=10.0)
    s_from, s = 0.9, 0.85
    res = chamfer_plasticity_step(x, s_from * Fp, target, cfg, rest_scale=(s_from, s))
    assert np.allclose(res.Fp, s * (0.95 * Fp + 0.05 * np.eye(3)), atol=1e-9)
    plain = chamfer_plasticity_step(x, Fp, target, cfg)
    assert np.allclose(np.linalg.det(res.Fp), s ** 3 * np.linalg.det(plain.Fp), rtol=1e-9)
