"""Steps 4-5 of the Chamfer-guided plasticity (paper section 3.4, eq. 4; physmorph.plasticity.step)
and step 6's test in one Taichi pass over the particles:

    Fp' = (1 - d_p) (I + eta_i dFp_i) Fp_i / s_from + d_p I,   dFp_i = (J_i + J_i^T) / 2,

and whether Fp' already lies inside the isochoric projection's bounds (det Fp' within det_bounds,
its singular values' spread about their geometric mean within max_anisotropy, each with the
projection's relative margin), so that only the few outside need the projection's SVD.

The reference is the NumPy form, physmorph.plasticity.step.fp_update_reference (tests compare the
two). At the paper's scale (511K particles) the NumPy form took 0.3-0.55 s of a frame on one
core, its [N, 3, 3] temporaries and the closed-form singular values of the test included.
"""

# No "from __future__ import annotations": Taichi needs the kernel annotations as objects.

import numpy as np
import taichi as ti

from physmorph.base.linalg3_funcs import det3, singular_values3
from physmorph.base.taichi_runtime import ensure_taichi


@ti.func
def _inside_bounds(M, det_lo, det_hi, max_anisotropy, m):
    """Whether M is inside the projection's bounds by the relative margin m (step.INSIDE_MARGIN;
    step.inside_bounds' test): det within (det_lo, det_hi), the largest singular value under
    g sqrt(a) and the smallest over g / sqrt(a), g = det^(1/3) and a = max_anisotropy."""
    det = det3(M)
    s = singular_values3(M)
    g = ti.pow(ti.max(det, 0.0), ti.f64(1.0 / 3.0))  # typed: a Python float would enter as float32
    half = ti.sqrt(max_anisotropy)
    return (det > det_lo / m) and (det < det_hi * m) and (s[0] < g * half * m) and (s[2] * half * m > g)


@ti.kernel
def _fp_update(J: ti.types.ndarray(dtype=ti.f64, ndim=3),  # [N, 3, 3] displacement Jacobians
               eta: ti.types.ndarray(dtype=ti.f64, ndim=1),  # [N] step sizes
               Fp: ti.types.ndarray(dtype=ti.f64, ndim=3),  # [N, 3, 3]
               scale_from: ti.f64, damping: ti.f64, det_lo: ti.f64, det_hi: ti.f64, max_anisotropy: ti.f64,
               margin: ti.f64,
               out: ti.types.ndarray(dtype=ti.f64, ndim=3),  # [N, 3, 3] out: Fp'
               inside: ti.types.ndarray(dtype=ti.i8, ndim=1)):  # [N] out: 1 where Fp' needs no projection
    """Fp' = (1 - d_p) (I + eta dFp) Fp / s_from + d_p I and its bounds test (module docstring)."""
    for i in range(Fp.shape[0]):
        Jm = ti.Matrix.zero(ti.f64, 3, 3)
        A = ti.Matrix.zero(ti.f64, 3, 3)
        for a, b in ti.static(ti.ndrange(3, 3)):
            Jm[a, b] = J[i, a, b]
            A[a, b] = Fp[i, a, b] / scale_from
        eye = ti.Matrix.identity(ti.f64, 3)
        M = (eye + eta[i] * (0.5 * (Jm + Jm.transpose()))) @ A
        M = (1.0 - damping) * M + damping * eye
        for a, b in ti.static(ti.ndrange(3, 3)):
            out[i, a, b] = M[a, b]
        inside[i] = ti.i8(1) if _inside_bounds(M, det_lo, det_hi, max_anisotropy, margin) else ti.i8(0)


def fp_update(J: np.ndarray,  # [N, 3, 3]
              eta: np.ndarray,  # [N]
              Fp: np.ndarray,  # [N, 3, 3]
              damping: float, det_bounds: tuple[float, float], max_anisotropy: float, margin: float,
              scale_from: float = 1.0) -> tuple[np.ndarray, np.ndarray]:  # -> [N, 3, 3] Fp', [N] bool inside
    """Steps 4-5 and the projection's bounds test by the relative ``margin`` (step.INSIDE_MARGIN;
    module docstring): (Fp', inside)."""
    ensure_taichi()
    J = np.ascontiguousarray(J, dtype=np.float64)
    Fp = np.ascontiguousarray(Fp, dtype=np.float64)
    out = np.empty_like(Fp)
    inside = np.zeros(len(Fp), dtype=np.int8)
    if len(Fp):
        _fp_update(J, np.ascontiguousarray(eta, dtype=np.float64), Fp, float(scale_from), float(damping),
                   float(det_bounds[0]), float(det_bounds[1]), float(max_anisotropy), float(margin), out, inside)
    return out, inside.astype(bool)
