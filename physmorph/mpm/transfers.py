"""The MLS-MPM transfers of one substep, forward (paper section 4, "Physics rollout"; equations in
physmorph/mpm/solver.py's docstring): steps acting on the model, the state and the control.

    P2G:  mv_I = sum_p w_Ip [m (1 - dt d) v + A (x_I - x_p)],  m_I = sum_p w_Ip m
    grid: v_I = mv_I / m_I, outward component zeroed on the BOUNDARY_CELLS layer of each face
    G2P:  v' = sum_I w_Ip v_I,  C' = 4/dx^2 sum_I w_Ip v_I (x_I - x_p)^T,  x' = x + dt v',
          F' = (1 - s) (I + dt C') F + s F

The 27-node quadratic B-spline stencil is the model's (stencil per particle, node per node); every
transfer loops over ti.ndrange(3, 3, 3). The forward stores the rotation of Fe (as a unit
quaternion) with its smallest pair sum and the P2G grid per substep; the adjoints
(physmorph.mpm.transfer_adjoints) restore them instead of running P2G and its SVD again.
"""

import taichi as ti

from .control import ControlField
from .model import MPMModel
from .trajectory import Trajectory


@ti.data_oriented
class Transfers:
    """P2G, the grid update and G2P of substep t: s_t and dFc_t -> s_(t+1)."""

    def __init__(self, model: MPMModel, trajectory: Trajectory, control: ControlField):
        self.model, self.trajectory, self.control = model, trajectory, control
        self.n, self.dtype = model.n, model.dtype

    @ti.kernel
    def clear_grid(self):
        for I in ti.grouped(self.trajectory.grid_m):
            self.trajectory.grid_mv[I] = ti.Vector.zero(self.dtype, 3)
            self.trajectory.grid_m[I] = 0.0

    @ti.kernel
    def p2g(self, t: ti.i32):
        """Fe = (F + dFc_t) Fp^-1, A = -dt V0 (4/dx^2) P(Fe) Fe^T + m C;
        mv_I += w_Ip (m (1 - dt d) v_p + A_p (x_I - x_p)),  m_I += w_Ip m_p.
        The rotation of Fe and its pair sum are kept per substep (R_q, gap_t), so the backward
        (TransferAdjoints.restore_p2g) needs no second SVD."""
        kq = 4.0 * self.dtype(self.model.inv_dx) * self.dtype(self.model.inv_dx)
        for p in range(self.n):
            xp = self.trajectory.x[t, p]
            base, fx, w, dw = self.model.stencil(xp)
            Fe = (self.trajectory.F[t, p] + self.control.ctrl[t, p]) @ self.model.Fp_inv[p]
            # warm start: the rotation one substep earlier. At the first substep the zero start
            # (no rotation) makes polar_from take the SVD, so a forward depends only on the loaded
            # state and the control; one call site, since each inlined SVD costs seconds of compile
            R0 = ti.Matrix.zero(self.dtype, 3, 3)
            if t > 0:
                R0 = self.trajectory.R_prev[p]
            R, S, gap = self.model.stress.polar_from(Fe, R0)
            self.trajectory.R_prev[p] = R
            self.trajectory.R_q[t, p] = self.model.quaternion_of(R)
            self.trajectory.gap_t[t, p] = gap
            P = self.model.stress.stress_from_polar(Fe, R)
            A = (-self.dtype(self.model.cfg.dt) * self.model.vol[p] * kq) * (P @ Fe.transpose()) + self.model.mass[p] * self.trajectory.C[t, p]
            mom = self.model.mass[p] * (1.0 - self.dtype(self.model.cfg.dt) * self.dtype(self.model.cfg.drag)) * self.trajectory.v[t, p]
            for i, j, k in ti.ndrange(3, 3, 3):
                off, dpos, wt = self.model.node(fx, w, i, j, k)
                self.trajectory.grid_mv[base + off] += wt * (mom + A @ dpos)
                self.trajectory.grid_m[base + off] += wt * self.model.mass[p]

    @ti.kernel
    def store_grid(self, t: ti.i32):
        """Keep substep t's P2G grid (m_I, mv_I) for the backward."""
        for I in ti.grouped(self.trajectory.grid_m):
            self.trajectory.grid_m_t[t, I] = self.trajectory.grid_m[I]
            self.trajectory.grid_mv_t[t, I] = self.trajectory.grid_mv[I]

    @ti.kernel
    def grid_update(self):
        """v_I = mv_I / m_I (0 on empty nodes), then the boundary condition."""
        for I in ti.grouped(self.trajectory.grid_m):
            m = self.trajectory.grid_m[I]
            v = ti.Vector.zero(self.dtype, 3)
            if m > 0:
                v = self.model.boundary(I, self.trajectory.grid_mv[I] / m)
            self.trajectory.grid_v[I] = v

    @ti.kernel
    def g2p(self, t: ti.i32):
        """v' = sum w v_I, C' = 4/dx^2 sum w v_I dpos^T, x' = x + dt v', F' = (1-s)(I + dt C')F + sF."""
        for p in range(self.n):
            xp = self.trajectory.x[t, p]
            base, fx, w, dw = self.model.stencil(xp)
            nv = ti.Vector.zero(self.dtype, 3)
            nC = ti.Matrix.zero(self.dtype, 3, 3)
            for i, j, k in ti.ndrange(3, 3, 3):
                off, dpos, wt = self.model.node(fx, w, i, j, k)
                gv = self.trajectory.grid_v[base + off]
                nv += wt * gv
                nC += (4.0 * self.dtype(self.model.inv_dx) * self.dtype(self.model.inv_dx) * wt) * gv.outer_product(dpos)
            Fo = self.trajectory.F[t, p]
            Fn = (ti.Matrix.identity(self.dtype, 3) + self.dtype(self.model.cfg.dt) * nC) @ Fo
            self.trajectory.v[t + 1, p] = nv
            self.trajectory.C[t + 1, p] = nC
            self.trajectory.x[t + 1, p] = ti.math.clamp(xp + self.dtype(self.model.cfg.dt) * nv, self.dtype(self.model.x_min), self.dtype(self.model.x_max))
            Fs = (1.0 - self.dtype(self.model.cfg.smoothing)) * Fn + self.dtype(self.model.cfg.smoothing) * Fo
            if ti.static(self.model.cfg.smoothing_mode == "isochoric"):
                Fs *= self.model.volume_scale(Fn, Fs)
            self.trajectory.F[t + 1, p] = Fs
