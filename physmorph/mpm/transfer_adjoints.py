"""The adjoints of one substep's transfers, each the hand-written reverse of its forward kernel in
physmorph.mpm.transfers (paper section 4, "Physics rollout"): steps acting on the model, the
stored state, the control's gradient and the adjoint (physmorph.mpm.adjoint).

The substep's forward records (the rotation of Fe as a unit quaternion with its smallest pair sum,
and the P2G grid) are restored instead of running P2G and its SVD again; with ``pair`` each
reverse kernel carries a second adjoint set, sharing the stencil, A and the node loop's loads.
"""

import taichi as ti

from physmorph.base import taichi_runtime  # noqa: F401  (Taichi's fast class test, before the kernels below)
from .adjoint import Adjoint
from .control import ControlField
from .g2p_adjoint import G2PAdjoint
from .model import MPMModel
from .trajectory import Trajectory


@ti.func
def grid_node_adjoint(m, vfree, vc, v_bar):
    """The reverse of a node's grid update, v = boundary(mv / m): (mv_bar, m_bar) from the
    velocity's adjoint v_bar (vfree = mv / m, vc after the boundary, whose zeroed components
    pass nothing back)."""
    mvb = ti.zero(v_bar)
    mb = ti.zero(m)
    if m > 0:
        vb = v_bar
        for a in ti.static(range(3)):
            if vc[a] == 0.0 and vfree[a] != 0.0:
                vb[a] = 0.0
        mvb = vb / m
        mb = -vb.dot(vfree) / m
    return mvb, mb


@ti.data_oriented
class TransferAdjoints:
    """Reverse of G2P, the grid update and P2G of substep t: adjoints of s_(t+1) -> adjoints of s_t
    and the control gradient of slot t."""

    def __init__(self, model: MPMModel, trajectory: Trajectory, control: ControlField, adjoint: Adjoint,
                 unrolled: bool = False):
        self.model, self.trajectory, self.control, self.adjoint = model, trajectory, control, adjoint
        self.n, self.dtype = model.n, model.dtype
        # the reverse of G2P's node loop unrolled over the stencil's rows (the transfers' choice:
        # physmorph.mpm.transfers' docstring), a compile-time constant
        self.unrolled = bool(unrolled)
        self.g2p = G2PAdjoint(model, trajectory, adjoint, self.unrolled)

    @ti.kernel
    def clear_grid_adjoint(self, pair: ti.template()):
        for I in ti.grouped(self.trajectory.grid_m):
            self.adjoint.grid_v_adj[I] = ti.Vector.zero(self.dtype, 3)
            if ti.static(pair):
                self.adjoint.grid_v_adj2[I] = ti.Vector.zero(self.dtype, 3)

    @ti.kernel
    def restore_grid(self, t: ti.i32, transfers: ti.template()):
        """Substep t's P2G grid (m_I, mv_I) as the forward stored it, and its velocities."""
        tr = self.trajectory
        for I in ti.grouped(tr.grid_m):
            m, mv = tr.grid_m_t[t, I], tr.grid_mv_t[t, I]
            tr.grid_m[I], tr.grid_mv[I] = m, mv
            tr.grid_v[I] = transfers.node_velocity(I, m, mv)

    @ti.func
    def _restore_particle(self, t, p):
        """Particle p's P2G quantities at substep t from the forward's records (no SVD): Fe = (F +
        dFc_t) Fp^-1, R and the pair sum as stored, S = sym(R^T Fe), A as in Transfers.p2g."""
        kq = 4.0 * self.dtype(self.model.inv_dx) * self.dtype(self.model.inv_dx)
        Fe = (self.trajectory.F[t, p] + self.control.ctrl[t, p]) @ self.model.Fp_inv[p]
        R = self.model.rotation_of(self.trajectory.R_q[t, p])
        S0 = R.transpose() @ Fe
        P = self.model.stress.stress_from_polar(Fe, R)
        A = (-self.dtype(self.model.cfg.dt) * self.model.vol[p] * kq) * (P @ Fe.transpose()) + self.model.mass[p] * self.trajectory.C[t, p]
        return Fe, R, 0.5 * (S0 + S0.transpose()), self.trajectory.gap_t[t, p], A

    @ti.kernel
    def p2g_backward(self, t: ti.i32, pair: ti.template()):
        """Reverse of Transfers.p2g: grid adjoints -> adjoints of (x, v, C, F) of state t and of dFc_t (pair:
        also the second set's, sharing the stencil, A and the node loop)."""
        damp = 1.0 - self.dtype(self.model.cfg.dt) * self.dtype(self.model.cfg.drag)
        for p in range(self.n):
            xp = self.trajectory.x[t, p]
            base, fx, w, dw = self.model.stencil(xp)
            Fe, R, S, gap, A = self._restore_particle(t, p)
            mp = self.model.mass[p]
            mom = mp * damp * self.trajectory.v[t, p]
            vbar, Abar, xbar = self._p2g_node_adjoints(base, fx, w, dw, mom, A, mp, self.adjoint.grid_mv_adj, self.adjoint.grid_m_adj)
            vbar2, Abar2, xbar2 = vbar, Abar, xbar
            if ti.static(pair):
                vbar2, Abar2, xbar2 = self._p2g_node_adjoints(base, fx, w, dw, mom, A, mp, self.adjoint.grid_mv_adj2,
                                                              self.adjoint.grid_m_adj2)
            # one call site of the stress's differential for both sets (each inlined copy costs
            # seconds of compilation): a loop over the sets
            for which in range(2 if ti.static(pair) else 1):
                vb, Ab, xb = vbar, Abar, xbar
                if ti.static(pair):
                    if which == 1:
                        vb, Ab, xb = vbar2, Abar2, xbar2
                Fhat_bar = self._p2g_F_adjoint(p, Ab, Fe, R, S, gap)
                if which == 0:
                    self._add_particle_adjoints(p, t, xb, mp * damp * vb, mp * Ab, Fhat_bar, self.adjoint.x_adj,
                                                self.adjoint.v_adj, self.adjoint.C_adj, self.adjoint.F_adj, self.control.ctrl_grad)
                if ti.static(pair):
                    if which == 1:
                        self._add_particle_adjoints(p, t, xb, mp * damp * vb, mp * Ab, Fhat_bar, self.adjoint.x_adj2,
                                                    self.adjoint.v_adj2, self.adjoint.C_adj2, self.adjoint.F_adj2, self.control.ctrl_base)

    @ti.func
    def _p2g_node_adjoints(self, base, fx: ti.template(), w: ti.template(), dw: ti.template(), mom, A, mp,
                           mv_adj: ti.template(), m_adj: ti.template()):
        """The node loop of p2g's reverse for one adjoint set: v_bar = sum w mv_bar_I, A_bar = sum
        w mv_bar_I (x_I - x_p)^T and x_bar = sum grad w (mv_bar_I . mv_I + m_bar_I m) - A^T v_bar.
        As in P2G, mv_I = m v + A (x_I - x_p) grows along a row of the stencil by a column of
        dx A, and A_bar = dx (sum w mv_bar_I off^T - v_bar fx^T): the nodes add vectors only."""
        Adx = self.dtype(self.model.dx) * A
        step_k = ti.Vector([Adx[0, 2], Adx[1, 2], Adx[2, 2]])  # mv's change along a row
        vbar = ti.Vector.zero(self.dtype, 3)
        xbar = ti.Vector.zero(self.dtype, 3)
        moment = ti.Matrix.zero(self.dtype, 3, 3)  # columns: sum w mv_bar_I off_a
        for i, j in ti.ndrange(3, 3):
            wij, dwi, dwj = w[i, 0] * w[j, 1], dw[i, 0] * w[j, 1], w[i, 0] * dw[j, 1]
            mv = mom + Adx @ (ti.Vector([i, j, 0], self.dtype) - fx)
            row, row_k = ti.Vector.zero(self.dtype, 3), ti.Vector.zero(self.dtype, 3)
            for k in range(3):
                node = base + ti.Vector([i, j, k])
                mvb = mv_adj[node]
                c = (wij * w[k, 2]) * mvb
                row += c
                row_k += ti.cast(k, self.dtype) * c
                gw = ti.Vector([dwi * w[k, 2], dwj * w[k, 2], wij * dw[k, 2]])
                xbar += (mvb.dot(mv) + m_adj[node] * mp) * gw
                mv += step_k
            vbar += row
            moment += ti.Matrix.cols([ti.cast(i, self.dtype) * row, ti.cast(j, self.dtype) * row, row_k])
        Abar = self.dtype(self.model.dx) * (moment - vbar.outer_product(fx))
        return vbar, Abar, xbar - A.transpose() @ vbar

    @ti.func
    def _p2g_F_adjoint(self, p, Abar, Fe, R, S, gap):
        """The particle part of p2g's reverse for one adjoint set: A_bar -> P_bar = tau_bar Fe ->
        Fe_bar (the stress's self-adjoint differential) -> the adjoint of F + dFc."""
        kq = 4.0 * self.dtype(self.model.inv_dx) * self.dtype(self.model.inv_dx)
        tau_bar = (-self.dtype(self.model.cfg.dt) * self.model.vol[p] * kq) * Abar
        P, dP = self.model.stress.stress_and_diff_polar(Fe, R, S, gap,
                                                         tau_bar @ Fe)  # P_bar = tau_bar Fe
        Fe_bar = tau_bar.transpose() @ P + dP
        return Fe_bar @ self.model.Fp_inv[p].transpose()

    @ti.func
    def _add_particle_adjoints(self, p, slot, xbar, vbar, Cbar, Fbar, xa: ti.template(), va: ti.template(),
                               Ca: ti.template(), Fa: ti.template(), grad: ti.template()):
        xa[p] += xbar
        va[p] += vbar
        Ca[p] += Cbar
        Fa[p] += Fbar
        grad[slot, p] += Fbar

    @ti.kernel
    def grid_backward(self, pair: ti.template()):
        """Reverse of Transfers.grid_update: v_bar -> (mv_bar, m_bar) through the mask and v = mv / m."""
        for I in ti.grouped(self.trajectory.grid_m):
            m = self.trajectory.grid_m[I]
            vfree = ti.Vector.zero(self.dtype, 3)
            vc = vfree
            if m > 0:
                vfree = self.trajectory.grid_mv[I] / m
                vc = self.model.boundary(I, vfree)
            a = self.adjoint
            vb = self.model.lanes.collect(a.grid_v_adj_lanes, a.grid_v_adj, I)
            a.grid_mv_adj[I], a.grid_m_adj[I] = grid_node_adjoint(m, vfree, vc, vb)
            if ti.static(pair):
                vb2 = self.model.lanes.collect(a.grid_v_adj2_lanes, a.grid_v_adj2, I)
                a.grid_mv_adj2[I], a.grid_m_adj2[I] = grid_node_adjoint(m, vfree, vc, vb2)

    def g2p_backward(self, t: int, pair: bool) -> None:
        """Reverse of Transfers.g2p (physmorph.mpm.g2p_adjoint): adjoints of state t+1 ->
        grid_v_adj and the (x, F) adjoints of state t (pair: also the second set's)."""
        self.g2p.backward(t, pair)
