"""P2G's stress on packs of particles, for the CPU's vector units (paper section 4, "Physics
rollout"; the constitutive model of physmorph.mpm.stress): the warm-started polar decomposition
Fe = R S and the MLS-MPM affine term A = -dt V0 (4/dx^2) P(Fe) Fe^T + m C of PACK particles at
once, P(Fe) = 2 mu (Fe - R) + lam (J - 1) cof(Fe).

Why packs: Taichi's CPU code runs one particle per loop iteration on scalar registers, and its
kernels ran at the rate of scalar fused multiply-adds (benchmarks/bench_roofline.py). LLVM's SLP
vectoriser, which Taichi runs, turns PACK identical scalar chains side by side into vector
instructions (8 float32 lanes in a 256-bit register). So a pack holds each quantity of PACK
particles as a row of PACK lanes: a 3x3 matrix per particle is a list of 9 Taichi vectors of
PACK lanes, entry (i, j) at 3 i + j, and every operation is written row by row.

The row-wise helpers are plain Python functions that build the expressions while Taichi compiles
(no Taichi function: inlining [9, PACK] matrices through Taichi functions, whose arguments and
results are local variables, made the polar decomposition's kernel compile 13 times slower). What
a helper returns for later rows to use is made Taichi variables (pack_values): Taichi compiles an
expression tree once per use, so trees nested through several helpers would compile
exponentially often.

The vectoriser needs a start: LLVM's SLP pass begins at stores to consecutive addresses or at
bundles of loop-carried values. Here it starts at the Newton loop's rotation (72 values carried
round the loop); a pack's stores go to its particles' own matrices, 36 B apart. Kernels without
such a loop vectorise only where their results are stored a row of lanes at a time (a field of
PACK-lane vectors; a scalar field's index arithmetic in 32-bit integers hides that its lanes
are consecutive).

The arithmetic per lane is polar_from's (physmorph.mpm.stress): the same Newton steps
R <- R exp(omega^), (tr S - S) omega = axial(S0 - S0^T), from the rotation one substep earlier,
each lane stopping where polar_from stops. A branch cannot differ between lanes, so a lane that
is done keeps its R while the others step, and the steps end when every lane is done. At the
first substep, where polar_from has no warm rotation and takes the SVD, the packs start the steps
from Higham's scaled Newton iteration instead (polar_start: a few vector steps where the SVD cost a
tenth of a forward's P2G). A lane that polar_from would hand to the SVD (pair sums below the
bound: near an inversion; no convergence within its steps; at the first substep, an inverted or
singular Fe) is marked, and P2G takes it through polar (the SVD) itself
(physmorph.mpm.transfers). The results are polar_from's, or at the first substep the SVD's, to
the float's round-off (the operations' order differs); tests/mpm/test_mpm_stress_packs.py
compares them.
"""

import warnings
from types import SimpleNamespace

import taichi as ti
from taichi.lang import impl
from taichi.lang.impl import expr_init

from physmorph.base import taichi_runtime  # noqa: F401  (Taichi's fast class test, before the kernels below)
from .stress import SERIES_ANGLE, WARM_GAP_MIN, warm_start_steps

PACK = 8  # particles a pack: a 256-bit vector register of float32
# polar_start's most steps, and per float type the relative move below which a lane has
# converged (the iteration converges quadratically: the error left is about its square)
POLAR_START_STEPS = 12
POLAR_START_TOL = {"f64": 1e-10, "f32": 1e-5}
ENTRIES = [(i, j) for i in range(3) for j in range(3)]  # a pack's rows: entry (i, j) at 3 i + j

# Taichi warns at every call of a plain Python function inside a kernel; the pack's helpers are
# called there on purpose (module docstring) and are named pack_*
warnings.filterwarnings("ignore", message=r'.*Calling non-taichi function "[\w.]*pack_', category=SyntaxWarning)


def pack_values(rows: list) -> list:
    """The rows as Taichi local variables. An expression a helper builds is a tree, and Taichi
    compiles a tree once for every place that uses it: a row used by several later rows, whose
    results are used several times again, would be compiled a number of times that grows
    exponentially with the helpers' nesting (a chain of 8 steps each using the one before twice
    took 20 s to compile, 0.1 s with a variable at each step). A variable is compiled once."""
    return [expr_init(row) for row in rows]


def pack_rows(M) -> list:
    """The rows of a [9, PACK] Taichi matrix as a list of PACK-lane vectors (expressions). A plain
    Python helper indexes through impl.subscript: M[r, lane] is translated only in Taichi's scope."""
    return [ti.Vector([impl.subscript(None, M, r, lane) for lane in range(PACK)]) for r in range(9)]


def pack_product(A: list, B: list, transpose_a: bool = False, transpose_b: bool = False) -> list:
    """A B (or with A^T, B^T) lane by lane."""
    def a(i, k):
        return A[3 * k + i] if transpose_a else A[3 * i + k]

    def b(k, j):
        return B[3 * j + k] if transpose_b else B[3 * k + j]

    return pack_values([a(i, 0) * b(0, j) + a(i, 1) * b(1, j) + a(i, 2) * b(2, j) for i, j in ENTRIES])


def pack_symmetric(A: list) -> list:
    return pack_values([0.5 * (A[3 * i + j] + A[3 * j + i]) for i, j in ENTRIES])


def pack_frobenius(A: list):
    total = A[0] * A[0]
    for entry in A[1:]:
        total = total + entry * entry
    return ti.sqrt(total)


def pack_determinant(A: list):
    return (A[0] * (A[4] * A[8] - A[5] * A[7]) - A[1] * (A[3] * A[8] - A[5] * A[6])
            + A[2] * (A[3] * A[7] - A[4] * A[6]))


def pack_cofactor(F: list) -> list:
    """cof(F) = J F^-T lane by lane: column c is the cross product of F's columns c + 1 and c + 2."""
    def entry(r, c):
        a, b, s, t = (c + 1) % 3, (c + 2) % 3, (r + 1) % 3, (r + 2) % 3
        return F[3 * s + a] * F[3 * t + b] - F[3 * t + a] * F[3 * s + b]

    return pack_values([entry(r, c) for r, c in ENTRIES])


def pack_pair_sums_exceed(S: list, c):
    """stress.pair_sums_exceed lane by lane: every s_i + s_j of the symmetric S above c."""
    t = S[0] + S[4] + S[8] - c
    a00, a11, a22 = t - S[0], t - S[4], t - S[8]
    a01, a02, a12 = -S[1], -S[2], -S[5]
    minor2 = a00 * a11 - a01 * a01
    det = a00 * (a11 * a22 - a12 * a12) - a01 * (a01 * a22 - a12 * a02) + a02 * (a01 * a12 - a11 * a02)
    return (a00 > 0.0) & (minor2 > 0.0) & (det > 0.0)


def pack_rotation_step(S0: list, S: list):
    """stress.newton_step's omega, lane by lane: (tr S - S) omega = axial(S0 - S0^T), the
    symmetric solve by its adjugate; returns omega's components and |omega|^2."""
    t = S[0] + S[4] + S[8]
    m00, m11, m22 = t - S[0], t - S[4], t - S[8]
    m01, m02, m12 = -S[1], -S[2], -S[5]
    c00, c01, c02, c11, c12, c22 = pack_values([m11 * m22 - m12 * m12, m02 * m12 - m01 * m22, m01 * m12 - m11 * m02,
                                                m00 * m22 - m02 * m02, m01 * m02 - m00 * m12, m00 * m11 - m01 * m01])
    inv_det = 1.0 / (m00 * c00 + m01 * c01 + m02 * c02)
    r0, r1, r2 = S0[7] - S0[5], S0[2] - S0[6], S0[3] - S0[1]
    o0, o1, o2 = pack_values([(c00 * r0 + c01 * r1 + c02 * r2) * inv_det, (c01 * r0 + c11 * r1 + c12 * r2) * inv_det,
                              (c02 * r0 + c12 * r1 + c22 * r2) * inv_det])
    return o0, o1, o2, o0 * o0 + o1 * o1 + o2 * o2


def pack_exp(o0, o1, o2, th2, a, b) -> list:
    """exp(omega^) = I + a K + b K^2 (K = omega^, K^2 = omega omega^T - th^2 I), a and b
    Rodrigues' coefficients, lane by lane."""
    return pack_values([1.0 + b * (o0 * o0 - th2), b * o0 * o1 - a * o2, b * o0 * o2 + a * o1,
                        b * o1 * o0 + a * o2, 1.0 + b * (o1 * o1 - th2), b * o1 * o2 - a * o0,
                        b * o2 * o0 - a * o1, b * o2 * o1 + a * o0, 1.0 + b * (o2 * o2 - th2)])


def pack_quaternion(R: list) -> list:
    """MPMModel.quaternion_of lane by lane: the unit quaternion (w, x, y, z) of the rotation R,
    each lane's Shepperd branch picked by the same tests and its components selected, not branched
    to. Returns its 4 components."""
    trace = R[0] + R[4] + R[8]
    first = trace > 0.0
    second = ~first & (R[0] > R[4]) & (R[0] > R[8])
    third = ~first & ~second & (R[4] > R[8])
    arg = ti.select(first, 1.0 + trace, ti.select(second, 1.0 + R[0] - R[4] - R[8],
                                                  ti.select(third, 1.0 + R[4] - R[0] - R[8], 1.0 + R[8] - R[0] - R[4])))
    r = 2.0 * ti.sqrt(ti.max(arg, 0.0))
    quarter, inv_r = 0.25 * r, 1.0 / r
    # the branches' other components: differences and sums of R's off-diagonal pairs over r
    wx, wy, wz = (R[7] - R[5]) * inv_r, (R[2] - R[6]) * inv_r, (R[3] - R[1]) * inv_r
    xy, xz, yz = (R[1] + R[3]) * inv_r, (R[2] + R[6]) * inv_r, (R[5] + R[7]) * inv_r
    return [ti.select(first, quarter, ti.select(second, wx, ti.select(third, wy, wz))),
            ti.select(first, wx, ti.select(second, quarter, ti.select(third, xy, xz))),
            ti.select(first, wy, ti.select(second, xy, ti.select(third, quarter, yz))),
            ti.select(first, wz, ti.select(second, xz, ti.select(third, yz, quarter)))]


def make_polar_start(dtype):
    """polar_start(Fe) for one float type (make_pack_funcs' polar_from starts from it)."""
    start_tol = POLAR_START_TOL["f64" if dtype == ti.f64 else "f32"]

    @ti.func
    def polar_start(Fe: ti.template()):
        """A rotation near Fe's polar one where no warm one is kept (the first substep): Higham's
        scaled Newton iteration X <- (z X + X^-T / z) / 2, z = (|X^-1|_F / |X|_F)^(1/2), from
        X = Fe, converging to the orthogonal polar factor of any nonsingular Fe (det -1 where det Fe
        < 0). Stops once every lane moves less than POLAR_START_TOL (relative); polar_from's Newton
        steps then check it, and a lane they cannot take (an inverted or singular Fe: its X has
        det -1 or is 0; no convergence) goes to the SVD as before."""
        X = ti.Matrix.rows(Fe)
        for _ in range(POLAR_START_STEPS):
            Xr = pack_values(pack_rows(X))
            cof = pack_cofactor(Xr)  # det(X) X^-T
            det = Xr[0] * cof[0] + Xr[1] * cof[1] + Xr[2] * cof[2]
            norm = pack_frobenius(Xr)
            regular = ti.abs(det) > dtype(1e-12) * norm * norm * norm
            inv_det = ti.select(regular, 1.0 / ti.select(regular, det, 1.0), 0.0)
            z = ti.sqrt(pack_frobenius(cof) * ti.abs(inv_det) / ti.select(regular, norm, 1.0))
            inv_z_det = ti.select(regular, inv_det / ti.select(regular, z, 1.0), 0.0)
            X_next = pack_values([0.5 * (z * Xr[r] + inv_z_det * cof[r]) for r in ti.static(range(9))])
            moved = pack_frobenius([X_next[r] - Xr[r] for r in ti.static(range(9))])
            X = ti.Matrix.rows([ti.select(regular, X_next[r], 0.0) for r in ti.static(range(9))])
            if not (regular & (moved > dtype(start_tol) * norm)).any():
                break
        return X

    return polar_start


def make_pack_funcs(dtype, mu: float, lam: float):
    """The pack's Taichi functions for one float type: polar_from(Fe, R0, fresh) -> (R, gap, needs_svd) and
    affine(Fe, R, stress_scale, mC) -> A, the matrices given as lists of rows and returned as
    [9, PACK] Taichi matrices (module docstring)."""
    steps, tol = warm_start_steps(dtype)
    polar_start = make_polar_start(dtype)

    @ti.func
    def polar_from(Fe: ti.template(), R0: ti.template(), fresh):
        """stress.polar_from lane by lane without its SVD: (R as a [9, PACK] matrix, gap,
        needs_svd), needs_svd 1 on the lanes polar_from would hand to polar (module docstring).
        ``fresh`` (every lane alike): no warm rotation is kept, R0 is ignored and polar_start
        gives the Newton steps theirs."""
        R = ti.Matrix.rows(R0)
        if fresh:
            R = polar_start(Fe)
        active = ti.abs(pack_determinant(pack_rows(R)) - 1.0) < dtype(1e-3)
        converged = active & False
        for _ in range(steps):
            Rr = pack_rows(R)
            S0 = pack_product(Rr, Fe, transpose_a=True)
            S = pack_symmetric(S0)
            active &= pack_pair_sums_exceed(S, dtype(WARM_GAP_MIN) * pack_frobenius(S))
            if not active.any():
                break
            o0, o1, o2, th2 = pack_rotation_step(S0, S)
            th = ti.sqrt(th2)
            # Rodrigues' coefficients by their series below SERIES_ANGLE (stress.newton_step)
            a = 1.0 - th2 / 6.0 * (1.0 - th2 / 20.0 * (1.0 - th2 / 42.0))
            b = 0.5 - th2 / 24.0 * (1.0 - th2 / 30.0 * (1.0 - th2 / 56.0))
            large = th > dtype(SERIES_ANGLE)
            if large.any():  # sines only where a lane needs them: a warm start's steps are small
                a = ti.select(large, ti.sin(th) / th, a)
                b = ti.select(large, (1.0 - ti.cos(th)) / th2, b)
            R_next = pack_product(Rr, pack_exp(o0, o1, o2, th2, a, b))
            R = ti.Matrix.rows([ti.select(active, R_next[r], Rr[r]) for r in ti.static(range(9))])
            done = active & (th < dtype(tol))
            converged |= done
            active &= ~done
            if not active.any():
                break
        Rr = pack_rows(R)
        S = pack_symmetric(pack_product(Rr, Fe, transpose_a=True))
        gap = dtype(WARM_GAP_MIN) * pack_frobenius(S)
        converged &= pack_pair_sums_exceed(S, gap)
        return R, gap, ~converged

    @ti.func
    def affine(Fe: ti.template(), R: ti.template(), stress_scale, mC: ti.template()):
        """A = stress_scale P(Fe) Fe^T + m C lane by lane as a [9, PACK] matrix (pack_affine),
        stress_scale = -dt V0 4/dx^2 per lane."""
        # typed here: a Python float outside Taichi's compiler becomes a float32 constant
        return ti.Matrix.rows(pack_affine(Fe, R, stress_scale, mC, dtype(2.0 * mu), dtype(lam)))

    return SimpleNamespace(polar_from=polar_from, affine=affine)


def pack_affine(Fe: list, R: list, stress_scale, mC: list, two_mu, lam) -> list:
    """stress_scale P(Fe) Fe^T + m C lane by lane, P = 2 mu (Fe - R) + lam (J - 1) cof(Fe),
    J = Fe : cof(Fe) / 3 (stress.stress_from_polar)."""
    cof = pack_cofactor(Fe)
    J3 = cof[0] * Fe[0]
    for r in range(1, 9):
        J3 = J3 + cof[r] * Fe[r]
    g = lam * (J3 / 3.0 - 1.0)
    P = [two_mu * (Fe[r] - R[r]) + g * cof[r] for r in range(9)]
    return [stress_scale * entry + mC[r] for r, entry in enumerate(pack_product(P, Fe, transpose_b=True))]
