"""The morph loop's per-frame measures of the particle state, each in one Taichi pass.

At the paper's scale (471K particles) the NumPy forms of these measures took ~1.5 s of every
frame: F Fp^-1 and its singular values for the elastic energy, Fp's singular values twice (the
metric's anisotropy and the stability monitor's clamp check), the particles' grid mass for the
volume IoU, and the surface mask's voxel density. Here each is one pass over the particles with the same formulas; the NumPy forms stay
the reference the tests compare against (physmorph.base.linalg3, physmorph.mpm.state,
physmorph.base.grid.splat_mass).

- :func:`deformation_measures`: for each particle, with Fe = F Fp^-1 (the elastic part, paper
  section 4 "Physics rollout", no control field), the shear term sum_i (s_i - 1)^2 = ||Fe - R||_F^2
  over Fe's signed singular values (the smallest negated where det Fe < 0), J = det Fe, det Fp and
  Fp's anisotropy s_max / s_min. Singular values as in linalg3.singular_values: the eigenvalues of
  M^T M by the trigonometric formula, the smallest taken from |det M| / (s1 s2).
- :func:`frame_strain`: a quantile over particles of |F_end F_start^-1 - I|_F, the deformation
  of one frame (the NumPy form, frame_strain_reference: ~0.5 s of a paper-scale frame on 2 cores).
- :func:`grid_mass`: m_I = sum_p w_Ip m_p with the quadratic B-spline of physmorph.base.grid (the MPM
  P2G mass transfer), stencil entries outside the grid dropped.
- :func:`voxel_density`: the surface mask's trilinear splat onto voxel centres
  (physmorph.morph.surface_mask.density_grid).
"""

# No "from __future__ import annotations": Taichi needs the kernel annotations as objects.

from dataclasses import dataclass

import numpy as np
import taichi as ti

from physmorph.base.grid import Grid
from physmorph.base.linalg3 import inverse3
from physmorph.settings.mpm import MPMConfig
from physmorph.mpm.state import volume_energy_density
from physmorph.base.linalg3_funcs import det3, matrix_at, singular_values3
from physmorph.base.taichi_runtime import ensure_taichi


@ti.kernel
def _deformation_kernel(F: ti.types.ndarray(dtype=ti.f64, ndim=3),  # [N, 3, 3]
                        Fp: ti.types.ndarray(dtype=ti.f64, ndim=3),  # [N, 3, 3]
                        shear: ti.types.ndarray(dtype=ti.f64, ndim=1),  # [N] out
                        det_elastic: ti.types.ndarray(dtype=ti.f64, ndim=1),  # [N] out
                        det_plastic: ti.types.ndarray(dtype=ti.f64, ndim=1),  # [N] out
                        anisotropy_plastic: ti.types.ndarray(dtype=ti.f64, ndim=1)):  # [N] out
    for p in range(F.shape[0]):
        Fm, P = matrix_at(F, p), matrix_at(Fp, p)
        Fe = Fm @ P.inverse()
        s = singular_values3(Fe)
        J = det3(Fe)
        if J < 0.0:
            s[2] = -s[2]
        shear[p] = ((s - 1.0) ** 2).sum()
        det_elastic[p] = J
        det_plastic[p] = det3(P)
        sp = singular_values3(P)
        anisotropy_plastic[p] = sp[0] / ti.max(sp[2], 1e-12)


@ti.kernel
def _splat_kernel(x: ti.types.ndarray(dtype=ti.f64, ndim=2),  # [N, 3]
                  weight: ti.types.ndarray(dtype=ti.f64, ndim=1),  # [N]
                  out: ti.types.ndarray(dtype=ti.f64, ndim=3),  # [R, R, R], zeroed, added to
                  lo: ti.f64, inv_h: ti.f64, quadratic: ti.template()):
    """out_I += w_Ip weight_p with g = (x - lo) / h - 1/2, base = floor(g), t = g - base: the
    quadratic B-spline on nodes lo + I h (0.5 (1 - t)^2, 0.75 - (t - 1/2)^2, 0.5 t^2; grid.bspline_weights)
    or the trilinear weights on voxel centres lo + (I + 1/2) h (1 - t, t); entries off the grid dropped."""
    R = out.shape[0]
    for p in range(x.shape[0]):
        g = ti.Vector([x[p, 0] - lo, x[p, 1] - lo, x[p, 2] - lo]) * inv_h - 0.5
        base = ti.floor(g, ti.i32)
        t = g - ti.cast(base, ti.f64)
        w = [0.5 * (1.0 - t) ** 2, 0.75 - (t - 0.5) ** 2, 0.5 * t ** 2] if ti.static(quadratic) else [1.0 - t, t]
        for a, b, c in ti.static(ti.ndrange(len(w), len(w), len(w))):
            I = base + ti.Vector([a, b, c])
            if 0 <= I[0] < R and 0 <= I[1] < R and 0 <= I[2] < R:
                out[I[0], I[1], I[2]] += w[a][0] * w[b][1] * w[c][2] * weight[p]


@ti.kernel
def _frame_strain_kernel(F_start: ti.types.ndarray(dtype=ti.f64, ndim=3),  # [N, 3, 3]
                         F_end: ti.types.ndarray(dtype=ti.f64, ndim=3),  # [N, 3, 3]
                         out: ti.types.ndarray(dtype=ti.f64, ndim=1)):  # [N] out; NaN where F_start is singular
    """out_p = |F_end F_start^-1 - I|_F (frame_strain)."""
    for p in range(F_start.shape[0]):
        A = matrix_at(F_start, p)
        det = det3(A)
        if det == 0.0 or not (ti.abs(det) < ti.math.inf):
            out[p] = ti.math.nan
        else:
            D = matrix_at(F_end, p) @ A.inverse() - ti.Matrix.identity(ti.f64, 3)
            out[p] = ti.sqrt((D * D).sum())


@dataclass(frozen=True)
class DeformationMeasures:
    """Per particle, from F and Fp (module docstring)."""

    shear: np.ndarray  # [N] sum_i (s_i(Fe) - 1)^2, Fe = F Fp^-1, signed singular values
    det_elastic: np.ndarray  # [N] det Fe
    det_plastic: np.ndarray  # [N] det Fp
    anisotropy_plastic: np.ndarray  # [N] largest over smallest singular value of Fp

    def elastic_energy(self, volume: np.ndarray,  # [N] rest volumes V0_p
                       cfg: MPMConfig) -> float:
        """sum_p V0_p Psi(Fe_p), Psi = mu ||Fe - R||^2 + Psi_vol(J) (physmorph.mpm.state.elastic_energy)."""
        psi = cfg.mu * self.shear + volume_energy_density(self.det_elastic, cfg.lam)
        return float((np.asarray(volume) * psi).sum())


def deformation_measures(F: np.ndarray,  # [N, 3, 3]
                         Fp: np.ndarray) -> DeformationMeasures:  # [N, 3, 3]
    """The shear term and determinant of Fe = F Fp^-1 and Fp's determinant and anisotropy, in
    float64, one Taichi pass (module docstring)."""
    ensure_taichi()
    F = np.ascontiguousarray(F, dtype=np.float64).reshape(-1, 3, 3)
    Fp = np.ascontiguousarray(Fp, dtype=np.float64).reshape(-1, 3, 3)
    if F.shape != Fp.shape:
        raise ValueError(f"F has shape {F.shape} and Fp {Fp.shape}; they must match")
    out = [np.empty(len(F)) for _ in range(4)]
    if len(F):
        _deformation_kernel(F, Fp, *out)
    return DeformationMeasures(*out)


# The share of the particles frame_strain's value is above: the body's strain rate, not one
# particle's (a frame's largest strain is a few particles at a fold, 5-20 times the 99th percentile).
FRAME_STRAIN_QUANTILE = 0.99


def frame_strain(F_start: np.ndarray,  # [N, 3, 3] F at the frame's start
                 F_end: np.ndarray,  # [N, 3, 3] F at its end
                 quantile: float = FRAME_STRAIN_QUANTILE) -> float:
    """The ``quantile`` over particles of |F_end F_start^-1 - I|_F: the deformation the body went
    through in one frame (0 for a rigid translation, ~|dt| x the velocity gradient for a small
    one). Each frame records it (the frame_strain metric)."""
    F_start = np.asarray(F_start, dtype=np.float64).reshape(-1, 3, 3)
    F_end = np.asarray(F_end, dtype=np.float64).reshape(-1, 3, 3)
    if F_start.shape != F_end.shape:
        raise ValueError(f"F_start has shape {F_start.shape} and F_end {F_end.shape}; they must match")
    if not len(F_start):
        return 0.0
    ensure_taichi()
    per = np.empty(len(F_start))
    _frame_strain_kernel(np.ascontiguousarray(F_start), np.ascontiguousarray(F_end), per)
    if not np.isfinite(per).all():  # as inverse3 names it
        bad = int(np.argmax(~np.isfinite(per)))
        raise np.linalg.LinAlgError(f"matrix {bad} of {len(per)} is singular or not finite (F_start)")
    return float(np.quantile(per, quantile))


def frame_strain_reference(F_start: np.ndarray,  # [N, 3, 3]
                           F_end: np.ndarray,  # [N, 3, 3]
                           quantile: float = FRAME_STRAIN_QUANTILE) -> float:
    """frame_strain in NumPy (inverse3, a batched product), the reference the tests compare with."""
    frame = np.asarray(F_end, dtype=np.float64).reshape(-1, 3, 3) @ inverse3(F_start)
    return float(np.quantile(np.linalg.norm(frame - np.eye(3), axis=(1, 2)), quantile))


def grid_mass(x: np.ndarray,  # [N, 3]
              mass: np.ndarray,  # [N]
              grid: Grid) -> np.ndarray:  # [res, res, res]
    """Particle mass on the grid's nodes, m_I = sum_p w_Ip m_p (physmorph.base.grid.splat_mass in one
    Taichi pass; summation order aside, the same numbers)."""
    ensure_taichi()
    x = np.ascontiguousarray(x, dtype=np.float64).reshape(-1, 3)
    mass = np.ascontiguousarray(mass, dtype=np.float64).reshape(-1)
    if len(x) != len(mass):
        raise ValueError(f"{len(x)} positions and {len(mass)} masses; they must match")
    out = np.zeros((grid.res,) * 3)
    if len(x):
        _splat_kernel(x, mass, out, float(grid.lo), 1.0 / grid.dx, True)
    return out


def voxel_density(x: np.ndarray,  # [N, 3]
                  weight: np.ndarray,  # [N]
                  voxels: int, lo: float, hi: float) -> np.ndarray:  # [voxels, voxels, voxels]
    """Trilinear splat of ``weight`` onto the centres of voxels x voxels x voxels cells of
    [lo, hi]^3 (physmorph.morph.surface_mask.density_grid in one Taichi pass)."""
    ensure_taichi()
    x = np.ascontiguousarray(x, dtype=np.float64).reshape(-1, 3)
    weight = np.ascontiguousarray(weight, dtype=np.float64).reshape(-1)
    if len(x) != len(weight):
        raise ValueError(f"{len(x)} positions and {len(weight)} weights; they must match")
    out = np.zeros((voxels,) * 3)
    if len(x):
        _splat_kernel(x, weight, out, float(lo), voxels / (hi - lo), False)
    return out
