"""Batched closed-form linear algebra of 3x3 matrices, for the per-frame metrics and checks.

NumPy's batched SVD costs ~0.7 s for 471K matrices on one core; the morph loop needs only the
singular values there (the energy's ||F - R||^2, the anisotropy bound), which the trigonometric
eigenvalue formula of the symmetric 3x3 matrix M^T M (Smith 1961) gives in a few vector operations.
Eigenvalues of a symmetric matrix are perfectly conditioned, so each singular value s is accurate to
about eps ||M||^2 / s, and a repeated one to sqrt(eps) (the acos near +-1): 1e-8 relative for the
deformation gradients of a morph; the smallest is taken from |det M| / (s1 s2), which keeps a
vanishing one accurate to its own size where s1 and s2 are not small. Tests compare against
np.linalg.svd, including repeated and vanishing singular values.
"""

from __future__ import annotations

import numpy as np


def det3(M: np.ndarray) -> np.ndarray:  # [N, 3, 3] -> [N]
    """Determinants by the cofactor expansion along the first row, a few vector operations
    (np.linalg.det factors each matrix: 0.14 s against 0.03 s for 471K matrices)."""
    M = np.asarray(M)
    a, b, c = M[:, 0, 0], M[:, 0, 1], M[:, 0, 2]
    return (a * (M[:, 1, 1] * M[:, 2, 2] - M[:, 1, 2] * M[:, 2, 1])
            - b * (M[:, 1, 0] * M[:, 2, 2] - M[:, 1, 2] * M[:, 2, 0])
            + c * (M[:, 1, 0] * M[:, 2, 1] - M[:, 1, 1] * M[:, 2, 0]))


def symmetric_eigenvalues(A: np.ndarray) -> np.ndarray:  # [N, 3, 3] symmetric -> [N, 3]
    """Eigenvalues of symmetric 3x3 matrices, descending: with q = tr(A) / 3, B = (A - q I) / p and
    p = sqrt(tr((A - q I)^2) / 6), they are q + 2 p cos(phi + 2 pi k / 3), phi = acos(det(B) / 2) / 3."""
    A = np.asarray(A, dtype=np.float64)
    q = np.trace(A, axis1=1, axis2=2) / 3.0
    C = A - q[:, None, None] * np.eye(3)
    p = np.sqrt((C * C).sum(axis=(1, 2)) / 6.0)
    safe = np.where(p > 0, p, 1.0)
    r = np.clip(det3(C / safe[:, None, None]) / 2.0, -1.0, 1.0)
    phi = np.arccos(r) / 3.0
    e1 = q + 2.0 * p * np.cos(phi)
    e3 = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    e2 = 3.0 * q - e1 - e3
    return np.stack([e1, e2, e3], axis=1)  # cos(phi) >= cos(phi + 2pi/3 k): e1 >= e2 >= e3


def singular_values(M: np.ndarray) -> np.ndarray:  # [N, 3, 3] -> [N, 3]
    """Singular values of each M, descending (>= 0): the square roots of the eigenvalues of M^T M."""
    M = np.asarray(M, dtype=np.float64)
    e = symmetric_eigenvalues(np.einsum("nji,njk->nik", M, M))
    s = np.sqrt(np.maximum(e, 0.0))
    # The smallest from |det M| = s1 s2 s3: det M is accurate to eps relative where the eigenvalue
    # of M^T M is accurate only to eps ||M||^2, so a vanishing s3 keeps its relative precision.
    s12 = s[:, 0] * s[:, 1]
    ok = s12 > 0
    s[ok, 2] = np.minimum(np.abs(det3(M[ok])) / s12[ok], s[ok, 1])
    return s


def signed_singular_values(M: np.ndarray) -> np.ndarray:  # [N, 3, 3] -> [N, 3]
    """The singular values with the smallest negated where det M < 0: the diagonal of M = U S V^T
    with U and V rotations (what the inversion-safe polar decomposition's stretch sees)."""
    s = singular_values(M)
    s[det3(M) < 0, 2] *= -1.0
    return s
