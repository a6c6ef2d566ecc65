"""Batched closed-form linear algebra of 3x3 matrices, for the per-frame metrics and checks.

NumPy's batched SVD costs ~0.7 s for 471K matrices on one core; the morph loop needs only the
singular values there (the energy's ||F - R||^2, the anisotropy bound), which the trigonometric
eigenvalue formula of the symmetric 3x3 matrix M^T M (Smith 1961) gives in a few vector operations.
Eigenvalues of a symmetric matrix are perfectly conditioned, so each singular value s is accurate to
about eps ||M||^2 / s, and a repeated one to sqrt(eps) (the acos near +-1): 1e-8 relative for the
deformation gradients of a morph; the smallest is taken from |det M| / (s1 s2), which keeps a
vanishing one accurate to its own size where s1 and s2 are not small. Tests compare against
np.linalg.svd, including repeated and vanishing singular values.

Each function works through its matrices ROW_BLOCK at a time: every operation is per matrix, so
the values are those of the whole array at once, while the temporaries (a few dozen arrays of a
block's size) stay in the core's cache instead of streaming through memory (inverse3 of 511K
matrices 0.09-0.14 s whole, 0.04 s by blocks; det3 0.02-0.03 s against 0.01 s).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

# matrices a function works on at a time (module docstring): 8192 x 9 float64 is 0.6 MB, a block's
# inputs, outputs and temporaries well inside a core's 2 MB L2
ROW_BLOCK = 8192


def _by_row_blocks(fn: Callable[[np.ndarray, int], np.ndarray],
                   M: np.ndarray) -> np.ndarray:  # [N, ...] -> [N, ...]
    """fn(block, start) for each block of ROW_BLOCK rows of M (start: its first row's index),
    the results in one array."""
    n = len(M)
    if n <= ROW_BLOCK:
        return fn(M, 0)
    out = None
    for a in range(0, n, ROW_BLOCK):
        part = fn(M[a:a + ROW_BLOCK], a)
        if out is None:
            out = np.empty((n, *part.shape[1:]), dtype=part.dtype)
        out[a:a + len(part)] = part
    return out


def det3(M: np.ndarray) -> np.ndarray:  # [N, 3, 3] -> [N]
    """Determinants by the cofactor expansion along the first row, a few vector operations
    (np.linalg.det factors each matrix: 0.14 s against 0.03 s for 471K matrices)."""
    return _by_row_blocks(lambda block, _: _det3(block), np.asarray(M))


def _det3(M: np.ndarray) -> np.ndarray:  # [N, 3, 3] -> [N]
    a, b, c = M[:, 0, 0], M[:, 0, 1], M[:, 0, 2]
    return (a * (M[:, 1, 1] * M[:, 2, 2] - M[:, 1, 2] * M[:, 2, 1])
            - b * (M[:, 1, 0] * M[:, 2, 2] - M[:, 1, 2] * M[:, 2, 0])
            + c * (M[:, 1, 0] * M[:, 2, 1] - M[:, 1, 1] * M[:, 2, 0]))


def symmetric_eigenvalues(A: np.ndarray) -> np.ndarray:  # [N, 3, 3] symmetric -> [N, 3]
    """Eigenvalues of symmetric 3x3 matrices, descending: with q = tr(A) / 3, B = (A - q I) / p and
    p = sqrt(tr((A - q I)^2) / 6), they are q + 2 p cos(phi + 2 pi k / 3), phi = acos(det(B) / 2) / 3."""
    return _by_row_blocks(lambda block, _: _symmetric_eigenvalues(block), np.asarray(A, dtype=np.float64))


def _symmetric_eigenvalues(A: np.ndarray) -> np.ndarray:  # [N, 3, 3] symmetric -> [N, 3]
    q = np.trace(A, axis1=1, axis2=2) / 3.0
    C = A - q[:, None, None] * np.eye(3)
    p = np.sqrt((C * C).sum(axis=(1, 2)) / 6.0)
    safe = np.where(p > 0, p, 1.0)
    r = np.clip(_det3(C / safe[:, None, None]) / 2.0, -1.0, 1.0)
    phi = np.arccos(r) / 3.0
    e1 = q + 2.0 * p * np.cos(phi)
    e3 = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    e2 = 3.0 * q - e1 - e3
    return np.stack([e1, e2, e3], axis=1)  # cos(phi) >= cos(phi + 2pi/3 k): e1 >= e2 >= e3


def singular_values(M: np.ndarray) -> np.ndarray:  # [N, 3, 3] -> [N, 3]
    """Singular values of each M, descending (>= 0): the square roots of the eigenvalues of M^T M."""
    return _by_row_blocks(lambda block, _: _singular_values(block, np.matmul(block.transpose(0, 2, 1), block)),
                          np.asarray(M, dtype=np.float64))


def _singular_values(M: np.ndarray,  # [N, 3, 3]
                     C: np.ndarray) -> np.ndarray:  # [N, 3, 3] M^T M -> [N, 3]
    s = np.sqrt(np.maximum(_symmetric_eigenvalues(C), 0.0))
    # The smallest from |det M| = s1 s2 s3: det M is accurate to eps relative where the eigenvalue
    # of M^T M is accurate only to eps ||M||^2, so a vanishing s3 keeps its relative precision.
    s12 = s[:, 0] * s[:, 1]
    ok = s12 > 0
    s[:, 2] = np.where(ok, np.minimum(np.abs(_det3(M)) / np.where(ok, s12, 1.0), s[:, 1]), s[:, 2])
    return s


def signed_singular_values(M: np.ndarray) -> np.ndarray:  # [N, 3, 3] -> [N, 3]
    """The singular values with the smallest negated where det M < 0: the diagonal of M = U S V^T
    with U and V rotations (what the inversion-safe polar decomposition's stretch sees)."""
    def signed(block: np.ndarray, _) -> np.ndarray:  # [B, 3, 3] -> [B, 3]
        s = _singular_values(block, np.matmul(block.transpose(0, 2, 1), block))
        s[_det3(block) < 0, 2] *= -1.0
        return s
    return _by_row_blocks(signed, np.asarray(M, dtype=np.float64))


def inverse3(M: np.ndarray) -> np.ndarray:  # [N, 3, 3] -> [N, 3, 3]
    """Inverses by the adjugate over the determinant, a few vector operations (np.linalg.inv
    factors each matrix: 0.26 s against ~0.03 s for 471K matrices). Accurate to about eps times
    the matrix's condition number, as a factorisation is; raises LinAlgError for a singular or
    non-finite matrix, as np.linalg.inv does for a singular one."""
    M = np.asarray(M, dtype=np.float64)
    return _by_row_blocks(lambda block, start: _inverse3(block, start, len(M)), M)


def _inverse3(M: np.ndarray,  # [B, 3, 3] rows start.. of the n inverted
              start: int, n: int) -> np.ndarray:  # [B, 3, 3]
    a, b, c = M[:, 0, 0], M[:, 0, 1], M[:, 0, 2]
    d, e, f = M[:, 1, 0], M[:, 1, 1], M[:, 1, 2]
    g, h, i = M[:, 2, 0], M[:, 2, 1], M[:, 2, 2]
    adj = np.empty_like(M)
    adj[:, 0, 0] = e * i - f * h
    adj[:, 0, 1] = c * h - b * i
    adj[:, 0, 2] = b * f - c * e
    adj[:, 1, 0] = f * g - d * i
    adj[:, 1, 1] = a * i - c * g
    adj[:, 1, 2] = c * d - a * f
    adj[:, 2, 0] = d * h - e * g
    adj[:, 2, 1] = b * g - a * h
    adj[:, 2, 2] = a * e - b * d
    det = a * adj[:, 0, 0] + b * adj[:, 1, 0] + c * adj[:, 2, 0]
    bad = ~np.isfinite(det) | (det == 0.0)
    if bad.any():
        raise np.linalg.LinAlgError(f"matrix {start + int(np.argmax(bad))} of {n} is singular or not finite (det {det[bad][0]})")
    adj /= det[:, None, None]
    return adj


def right_stretch(F: np.ndarray) -> np.ndarray:  # [N, 3, 3] -> [N, 3, 3]
    """U = sqrt(F^T F), the symmetric positive stretch of F = R U (V diag(s) V^T for F = W diag(s)
    V^T), without an SVD: with C = F^T F and the invariants of U from its eigenvalues s (the
    singular values of F), I1 = s1 + s2 + s3, I2 = s1 s2 + s2 s3 + s3 s1, I3 = s1 s2 s3,
    U = (-C^2 + (I1^2 - I2) C + I1 I3 I) / (I1 I2 - I3) (Cayley-Hamilton; Hoger and Carlson 1984).
    The denominator is (s1 + s2)(s2 + s3)(s3 + s1) > 0 unless two singular values vanish. The
    invariants are symmetric in s, so a repeated pair's sqrt(eps) error (singular_values) cancels
    in them to first order: U to ~1e-12 relative for the matrices of a morph (np.linalg.svd: 1.4 s
    against ~0.1 s for 471K)."""
    return _by_row_blocks(lambda block, _: _right_stretch(block), np.asarray(F, dtype=np.float64))


def _right_stretch(F: np.ndarray) -> np.ndarray:  # [N, 3, 3] -> [N, 3, 3]
    C = np.matmul(F.transpose(0, 2, 1), F)
    s = _singular_values(F, C)
    i1 = s.sum(axis=1)
    i2 = s[:, 0] * s[:, 1] + s[:, 1] * s[:, 2] + s[:, 2] * s[:, 0]
    i3 = np.abs(_det3(F))
    U = (i1 * i1 - i2)[:, None, None] * C - np.matmul(C, C)
    U[:, [0, 1, 2], [0, 1, 2]] += (i1 * i3)[:, None]
    U /= (i1 * i2 - i3)[:, None, None]
    return U
