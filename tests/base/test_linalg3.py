"""Closed-form 3x3 determinants and singular values against NumPy's, on the matrices a morph meets and the hard cases."""

import numpy as np
import pytest

from physmorph.base.linalg3 import det3, inverse3, right_stretch, signed_singular_values, singular_values, symmetric_eigenvalues
from physmorph.mpm.state import fixed_corotated_energy_density, polar_rotation


def _cases() -> np.ndarray:  # [N, 3, 3]
    rng = np.random.default_rng(0)
    rot = np.linalg.qr(rng.normal(size=(6, 3, 3)))[0]
    rot *= np.sign(np.linalg.det(rot))[:, None, None]
    diag = [np.diag(d) for d in ([1, 1, 1], [2, 1, 1], [1, 1, 0.5], [3, 2, 1], [1e-3, 1, 1], [0, 1, 2], [0, 0, 0],
                                 [5, 5, 5], [1, -1, 1], [2, 2, -0.3])]
    spun = [r @ d @ r2.T for d in diag for r, r2 in zip(rot, rot[::-1])]
    near_identity = np.eye(3) + 0.1 * rng.normal(size=(200, 3, 3))
    wild = rng.normal(size=(200, 3, 3)) * rng.uniform(0.01, 10.0, size=(200, 1, 1))
    return np.concatenate([np.array(diag, float), np.array(spun), near_identity, wild])


def test_determinants_match_numpy():
    """det3 against np.linalg.det: to round-off of the entries' products (exact zeros stay zero,
    signs of inverted matrices kept)."""
    M = _cases()
    scale = np.abs(M).reshape(len(M), -1).max(axis=1) ** 3
    assert np.all(np.abs(det3(M) - np.linalg.det(M)) <= 1e-14 * scale)
    assert det3(np.zeros((2, 3, 3))).tolist() == [0.0, 0.0]
    clear = np.abs(np.linalg.det(M)) > 1e-10 * scale
    assert np.array_equal(np.sign(det3(M[clear])), np.sign(np.linalg.det(M[clear])))
    assert det3(np.zeros((0, 3, 3))).shape == (0,)


def test_singular_values_match_numpy_svd():
    M = _cases()
    want = np.linalg.svd(M, compute_uv=False)
    got = singular_values(M)
    scale = np.abs(M).reshape(len(M), -1).max(axis=1, keepdims=True) + 1e-300
    # eigenvalues of M^T M are exact to eps |M|^2, so s to about sqrt(eps) |M| where s ~ 0; a repeated
    # value (r = +-1 in the acos) also costs sqrt(eps): 1e-8 relative, far below what the metrics need
    assert np.all(np.abs(got - want) <= 1e-7 * scale + 1e-12)
    big = want > 1e-2 * scale
    np.testing.assert_allclose(got[big], want[big], rtol=2e-8)
    assert np.all(np.diff(got, axis=1) <= 1e-12 * scale)  # descending


def test_a_vanishing_smallest_singular_value_keeps_its_relative_precision():
    """s3 -> 0 beside s1, s2 ~ 1 (a nearly flattened particle): s3 to 1e-8 of itself, where the
    eigenvalue of M^T M alone gives it only to about eps / s3^2 (1e-4 at s3 = 1e-6)."""
    rng = np.random.default_rng(3)
    rot = np.linalg.qr(rng.normal(size=(40, 3, 3)))[0]
    s3 = np.logspace(-6, -2, 40)
    M = rot @ (np.array([1.3, 0.9, 1.0])[None, :, None] * np.eye(3) * np.stack([np.ones(40), np.ones(40), s3], 1)[:, :, None]) @ rot[::-1]
    want = np.linalg.svd(M, compute_uv=False)
    np.testing.assert_allclose(singular_values(M)[:, 2], want[:, 2], rtol=1e-8)


def test_symmetric_eigenvalues_match_eigvalsh():
    M = _cases()
    A = M + M.transpose(0, 2, 1)
    np.testing.assert_allclose(symmetric_eigenvalues(A), np.linalg.eigvalsh(A)[:, ::-1],
                               atol=1e-10 * (np.abs(A).max() + 1))


def test_signed_singular_values_give_the_polar_stretch_of_inverted_matrices():
    """||F - R||^2 = sum (s_i - 1)^2 over the signed values, R the det +1 polar rotation."""
    F = _cases()
    R = polar_rotation(F)
    direct = ((F - R) ** 2).sum(axis=(1, 2))
    via_s = ((signed_singular_values(F) - 1.0) ** 2).sum(axis=1)
    # singular F (s_3 = 0: its sign, and its value to sqrt(eps)) agree to 1e-7
    np.testing.assert_allclose(via_s, direct, rtol=1e-7, atol=1e-7)
    assert (np.linalg.det(F) < 0).sum() > 50  # inverted matrices are among the cases


def test_energy_density_unchanged_by_the_closed_form():
    F = np.eye(3) + 0.2 * np.random.default_rng(1).normal(size=(300, 3, 3))
    R = polar_rotation(F)
    J = np.linalg.det(F)
    shear = 2.0 * ((F - R) ** 2).sum(axis=(1, 2))
    got = fixed_corotated_energy_density(F, 2.0, 3.0)
    np.testing.assert_allclose(got, shear + 1.5 * (J - 1.0) ** 2, rtol=1e-9, atol=1e-12)


def test_inverses_match_numpy_and_refuse_singular_matrices():
    """inverse3 against np.linalg.inv on the invertible cases (inverted ones among them), to round-off
    times the condition number; a singular matrix raises LinAlgError as NumPy's does."""
    M = _cases()
    ok = np.abs(np.linalg.det(M)) > 1e-6 * np.abs(M).reshape(len(M), -1).max(axis=1) ** 3
    A = M[ok]
    want = np.linalg.inv(A)
    cond = np.linalg.cond(A)
    err = np.abs(inverse3(A) - want).reshape(len(A), -1).max(axis=1) / np.abs(want).reshape(len(A), -1).max(axis=1)
    assert np.all(err <= 1e-14 * cond)
    np.testing.assert_allclose(inverse3(A) @ A, np.broadcast_to(np.eye(3), A.shape), atol=1e-11 * cond.max())
    assert (np.linalg.det(A) < 0).sum() > 50
    with pytest.raises(np.linalg.LinAlgError, match="matrix 1 of 2"):
        inverse3(np.stack([np.eye(3), np.diag([1.0, 0.0, 2.0])]))
    assert inverse3(np.zeros((0, 3, 3))).shape == (0, 3, 3)


def _stretch_by_svd(F: np.ndarray) -> np.ndarray:  # [N, 3, 3]
    """The reference: V diag(s) V^T from F = W diag(s) V^T."""
    _, s, Vt = np.linalg.svd(F)
    return np.einsum("nji,nj,njk->nik", Vt, s, Vt)


def test_right_stretch_matches_the_svd():
    """sqrt(F^T F) in closed form against the SVD's V diag(s) V^T: repeated singular values (a pure
    rotation, a uniaxial stretch), inverted and nearly flat matrices, to 1e-12 of |F|; symmetric;
    and F = R U with R a rotation where det F > 0."""
    F = _cases()
    keep = np.linalg.svd(F, compute_uv=False)[:, 1] > 1e-9  # U is defined unless two values vanish
    F = F[keep]
    U = right_stretch(F)
    scale = np.abs(F).reshape(len(F), -1).max(axis=1)[:, None, None]
    assert np.all(np.abs(U - _stretch_by_svd(F)) <= 1e-12 * scale + 1e-15)
    np.testing.assert_array_equal(U, U.transpose(0, 2, 1))
    pos = np.linalg.det(F) > 1e-3 * scale[:, 0, 0] ** 3
    R = F[pos] @ np.linalg.inv(U[pos])
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-10)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-10)


def test_row_blocks_give_the_values_of_the_whole_array():
    """Past ROW_BLOCK matrices each function works block by block: the same bits as one pass over
    the whole array (every operation is per matrix), in the caller's dtype, and a singular matrix
    is named by its index in the whole array."""
    from physmorph.base import linalg3

    rng = np.random.default_rng(3)
    n = 2 * linalg3.ROW_BLOCK + 17
    M = np.concatenate([np.tile(_cases(), (n // len(_cases()) + 1, 1, 1))[:n // 2],
                        np.eye(3) + 0.3 * rng.normal(size=(n - n // 2, 3, 3))])
    S = M @ M.transpose(0, 2, 1)
    whole = {"det3": linalg3._det3(M), "symmetric_eigenvalues": linalg3._symmetric_eigenvalues(S),
             "singular_values": linalg3._singular_values(M, M.transpose(0, 2, 1) @ M),
             "right_stretch": linalg3._right_stretch(M[n // 2:])}
    assert np.array_equal(det3(M), whole["det3"])
    assert np.array_equal(symmetric_eigenvalues(S), whole["symmetric_eigenvalues"])
    assert np.array_equal(singular_values(M), whole["singular_values"])
    assert np.array_equal(right_stretch(M[n // 2:]), whole["right_stretch"])
    signed = whole["singular_values"].copy()
    signed[whole["det3"] < 0, 2] *= -1.0
    assert np.array_equal(signed_singular_values(M), signed)
    G = M[n // 2:]
    assert np.array_equal(inverse3(G), linalg3._inverse3(G, 0, len(G)))
    assert det3(G.astype(np.float32)).dtype == np.float32
    G = G.copy()
    G[linalg3.ROW_BLOCK + 5] = 0.0
    with pytest.raises(np.linalg.LinAlgError, match=f"matrix {linalg3.ROW_BLOCK + 5} of {len(G)} "):
        inverse3(G)
