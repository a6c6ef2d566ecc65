"""Closed-form 3x3 linear algebra as Taichi functions, float64: the kernels' forms of
physmorph.base.linalg3 (its NumPy functions are their references)."""

# No "from __future__ import annotations": Taichi needs the annotations as objects.

import taichi as ti

from physmorph.base import taichi_runtime  # noqa: F401  (Taichi's fast class test, before the functions below)


@ti.func
def det3(M):
    """det M by the cofactor expansion along the first row (linalg3.det3)."""
    return (M[0, 0] * (M[1, 1] * M[2, 2] - M[1, 2] * M[2, 1])
            - M[0, 1] * (M[1, 0] * M[2, 2] - M[1, 2] * M[2, 0])
            + M[0, 2] * (M[1, 0] * M[2, 1] - M[1, 1] * M[2, 0]))


@ti.func
def singular_values3(M):
    """Descending singular values of a 3x3 f64 matrix (linalg3.singular_values): with A = M^T M,
    q = tr A / 3, p = sqrt(tr((A - q I)^2) / 6), phi = acos(det((A - q I) / p) / 2) / 3, the
    eigenvalues are q + 2 p cos(phi + 2 pi k / 3); s3 = min(|det M| / (s1 s2), s2)."""
    A = M.transpose() @ M
    q = (A[0, 0] + A[1, 1] + A[2, 2]) / 3.0
    C = A - q * ti.Matrix.identity(ti.f64, 3)
    p = ti.sqrt((C * C).sum() / 6.0)
    safe = p if p > 0.0 else 1.0
    r = ti.min(ti.max(det3(C / safe) / 2.0, -1.0), 1.0)
    phi = ti.acos(r) / 3.0
    e1 = q + 2.0 * p * ti.cos(phi)
    # 2 pi / 3 from f64 operations: a Python float in a kernel is an f32 literal
    e3 = q + 2.0 * p * ti.cos(phi + ti.acos(ti.cast(-0.5, ti.f64)))
    e2 = 3.0 * q - e1 - e3
    s1 = ti.sqrt(ti.max(e1, 0.0))
    s2 = ti.sqrt(ti.max(e2, 0.0))
    s3 = ti.sqrt(ti.max(e3, 0.0))
    if s1 * s2 > 0.0:
        s3 = ti.min(ti.abs(det3(M)) / (s1 * s2), s2)
    return ti.Vector([s1, s2, s3])


@ti.func
def matrix_at(a: ti.template(), p):
    """Row p of an [N, 3, 3] f64 ndarray as a matrix."""
    M = ti.Matrix.zero(ti.f64, 3, 3)
    for i, j in ti.static(ti.ndrange(3, 3)):
        M[i, j] = a[p, i, j]
    return M
