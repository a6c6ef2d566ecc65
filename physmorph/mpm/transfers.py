"""The MLS-MPM transfers of one substep, forward (paper section 4, "Physics rollout"; equations in
physmorph/mpm/solver.py's docstring): steps acting on the model, the state and the control.

    P2G:  mv_I = sum_p w_Ip [m (1 - dt d) v + A (x_I - x_p)],  m_I = sum_p w_Ip m
    grid: v_I = mv_I / m_I, outward component zeroed on the BOUNDARY_CELLS layer of each face
    G2P:  v' = sum_I w_Ip v_I,  C' = 4/dx^2 sum_I w_Ip v_I (x_I - x_p)^T,  x' = x + dt v',
          F' = (1 - s) (I + dt C') F + s F

The 27-node quadratic B-spline stencil is the model's (weights per particle). The transfers and
their adjoints walk it row by row (dynamic loops over (i, j), then k: small kernels to compile):
x_I - x_p = (off - fx) dx is affine in the node's offset, so a product with it grows by one
column per node along a row, and a sum of outer products with it is taken once per particle from
the nodes' moments; a node costs a few vector operations, not 3x3 products. P2G and the reverse of
G2P add into per-thread lanes of the grid (physmorph.mpm.lanes), not with atomic adds. The forward
stores the rotation of Fe (as a unit quaternion) with its smallest pair sum and the P2G grid per
substep; the adjoints (physmorph.mpm.transfer_adjoints) restore them instead of running P2G and its
SVD again.

On the CPU from PACKED_STRESS_MIN_PARTICLES on, P2G's polar decomposition (with its quaternion
and pair sum) and affine term run first on packs of particles (p2g_stress:
physmorph.mpm.stress_packs, in the vector units), and P2G's particle loop reads A; the particles a
pack marks go through the SVD there. Below that size and on a GPU one kernel does both, a
particle an iteration; it is also the packs' reference (Transfers(..., packed=False)). At the
same scale P2G's and G2P's node loops are unrolled over the stencil's rows: in a loop over the
rows the weights w[i], w[j] are indexed at run time, from memory; unrolled they stay in registers
(at the paper's scale each kernel 30-45 % faster; its compilation ~6 s longer, a cost the small
solvers of the tests and the default profile do not pay).
"""

import taichi as ti

from physmorph.base import taichi_runtime  # noqa: F401  (Taichi's fast class test, before the kernels below)
from .control import ControlField
from .lanes import LANE_BLOCK
from .model import MPMModel
from .stress_packs import ENTRIES, PACK, make_pack_funcs, pack_quaternion, pack_rows
from .trajectory import Trajectory


@ti.data_oriented
class Transfers:
    """P2G, the grid update and G2P of substep t: s_t and dFc_t -> s_(t+1)."""

    def __init__(self, model: MPMModel, trajectory: Trajectory, control: ControlField, packed: bool | None = None):
        self.model, self.trajectory, self.control = model, trajectory, control
        self.n, self.dtype = model.n, model.dtype
        # P2G's stress on packs first (the CPU, from PACKED_STRESS_MIN_PARTICLES on; module
        # docstring): a compile-time constant
        if packed is None:
            packed = model.at_scale
        self.packed = bool(packed)
        # at the same scale P2G's and G2P's rows of the stencil are unrolled (module docstring)
        self.unrolled = self.packed
        self.packs = (self.n + PACK - 1) // PACK
        if self.packed:
            cfg = model.cfg
            self.pack = make_pack_funcs(self.dtype, cfg.mu, cfg.lam)
            # the substep's A per particle, as p2g_stress leaves it for p2g
            self.affine = ti.types.matrix(3, 3, self.dtype).field(shape=self.n)

    def run_p2g(self, t: int) -> None:
        """P2G of substep t into the lanes (or the grid): its stress pass first on the CPU."""
        if self.packed:
            self.p2g_stress(t)
        self.p2g(t)

    @ti.kernel
    def clear_grid(self):
        """m_I and mv_I zero (before an atomic scatter into them: the loss's splat, P2G on a GPU)."""
        for I in ti.grouped(self.trajectory.grid_m):
            self.trajectory.grid_mv[I] = ti.Vector.zero(self.dtype, 3)
            self.trajectory.grid_m[I] = 0.0

    @ti.kernel
    def p2g(self, t: ti.i32):
        """Fe = (F + dFc_t) Fp^-1, A = -dt V0 (4/dx^2) P(Fe) Fe^T + m C;
        mv_I += w_Ip (m (1 - dt d) v_p + A_p (x_I - x_p)),  m_I += w_Ip m_p, into the lanes
        (physmorph.mpm.lanes; grid_update sums them). The rotation of Fe and its pair sum are kept
        per substep (R_q, gap_t), so the backward (TransferAdjoints._restore_particle) needs no second SVD."""
        lanes = self.trajectory.lanes
        if ti.static(lanes.private):
            ti.loop_config(block_dim=LANE_BLOCK)
            for c in range(lanes.blocks):
                for p in range(lanes.first(c), lanes.first(c + 1)):
                    self._p2g_particle(t, p, c // LANE_BLOCK)
        else:
            for p in range(self.n):
                self._p2g_particle(t, p, 0)

    @ti.func
    def _fe(self, t, p):
        """Fe = (F + dFc_t) Fp^-1 of particle p at substep t."""
        return (self.trajectory.F[t, p] + self.control.ctrl[t, p]) @ self.model.Fp_inv[p]

    @ti.func
    def _stress_scale(self, p):
        """-dt V0 4/dx^2: A's factor on P(Fe) Fe^T."""
        kq = 4.0 * self.dtype(self.model.inv_dx) * self.dtype(self.model.inv_dx)
        return -self.dtype(self.model.cfg.dt) * self.model.vol[p] * kq

    @ti.func
    def _affine(self, t, p, warm):
        """A of particle p at substep t from its own polar decomposition (warm: from R_prev),
        the rotation, its quaternion and its pair sum kept in R_prev, R_q and gap_t."""
        Fe = self._fe(t, p)
        # warm start: the rotation one substep earlier. At the first substep the zero start
        # (no rotation) makes polar_from take the SVD, so a forward depends only on the loaded
        # state and the control; one call site, since each inlined SVD costs seconds of compile
        R0 = ti.Matrix.zero(self.dtype, 3, 3)
        if warm:
            R0 = self.trajectory.R_prev[p]
        R, S, gap = self.model.stress.polar_from(Fe, R0)
        self.trajectory.R_prev[p] = R
        self.trajectory.R_q[t, p] = self.model.quaternion_of(R)
        self.trajectory.gap_t[t, p] = gap
        P = self.model.stress.stress_from_polar(Fe, R)
        return self._stress_scale(p) * (P @ Fe.transpose()) + self.model.mass[p] * self.trajectory.C[t, p]

    @ti.kernel
    def p2g_stress(self, t: ti.i32):
        """P2G's polar decomposition and A on packs of PACK particles (physmorph.mpm.stress_packs):
        R, its quaternion, its pair sum and A into R_prev, R_q, gap_t and affine; a particle the pack hands to the SVD
        gets gap_t -1, which p2g reads."""
        for pack in range(self.packs):
            self._stress_pack(t, pack)

    @ti.func
    def _stress_pack(self, t, pack):
        tr, f = self.trajectory, self.dtype
        # the pack's particles (the last pack repeats the last particle) and their inputs
        ps = [ti.min(pack * PACK + lane, self.n - 1) for lane in ti.static(range(PACK))]
        Fes = [self._fe(t, p) for p in ti.static(ps)]
        mCs = [self.model.mass[p] * tr.C[t, p] for p in ti.static(ps)]
        R0s = [ti.select(t > 0, tr.R_prev[p], ti.Matrix.zero(f, 3, 3)) for p in ti.static(ps)]
        Fe = [ti.Vector([m[i, j] for m in ti.static(Fes)]) for i, j in ti.static(ENTRIES)]
        R0 = [ti.Vector([m[i, j] for m in ti.static(R0s)]) for i, j in ti.static(ENTRIES)]
        mC = [ti.Vector([m[i, j] for m in ti.static(mCs)]) for i, j in ti.static(ENTRIES)]
        scale = ti.Vector([self._stress_scale(p) for p in ti.static(ps)])
        R, gap, needs_svd = self.pack.polar_from(Fe, R0, t == 0)
        Rr = pack_rows(R)
        A = self.pack.affine(Fe, Rr, scale, mC)
        q = pack_quaternion(Rr)
        for lane in ti.static(range(PACK)):
            p = pack * PACK + lane
            if p < self.n:
                tr.R_prev[p] = ti.Matrix([[Rr[3 * i + j][lane] for j in ti.static(range(3))] for i in ti.static(range(3))])
                tr.R_q[t, p] = ti.Vector([q[c][lane] for c in ti.static(range(4))])
                self.affine[p] = ti.Matrix([[A[3 * i + j, lane] for j in ti.static(range(3))] for i in ti.static(range(3))])
                tr.gap_t[t, p] = ti.select(needs_svd[lane], -1.0, gap[lane])

    @ti.func
    def _p2g_particle(self, t, p, lane):
        """Particle p's share of P2G, added into the grid's lane ``lane``."""
        xp = self.trajectory.x[t, p]
        base, fx, w, dw = self.model.stencil(xp)
        A = ti.Matrix.zero(self.dtype, 3, 3)
        if ti.static(self.packed):
            A = self.affine[p]
            if self.trajectory.gap_t[t, p] < 0.0:  # the pack left it to the SVD
                A = self._affine(t, p, False)
        else:
            A = self._affine(t, p, t > 0)
        mom = self.model.mass[p] * (1.0 - self.dtype(self.model.cfg.dt) * self.dtype(self.model.cfg.drag)) * self.trajectory.v[t, p]
        # x_I - x_p = (off - fx) dx: along a row of the stencil A (x_I - x_p) grows by dx A's
        # third column, so a node adds one vector rather than a 3x3 product
        Adx = self.dtype(self.model.dx) * A
        step_k = ti.Vector([Adx[0, 2], Adx[1, 2], Adx[2, 2]])
        row0 = mom - Adx @ fx
        mp = self.model.mass[p]
        if ti.static(self.unrolled):
            for i, j in ti.static(ti.ndrange(3, 3)):
                self._p2g_row(base, w, i, j, row0 + Adx @ ti.Vector([i, j, 0], self.dtype), step_k, mp, lane)
        else:
            for i, j in ti.ndrange(3, 3):
                self._p2g_row(base, w, i, j, row0 + Adx @ ti.Vector([i, j, 0], self.dtype), step_k, mp, lane)

    @ti.func
    def _p2g_row(self, base, w: ti.template(), i, j, u, step_k, mp, lane):
        """Row (i, j) of a particle's stencil added into lane ``lane``: node (i, j, k) gets
        w_Ip (m v + A (x_I - x_p)) (u at k = 0) and w_Ip m."""
        tr = self.trajectory
        wij = w[i, 0] * w[j, 1]
        for k in ti.static(range(3)):
            wt = wij * w[k, 2]
            tr.lanes.add_mass_momentum(tr.grid_mvm_lanes, tr.grid_mv, tr.grid_m, lane, base + ti.Vector([i, j, k]),
                                       wt * u, wt * mp)
            u += step_k

    @ti.kernel
    def grid_update(self, t: ti.i32):
        """Substep t's P2G grid (m_I, mv_I): the lanes summed into the working grid and kept for the
        backward; then v_I = mv_I / m_I (0 on empty nodes) and the boundary condition."""
        tr = self.trajectory
        for I in ti.grouped(tr.grid_m):
            m, mv = tr.lanes.collect_mass_momentum(tr.grid_mvm_lanes, tr.grid_mv, tr.grid_m, I)
            tr.grid_m[I], tr.grid_mv[I] = m, mv
            tr.grid_m_t[t, I], tr.grid_mv_t[t, I] = m, mv
            tr.grid_v[I] = self.node_velocity(I, m, mv)

    @ti.func
    def node_velocity(self, I, m, mv):
        """v_I = mv_I / m_I (0 on an empty node), then the boundary condition."""
        v = ti.Vector.zero(self.dtype, 3)
        if m > 0:
            v = self.model.boundary(I, mv / m)
        return v

    @ti.func
    def _g2p_row(self, base, w: ti.template(), i, j, nv, moment):
        """nv and moment with row (i, j) of the stencil added: sum w v_I and its columns sum w v_I off_a."""
        row, row_k = ti.Vector.zero(self.dtype, 3), ti.Vector.zero(self.dtype, 3)
        wij = w[i, 0] * w[j, 1]
        for k in ti.static(range(3)):
            c = (wij * w[k, 2]) * self.trajectory.grid_v[base + ti.Vector([i, j, k])]
            row += c
            row_k += ti.cast(k, self.dtype) * c
        return nv + row, moment + ti.Matrix.cols([ti.cast(i, self.dtype) * row, ti.cast(j, self.dtype) * row, row_k])

    @ti.kernel
    def g2p(self, t: ti.i32):
        """v' = sum w v_I, C' = 4/dx^2 sum w v_I dpos^T, x' = x + dt v', F' = (1-s)(I + dt C')F + sF."""
        for p in range(self.n):
            xp = self.trajectory.x[t, p]
            base, fx, w, dw = self.model.stencil(xp)
            # sum w v_I (x_I - x_p)^T = dx (sum w v_I off^T - v' fx^T): the nodes add vectors, the
            # outer products are taken once per particle
            nv = ti.Vector.zero(self.dtype, 3)
            moment = ti.Matrix.zero(self.dtype, 3, 3)  # columns: sum w v_I off_a
            if ti.static(self.unrolled):
                for i, j in ti.static(ti.ndrange(3, 3)):
                    nv, moment = self._g2p_row(base, w, i, j, nv, moment)
            else:
                for i, j in ti.ndrange(3, 3):
                    nv, moment = self._g2p_row(base, w, i, j, nv, moment)
            kq = 4.0 * self.dtype(self.model.inv_dx) * self.dtype(self.model.inv_dx)
            nC = (kq * self.dtype(self.model.dx)) * (moment - nv.outer_product(fx))
            Fo = self.trajectory.F[t, p]
            Fn = (ti.Matrix.identity(self.dtype, 3) + self.dtype(self.model.cfg.dt) * nC) @ Fo
            self.trajectory.v[t + 1, p] = nv
            self.trajectory.C[t + 1, p] = nC
            self.trajectory.x[t + 1, p] = ti.math.clamp(xp + self.dtype(self.model.cfg.dt) * nv, self.dtype(self.model.x_min), self.dtype(self.model.x_max))
            Fs = (1.0 - self.dtype(self.model.cfg.smoothing)) * Fn + self.dtype(self.model.cfg.smoothing) * Fo
            if ti.static(self.model.cfg.smoothing_mode == "isochoric"):
                Fs *= self.model.volume_scale(Fn, Fs)
            self.trajectory.F[t + 1, p] = Fs
