"""The constitutive model of the MPM solver (paper section 4): fixed corotated elasticity
(Stomakhin et al. 2012) as Taichi functions, P(Fe) = 2 mu (Fe - R) + g(J) cof(Fe), its
polar factors and its differential dP(Fe)[dFe] (the Hessian of Psi applied to dFe), plus
evaluate_stress, which runs them on arrays (tests and diagnostics compare it with
physmorph.mpm.reference and finite differences).

The derivative of the rotation R (which Taichi's autodiff cannot do for ti.svd) is hand-written:
dR = R omega^, (tr S - S) omega = axial(R^T dFe - dFe^T R), S = R^T Fe, with the pair sums
s_i + s_j (eigenvalues of tr S - S) floored for the singular/inverted cases.

The volume term g(J) = dPsi_vol/dJ is the paper's: Psi_vol = lam/2 (J - 1)^2, g = lam (J - 1).
Its Kirchhoff pressure g J = lam (J - 1) J is largest at J = 1/2 and falls to 0 as J -> 0: past
half its volume the material resists compression less the more it is compressed (the solver's
floor on det F, MPMConfig.min_volume_ratio, keeps it from there).
"""

from types import SimpleNamespace

import numpy as np
import taichi as ti

from physmorph.base.taichi_runtime import init_taichi

# Floor of s_i + s_j in the rotation derivative, relative to the largest singular value: keeps
# dR bounded when two singular values of an inverted Fe cancel (guard of the singular case).
_ROT_DENOM_FLOOR = 1e-6
# polar_from falls back to the SVD below this smallest pair sum, relative to |S|
WARM_GAP_MIN = 0.05
# Rodrigues' coefficients by their series to th^6 below this angle (rad): the next terms,
# th^8 / 9! and th^8 / 10!, are below 1.1e-16 there
SERIES_ANGLE = 0.05


@ti.func
def cofactor(F):
    """cof(F) = J F^-T, columns c0 = f1 x f2, c1 = f2 x f0, c2 = f0 x f1 (polynomial in F)."""
    f0 = ti.Vector([F[0, 0], F[1, 0], F[2, 0]])
    f1 = ti.Vector([F[0, 1], F[1, 1], F[2, 1]])
    f2 = ti.Vector([F[0, 2], F[1, 2], F[2, 2]])
    c0 = f1.cross(f2)
    c1 = f2.cross(f0)
    c2 = f0.cross(f1)
    return ti.Matrix.cols([c0, c1, c2])


@ti.func
def _cofactor_diff(F, dF):
    """d cof(F)[dF]: product rule on the cross products of cofactor."""
    f0 = ti.Vector([F[0, 0], F[1, 0], F[2, 0]])
    f1 = ti.Vector([F[0, 1], F[1, 1], F[2, 1]])
    f2 = ti.Vector([F[0, 2], F[1, 2], F[2, 2]])
    d0 = ti.Vector([dF[0, 0], dF[1, 0], dF[2, 0]])
    d1 = ti.Vector([dF[0, 1], dF[1, 1], dF[2, 1]])
    d2 = ti.Vector([dF[0, 2], dF[1, 2], dF[2, 2]])
    c0 = d1.cross(f2) + f1.cross(d2)
    c1 = d2.cross(f0) + f2.cross(d0)
    c2 = d0.cross(f1) + f0.cross(d1)
    return ti.Matrix.cols([c0, c1, c2])


@ti.func
def pair_sums_exceed(S, c):
    """Whether every pair sum s_i + s_j of the symmetric S's eigenvalues exceeds c, i.e.
    tr S - lambda_max(S) > c: A = (tr S - c) I - S (eigenvalues s_i + s_j - c) is positive definite,
    which Sylvester's criterion reads off its leading principal minors, without the eigenvalue's
    arccos and cos."""
    t = S.trace() - c
    a00, a11, a22 = t - S[0, 0], t - S[1, 1], t - S[2, 2]
    a01, a02, a12 = -S[0, 1], -S[0, 2], -S[1, 2]
    minor2 = a00 * a11 - a01 * a01
    det = a00 * (a11 * a22 - a12 * a12) - a01 * (a01 * a22 - a12 * a02) + a02 * (a01 * a12 - a11 * a02)
    return (a00 > 0.0) & (minor2 > 0.0) & (det > 0.0)


def warm_start_steps(dtype) -> tuple[int, float]:
    """polar_from's most Newton steps and the step angle below which it has converged (the
    step's error is ~angle^2: below the float's precision there)."""
    return (6, 1e-7) if dtype == ti.f64 else (4, 1e-4)


def make_newton_funcs(dtype):
    """The pieces of a Newton step on the rotation of Fe, for one float type: skew_solve, axial,
    hat, and newton_step (R <- R exp(omega^)); the stress's differential shares the first three."""

    @ti.func
    def skew_solve(S, gap, rhs):
        """omega with (tr(S) I - S) omega = rhs; the eigenvalues of that matrix are the pair
        sums s_i + s_j of the signed singular values; the smallest one, gap, is floored."""
        Mt = S.trace() * ti.Matrix.identity(dtype, 3) - S
        floor = _ROT_DENOM_FLOOR * ti.sqrt((S * S).sum()) + 1e-30
        if gap < floor:
            Mt += (floor - gap) * ti.Matrix.identity(dtype, 3)
        return Mt.inverse() @ rhs

    @ti.func
    def axial(W):
        return ti.Vector([W[2, 1] - W[1, 2], W[0, 2] - W[2, 0], W[1, 0] - W[0, 1]])

    @ti.func
    def hat(w):
        return ti.Matrix([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]], dtype)

    @ti.func
    def newton_step(R, S0, S, gap):
        """R <- R exp(omega^) with (tr S - S) omega = axial(S0 - S0^T), S0 = R^T Fe, S = sym(S0)
        (Rodrigues' formula, its series below a small angle); returns the new R and |omega|."""
        om = skew_solve(S, gap, axial(S0))
        th2 = om.dot(om)
        th = ti.sqrt(th2)
        # sin(th) / th and (1 - cos th) / th^2 by their series to th^6 below SERIES_ANGLE (the
        # first term left out is below float64's round-off there), so the usual small step of a
        # warm start costs no sine and cosine
        a = 1.0 - th2 / 6.0 * (1.0 - th2 / 20.0 * (1.0 - th2 / 42.0))
        b = 0.5 - th2 / 24.0 * (1.0 - th2 / 30.0 * (1.0 - th2 / 56.0))
        if th > SERIES_ANGLE:
            a = ti.sin(th) / th
            b = (1.0 - ti.cos(th)) / th2
        K = hat(om)
        return R @ (ti.Matrix.identity(dtype, 3) + a * K + b * (K @ K)), th

    return SimpleNamespace(skew_solve=skew_solve, axial=axial, hat=hat, newton_step=newton_step)


def make_rotation_funcs(dtype):
    """The polar decomposition Fe = R S as Taichi functions for one float type: polar(Fe) (SVD,
    Newton-polished in float64), polar_from(Fe, R0) (Newton steps warm-started at R0, falling back
    to polar) and the Newton step's pieces (make_newton_funcs)."""
    newton = make_newton_funcs(dtype)
    newton_step = newton.newton_step
    newton_steps = 2 if dtype == ti.f64 else 0
    warm_steps, warm_tol = warm_start_steps(dtype)

    @ti.func
    def polar(Fe):
        """Fe = R S with det R = +1 (inversion-aware): ti.svd gives R = U V^T; in float64 two
        Newton steps on the symmetry of R^T Fe polish it (ti.svd is only ~1e-6 accurate), each
        R <- R exp(omega^), (tr S - S) omega = axial(S - S^T)."""
        U, sig, V = ti.svd(Fe, dtype)
        R = U @ V.transpose()
        gap = sig[1, 1] + sig[2, 2]  # ti.svd sorts s0 >= s1 >= |s2|: smallest pair sum
        for _ in ti.static(range(newton_steps)):
            S0 = R.transpose() @ Fe
            R, _th = newton_step(R, S0, 0.5 * (S0 + S0.transpose()), gap)
        S = R.transpose() @ Fe
        return R, 0.5 * (S + S.transpose()), gap

    @ti.func
    def polar_from(Fe, R0):
        """polar(Fe) by Newton steps on the symmetry of R^T Fe started from the rotation R0 (the
        particle's rotation one substep earlier): each step R <- R exp(omega^) with
        (tr S - S) omega = axial(S0 - S0^T), S0 = R^T Fe, S = sym(S0), converging quadratically, so
        one or two steps reach float32 precision where the rotation moved little. Falls back to
        polar(Fe) (its SVD) where R0 is not a rotation (no earlier substep), where the steps have
        not converged after a few, or where the smallest pair sum of the signed singular values
        (tr S - lambda_max(S)) is below WARM_GAP_MIN |S| or negative: near an inversion, or a
        step that found another stationary rotation (R flipped by pi about an axis of S, which
        negates two eigenvalues of S and makes it negative). The pair sums are only tested against
        that bound (pair_sums_exceed, no eigenvalue), and a warm rotation's gap is the bound
        itself: a lower bound of the smallest pair sum, all the rotation's derivative needs
        (skew_solve floors the pair sums at 1e-6 |S|, far below it, so the bound and the exact
        value give the same solve). The SVD's gap is the exact smallest pair sum."""
        R = R0
        converged = False
        gap = dtype(0.0)
        if ti.abs(R0.determinant() - 1.0) < dtype(1e-3):
            for _ in range(warm_steps):
                S0 = R.transpose() @ Fe
                S = 0.5 * (S0 + S0.transpose())
                bound = dtype(WARM_GAP_MIN) * ti.sqrt((S * S).sum())
                if not pair_sums_exceed(S, bound):
                    break
                # gap > bound, far above skew_solve's floor (1e-6 |S|): the bound stands in for it
                R, th = newton_step(R, S0, S, bound)
                if th < dtype(warm_tol):  # the step's error is ~th^2: below the float's precision
                    converged = True
                    break
        S = R.transpose() @ Fe
        S = 0.5 * (S + S.transpose())
        if converged:
            gap = dtype(WARM_GAP_MIN) * ti.sqrt((S * S).sum())
            converged = pair_sums_exceed(S, gap)
        if not converged:
            R, S, gap = polar(Fe)
        return R, S, gap

    return SimpleNamespace(polar=polar, polar_from=polar_from, skew_solve=newton.skew_solve, axial=newton.axial,
                           hat=newton.hat)


def make_stress_funcs(dtype, mu: float, lam: float):
    """Fixed-corotated P(Fe), its polar factors and the
    differential dP(Fe)[dFe], for one float type. Returns a namespace of Taichi functions:
    stress(Fe), polar(Fe) -> (R, S, gap), stress_from_polar(Fe, R), stress_and_diff(Fe, dFe),
    stress_and_diff_polar(Fe, R, S, gap, dFe)."""
    rotation = make_rotation_funcs(dtype)
    polar, skew_solve, axial, hat = rotation.polar, rotation.skew_solve, rotation.axial, rotation.hat
    # Python float constants would enter kernels as f32; typed constants keep float64 exact
    two_mu = 2.0 * mu

    @ti.func
    def volume_term(J):
        """(g(J), g'(J)) = (lam (J - 1), lam), the module docstring's volume term."""
        g = dtype(lam) * (J - 1.0)
        dg = dtype(lam)
        return g, dg

    @ti.func
    def stress_from_polar(Fe, R):
        """P = 2 mu (Fe - R) + g(J) cof(Fe)  (Stomakhin et al. 2012: g = lam (J - 1)), R the rotation of Fe."""
        cof = cofactor(Fe)
        J = (cof * Fe).sum() / 3.0  # det Fe = Fe : cof(Fe) / 3
        g, _ = volume_term(J)
        return dtype(two_mu) * (Fe - R) + g * cof

    @ti.func
    def stress(Fe):
        R, S, gap = polar(Fe)
        return stress_from_polar(Fe, R)

    @ti.func
    def stress_and_diff_polar(Fe, R, S, gap, dFe):
        """(P(Fe), dP[dFe]) with the polar factors given. dR = R omega^ with
        (tr S - S) omega = axial(R^T dFe - dFe^T R) (floored pair sums: singular guard).
        dP is the Hessian of Psi applied to dFe, hence self-adjoint: the same map gives the
        reverse-mode product  Fe_bar = dP[P_bar]."""
        cof = cofactor(Fe)  # shared by P and dP
        J = (cof * Fe).sum() / 3.0
        g, dg = volume_term(J)
        P = dtype(two_mu) * (Fe - R) + g * cof
        om = skew_solve(S, gap, axial(R.transpose() @ dFe))
        dR = R @ hat(om)
        dJ = (cof * dFe).sum()
        dP = dtype(two_mu) * (dFe - dR) + dg * dJ * cof + g * _cofactor_diff(Fe, dFe)
        return P, dP

    @ti.func
    def stress_and_diff(Fe, dFe):
        R, S, gap = polar(Fe)
        return stress_and_diff_polar(Fe, R, S, gap, dFe)

    return SimpleNamespace(stress=stress, polar=polar, polar_from=rotation.polar_from,
                           stress_from_polar=stress_from_polar, stress_and_diff=stress_and_diff,
                           stress_and_diff_polar=stress_and_diff_polar)


_stress_kernels: dict = {}


def evaluate_stress(Fe: np.ndarray,  # [N, 3, 3]
                    dFe: np.ndarray,  # [N, 3, 3]
                    mu: float, lam: float, precision: str = "float64") -> tuple[np.ndarray, np.ndarray]:
    """Run the solver's Taichi stress P(Fe) and differential dP(Fe)[dFe] on arrays (for tests
    and diagnostics). Returns (P [N, 3, 3], dP [N, 3, 3]) as float64."""
    if not _runtime_ready():
        init_taichi("cpu")
    dtype = ti.f64 if precision == "float64" else ti.f32
    npd = np.float64 if precision == "float64" else np.float32
    key = (precision, float(mu), float(lam))
    if key not in _stress_kernels:
        stress_and_diff = make_stress_funcs(dtype, float(mu), float(lam)).stress_and_diff
        mat = ti.types.matrix(3, 3, dtype)

        @ti.kernel
        def run(Fe: ti.types.ndarray(dtype=mat, ndim=1), dFe: ti.types.ndarray(dtype=mat, ndim=1),
                P: ti.types.ndarray(dtype=mat, ndim=1), dP: ti.types.ndarray(dtype=mat, ndim=1)):
            for p in range(Fe.shape[0]):
                P[p], dP[p] = stress_and_diff(Fe[p], dFe[p])

        _stress_kernels[key] = run
    Fe = np.ascontiguousarray(Fe, dtype=npd).reshape(-1, 3, 3)
    dFe = np.ascontiguousarray(dFe, dtype=npd).reshape(-1, 3, 3)
    P = np.zeros_like(Fe)
    dP = np.zeros_like(Fe)
    _stress_kernels[key](Fe, dFe, P, dP)
    return P.astype(np.float64), dP.astype(np.float64)


def evaluate_polar(Fe: np.ndarray,  # [N, 3, 3]
                   R0: np.ndarray | None = None,  # [N, 3, 3] warm starts (polar_from); None: the SVD (polar)
                   precision: str = "float64") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run the solver's polar decomposition on arrays (for tests and diagnostics): (R [N, 3, 3],
    S [N, 3, 3], gap [N]) as float64, from the SVD or, with R0, from those rotations."""
    if not _runtime_ready():
        init_taichi("cpu")
    dtype = ti.f64 if precision == "float64" else ti.f32
    npd = np.float64 if precision == "float64" else np.float32
    key = ("polar", precision)
    if key not in _stress_kernels:
        funcs = make_stress_funcs(dtype, 1.0, 1.0)
        mat = ti.types.matrix(3, 3, dtype)

        @ti.kernel
        def run(Fe: ti.types.ndarray(dtype=mat, ndim=1), R0: ti.types.ndarray(dtype=mat, ndim=1), warm: ti.i32,
                R: ti.types.ndarray(dtype=mat, ndim=1), S: ti.types.ndarray(dtype=mat, ndim=1),
                gap: ti.types.ndarray(dtype=dtype, ndim=1)):
            for p in range(Fe.shape[0]):
                if warm:
                    R[p], S[p], gap[p] = funcs.polar_from(Fe[p], R0[p])
                else:
                    R[p], S[p], gap[p] = funcs.polar(Fe[p])

        _stress_kernels[key] = run
    Fe = np.ascontiguousarray(Fe, dtype=npd).reshape(-1, 3, 3)
    R0_ = np.zeros_like(Fe) if R0 is None else np.ascontiguousarray(R0, dtype=npd).reshape(-1, 3, 3)
    R, S, gap = np.zeros_like(Fe), np.zeros_like(Fe), np.zeros(len(Fe), npd)
    _stress_kernels[key](Fe, R0_, int(R0 is not None), R, S, gap)
    return R.astype(np.float64), S.astype(np.float64), gap.astype(np.float64)


def _runtime_ready() -> bool:
    from physmorph.base.taichi_runtime import taichi_state

    return bool(taichi_state())
