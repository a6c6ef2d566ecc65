"""The MLS-MPM transfers of one substep, each forward kernel beside its hand-written adjoint
(paper section 4, "Physics rollout"; equations in physmorph/mpm/solver.py's docstring).

    P2G:  mv_I = sum_p w_Ip [m (1 - dt d) v + A (x_I - x_p)],  m_I = sum_p w_Ip m
    grid: v_I = mv_I / m_I, outward component zeroed on the BOUNDARY_CELLS layer of each face
    G2P:  v' = sum_I w_Ip v_I,  C' = 4/dx^2 sum_I w_Ip v_I (x_I - x_p)^T,  x' = x + dt v',
          F' = (1 - s) (I + dt C') F + s F

The 27-node quadratic B-spline stencil is _stencil (per particle) and _node (per node); every
transfer loops over ti.ndrange(3, 3, 3). The forward stores the rotation of Fe (as a unit
quaternion) with its smallest pair sum and the P2G grid per substep; the adjoints restore them
instead of running P2G and its SVD again. A mixin of MPMSolver: the fields are SolverFields'.
"""

import numpy as np
import taichi as ti

from .state import ParticleState


class Transfers:
    """P2G, grid update and G2P with their adjoints, and the particle state's load and export."""

    @ti.func
    def _stencil(self, xp):
        """Quadratic B-spline: base node, fractional offset fx, weights w[axis][k], dw/dx."""
        xg = (xp - self.dtype(self._lo)) * self.dtype(self._inv_dx)
        base = ti.floor(xg - 0.5, ti.i32)
        fx = xg - ti.cast(base, self.dtype)
        # rows: stencil offset 0..2, columns: axis (dynamic loops over the 27 nodes keep the
        # kernels small to compile)
        w = ti.Matrix.rows([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2])
        dw = ti.Matrix.rows([(fx - 1.5) * self.dtype(self._inv_dx), -2.0 * (fx - 1.0) * self.dtype(self._inv_dx),
                             (fx - 0.5) * self.dtype(self._inv_dx)])
        return base, fx, w, dw

    @ti.func
    def _node(self, fx: ti.template(), w: ti.template(), i, j, k):
        """Node (i, j, k) of the stencil: offset from base, x_I - x_p and weight w_Ip.
        fx and w are taken by reference (ti.template()): passed by value they were copied for
        every node, which made P2G's backward ~50 % and G2P ~25 % slower (kernel profiler)."""
        off = ti.Vector([i, j, k])
        dpos = (ti.cast(off, self.dtype) - fx) * self.dtype(self._dx)
        return off, dpos, w[i, 0] * w[j, 1] * w[k, 2]

    @ti.func
    def _node_grad(self, w: ti.template(), dw: ti.template(), i, j, k):
        """grad_x w_Ip of node (i, j, k) (only the reverse kernels need it)."""
        return ti.Vector([dw[i, 0] * w[j, 1] * w[k, 2], w[i, 0] * dw[j, 1] * w[k, 2], w[i, 0] * w[j, 1] * dw[k, 2]])

    @ti.kernel
    def _clear_grid(self):
        for I in ti.grouped(self.grid_m):
            self.grid_mv[I] = ti.Vector.zero(self.dtype, 3)
            self.grid_m[I] = 0.0

    @ti.kernel
    def _clear_grid_adj(self, pair: ti.template()):
        for I in ti.grouped(self.grid_m):
            self.grid_v_adj[I] = ti.Vector.zero(self.dtype, 3)
            if ti.static(pair):
                self.grid_v_adj2[I] = ti.Vector.zero(self.dtype, 3)

    @ti.kernel
    def _p2g(self, t: ti.i32):
        """Fe = (F + dFc_t) Fp^-1, A = -dt V0 (4/dx^2) P(Fe) Fe^T + m C;
        mv_I += w_Ip (m (1 - dt d) v_p + A_p (x_I - x_p)),  m_I += w_Ip m_p.
        The rotation of Fe and its pair sum are kept per substep (R_q, gap_t), so the backward
        (_restore_p2g) needs no second SVD."""
        kq = 4.0 * self.dtype(self._inv_dx) * self.dtype(self._inv_dx)
        for p in range(self.n):
            xp = self.x[t, p]
            base, fx, w, dw = self._stencil(xp)
            Fe = (self.F[t, p] + self.ctrl[t, p]) @ self.Fp_inv[p]
            # warm start: the rotation one substep earlier. At the first substep the zero start
            # (no rotation) makes polar_from take the SVD, so a forward depends only on the loaded
            # state and the control; one call site, since each inlined SVD costs seconds of compile
            R0 = ti.Matrix.zero(self.dtype, 3, 3)
            if t > 0:
                R0 = self.R_prev[p]
            R, S, gap = self._stress_model.polar_from(Fe, R0)
            self.R_prev[p] = R
            self.R_q[t, p] = self._quaternion_of(R)
            self.gap_t[t, p] = gap
            P = self._stress_model.stress_from_polar(Fe, R)
            A = (-self.dtype(self.cfg.dt) * self.vol[p] * kq) * (P @ Fe.transpose()) + self.mass[p] * self.C[t, p]
            mom = self.mass[p] * (1.0 - self.dtype(self.cfg.dt) * self.dtype(self.cfg.drag)) * self.v[t, p]
            for i, j, k in ti.ndrange(3, 3, 3):
                off, dpos, wt = self._node(fx, w, i, j, k)
                self.grid_mv[base + off] += wt * (mom + A @ dpos)
                self.grid_m[base + off] += wt * self.mass[p]

    @ti.func
    def _quaternion_of(self, R):
        """The unit quaternion (w, x, y, z) of the rotation R (Shepperd's branches: the largest of
        4w^2, 4x^2, 4y^2, 4z^2 is taken from the diagonal, so no division by a small number)."""
        tr = R[0, 0] + R[1, 1] + R[2, 2]
        q = ti.Vector.zero(self.dtype, 4)
        if tr > 0.0:
            r = 2.0 * ti.sqrt(1.0 + tr)
            q = ti.Vector([0.25 * r, (R[2, 1] - R[1, 2]) / r, (R[0, 2] - R[2, 0]) / r, (R[1, 0] - R[0, 1]) / r])
        elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
            r = 2.0 * ti.sqrt(ti.max(1.0 + R[0, 0] - R[1, 1] - R[2, 2], 0.0))
            q = ti.Vector([(R[2, 1] - R[1, 2]) / r, 0.25 * r, (R[0, 1] + R[1, 0]) / r, (R[0, 2] + R[2, 0]) / r])
        elif R[1, 1] > R[2, 2]:
            r = 2.0 * ti.sqrt(ti.max(1.0 + R[1, 1] - R[0, 0] - R[2, 2], 0.0))
            q = ti.Vector([(R[0, 2] - R[2, 0]) / r, (R[0, 1] + R[1, 0]) / r, 0.25 * r, (R[1, 2] + R[2, 1]) / r])
        else:
            r = 2.0 * ti.sqrt(ti.max(1.0 + R[2, 2] - R[0, 0] - R[1, 1], 0.0))
            q = ti.Vector([(R[1, 0] - R[0, 1]) / r, (R[0, 2] + R[2, 0]) / r, (R[1, 2] + R[2, 1]) / r, 0.25 * r])
        return q

    @ti.func
    def _rotation_of(self, q):
        """The rotation of the quaternion q (w, x, y, z), normalised first."""
        u = q / q.norm()
        w, x, y, z = u[0], u[1], u[2], u[3]
        return ti.Matrix([[1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)],
                          [2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w)],
                          [2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)]], self.dtype)

    @ti.kernel
    def _store_grid(self, t: ti.i32):
        """Keep substep t's P2G grid (m_I, mv_I) for the backward."""
        for I in ti.grouped(self.grid_m):
            self.grid_m_t[t, I] = self.grid_m[I]
            self.grid_mv_t[t, I] = self.grid_mv[I]

    @ti.kernel
    def _restore_p2g(self, t: ti.i32):
        """The backward's scratch (A, Fe, its polar factors) and substep t's grid, from the forward's stored polar factors and grid:
        Fe = (F + dFc_t) Fp^-1, R and gap as stored, S = sym(R^T Fe), A as in _p2g."""
        kq = 4.0 * self.dtype(self._inv_dx) * self.dtype(self._inv_dx)
        for I in ti.grouped(self.grid_m):
            self.grid_m[I] = self.grid_m_t[t, I]
            self.grid_mv[I] = self.grid_mv_t[t, I]
        for p in range(self.n):
            Fe = (self.F[t, p] + self.ctrl[t, p]) @ self.Fp_inv[p]
            R = self._rotation_of(self.R_q[t, p])
            S0 = R.transpose() @ Fe
            P = self._stress_model.stress_from_polar(Fe, R)
            A = (-self.dtype(self.cfg.dt) * self.vol[p] * kq) * (P @ Fe.transpose()) + self.mass[p] * self.C[t, p]
            self.A_s[p] = A
            self.Fe_s[p] = Fe
            self.R_s[p] = R
            self.S_s[p] = 0.5 * (S0 + S0.transpose())
            self.gap_s[p] = self.gap_t[t, p]

    @ti.kernel
    def _p2g_backward(self, t: ti.i32, pair: ti.template()):
        """Reverse of _p2g: grid adjoints -> adjoints of (x, v, C, F) of state t and of dFc_t (pair:
        also the second set's, sharing the stencil, A and the node loop)."""
        damp = 1.0 - self.dtype(self.cfg.dt) * self.dtype(self.cfg.drag)
        for p in range(self.n):
            xp = self.x[t, p]
            base, fx, w, dw = self._stencil(xp)
            A = self.A_s[p]
            mp = self.mass[p]
            mom = mp * damp * self.v[t, p]
            vbar = ti.Vector.zero(self.dtype, 3)
            Abar = ti.Matrix.zero(self.dtype, 3, 3)
            xbar = ti.Vector.zero(self.dtype, 3)
            vbar2, Abar2, xbar2 = vbar, Abar, xbar
            for i, j, k in ti.ndrange(3, 3, 3):
                off, dpos, wt = self._node(fx, w, i, j, k)
                gw = self._node_grad(w, dw, i, j, k)
                mv = mom + A @ dpos
                mvb = self.grid_mv_adj[base + off]
                vbar += wt * mvb
                Abar += wt * mvb.outer_product(dpos)
                xbar += gw * (mvb.dot(mv) + self.grid_m_adj[base + off] * mp) - wt * (A.transpose() @ mvb)
                if ti.static(pair):
                    mvb2 = self.grid_mv_adj2[base + off]
                    vbar2 += wt * mvb2
                    Abar2 += wt * mvb2.outer_product(dpos)
                    xbar2 += gw * (mvb2.dot(mv) + self.grid_m_adj2[base + off] * mp) - wt * (A.transpose() @ mvb2)
            # one call site of the stress's differential for both sets (each inlined copy costs
            # seconds of compilation): a loop over the sets
            for which in range(2 if ti.static(pair) else 1):
                vb, Ab, xb = vbar, Abar, xbar
                if ti.static(pair):
                    if which == 1:
                        vb, Ab, xb = vbar2, Abar2, xbar2
                Fhat_bar = self._p2g_F_adjoint(p, Ab)
                if which == 0:
                    self._add_particle_adjoints(p, t, xb, mp * damp * vb, mp * Ab, Fhat_bar, self.x_adj,
                                                self.v_adj, self.C_adj, self.F_adj, self.ctrl_grad)
                if ti.static(pair):
                    if which == 1:
                        self._add_particle_adjoints(p, t, xb, mp * damp * vb, mp * Ab, Fhat_bar, self.x_adj2,
                                                    self.v_adj2, self.C_adj2, self.F_adj2, self.ctrl_base)

    @ti.func
    def _p2g_F_adjoint(self, p, Abar):
        """The particle part of _p2g's reverse for one adjoint set: A_bar -> P_bar = tau_bar Fe ->
        Fe_bar (the stress's self-adjoint differential) -> the adjoint of F + dFc."""
        kq = 4.0 * self.dtype(self._inv_dx) * self.dtype(self._inv_dx)
        Fe = self.Fe_s[p]
        tau_bar = (-self.dtype(self.cfg.dt) * self.vol[p] * kq) * Abar
        P, dP = self._stress_model.stress_and_diff_polar(Fe, self.R_s[p], self.S_s[p], self.gap_s[p],
                                                         tau_bar @ Fe)  # P_bar = tau_bar Fe
        Fe_bar = tau_bar.transpose() @ P + dP
        return Fe_bar @ self.Fp_inv[p].transpose()

    @ti.func
    def _add_particle_adjoints(self, p, slot, xbar, vbar, Cbar, Fbar, xa: ti.template(), va: ti.template(),
                               Ca: ti.template(), Fa: ti.template(), grad: ti.template()):
        xa[p] += xbar
        va[p] += vbar
        Ca[p] += Cbar
        Fa[p] += Fbar
        grad[slot, p] += Fbar

    @ti.func
    def _boundary(self, I, v):
        """Zero the outward velocity component on the BOUNDARY_CELLS layer of every face."""
        out = v
        for a in ti.static(range(3)):
            if I[a] < self._bound and v[a] < 0:
                out[a] = 0.0
            if I[a] >= self._res - self._bound and v[a] > 0:
                out[a] = 0.0
        return out

    @ti.kernel
    def _grid_update(self):
        """v_I = mv_I / m_I (0 on empty nodes), then the boundary condition."""
        for I in ti.grouped(self.grid_m):
            m = self.grid_m[I]
            v = ti.Vector.zero(self.dtype, 3)
            if m > 0:
                v = self._boundary(I, self.grid_mv[I] / m)
            self.grid_v[I] = v

    @ti.kernel
    def _grid_backward(self, pair: ti.template()):
        """Reverse of _grid_update: v_bar -> (mv_bar, m_bar) through the mask and v = mv / m."""
        for I in ti.grouped(self.grid_m):
            m = self.grid_m[I]
            vfree = ti.Vector.zero(self.dtype, 3)
            vc = vfree
            if m > 0:
                vfree = self.grid_mv[I] / m
                vc = self._boundary(I, vfree)
            self._grid_adjoint_node(I, m, vfree, vc, self.grid_v_adj, self.grid_mv_adj, self.grid_m_adj)
            if ti.static(pair):
                self._grid_adjoint_node(I, m, vfree, vc, self.grid_v_adj2, self.grid_mv_adj2, self.grid_m_adj2)

    @ti.func
    def _grid_adjoint_node(self, I, m, vfree, vc, va: ti.template(), mva: ti.template(), ma: ti.template()):
        """One adjoint set at node I: the boundary's zeroed components pass nothing back."""
        mvb = ti.Vector.zero(self.dtype, 3)
        mb = ti.cast(0.0, self.dtype)
        if m > 0:
            vb = va[I]
            for a in ti.static(range(3)):
                if vc[a] == 0.0 and vfree[a] != 0.0:
                    vb[a] = 0.0
            mvb = vb / m
            mb = -vb.dot(vfree) / m
        mva[I] = mvb
        ma[I] = mb

    @ti.kernel
    def _g2p(self, t: ti.i32):
        """v' = sum w v_I, C' = 4/dx^2 sum w v_I dpos^T, x' = x + dt v', F' = (1-s)(I + dt C')F + sF."""
        for p in range(self.n):
            xp = self.x[t, p]
            base, fx, w, dw = self._stencil(xp)
            nv = ti.Vector.zero(self.dtype, 3)
            nC = ti.Matrix.zero(self.dtype, 3, 3)
            for i, j, k in ti.ndrange(3, 3, 3):
                off, dpos, wt = self._node(fx, w, i, j, k)
                gv = self.grid_v[base + off]
                nv += wt * gv
                nC += (4.0 * self.dtype(self._inv_dx) * self.dtype(self._inv_dx) * wt) * gv.outer_product(dpos)
            Fo = self.F[t, p]
            Fn = (ti.Matrix.identity(self.dtype, 3) + self.dtype(self.cfg.dt) * nC) @ Fo
            self.v[t + 1, p] = nv
            self.C[t + 1, p] = nC
            self.x[t + 1, p] = ti.math.clamp(xp + self.dtype(self.cfg.dt) * nv, self.dtype(self._x_min), self.dtype(self._x_max))
            Fs = (1.0 - self.dtype(self.cfg.smoothing)) * Fn + self.dtype(self.cfg.smoothing) * Fo
            if ti.static(self.cfg.smoothing_mode == "isochoric"):
                Fs *= self._volume_scale(Fn, Fs)
            self.F[t + 1, p] = Fs

    @ti.func
    def _volume_target(self, Fn):
        """det F' under isochoric smoothing: max(det F_new, J_min), J_min = min_volume_ratio."""
        J = Fn.determinant()
        if ti.static(self.cfg.min_volume_ratio > 0):
            J = ti.max(J, self.dtype(self.cfg.min_volume_ratio))
        return J

    @ti.func
    def _volume_scale(self, Fn, Fs):
        """r = (max(det F_new, J_min) / det F_s)^(1/3) (smoothing_mode "isochoric"); 1 where the
        ratio is not positive (an inverted F, which the blend cannot rescale)."""
        q = self._volume_target(Fn) / Fs.determinant()
        r = ti.cast(1.0, self.dtype)
        if q > 0:
            r = ti.pow(q, self.dtype(1.0 / 3.0))
        return r

    @ti.kernel
    def _g2p_backward(self, t: ti.i32, pair: ti.template()):
        """Reverse of _g2p: adjoints of state t+1 -> grid_v_adj and the (x, F) adjoints of state t
        (pair: also the second set's, sharing the stencil and the node loop's grid loads)."""
        kq = 4.0 * self.dtype(self._inv_dx) * self.dtype(self._inv_dx)
        for p in range(self.n):
            xp = self.x[t, p]
            base, fx, w, dw = self._stencil(xp)
            xbar, vbar, Cbar = ti.Vector.zero(self.dtype, 3), ti.Vector.zero(self.dtype, 3), ti.Matrix.zero(self.dtype, 3, 3)
            xbar2, vbar2, Cbar2 = xbar, vbar, Cbar  # set in the loop below
            # one call site of the particle part for both sets (a loop over the sets)
            for which in range(2 if ti.static(pair) else 1):
                xa, va, Ca, Fa = self.x_adj[p], self.v_adj[p], self.C_adj[p], self.F_adj[p]
                if ti.static(pair):
                    if which == 1:
                        xa, va, Ca, Fa = self.x_adj2[p], self.v_adj2[p], self.C_adj2[p], self.F_adj2[p]
                xb, vb, Cb, Fb = self._g2p_particle_adjoint(t, p, xa, va, Ca, Fa)
                if which == 0:
                    xbar, vbar, Cbar = xb, vb, Cb
                    self._set_F_adjoint(p, Fb, self.v_adj, self.C_adj, self.F_adj)
                if ti.static(pair):
                    if which == 1:
                        xbar2, vbar2, Cbar2 = xb, vb, Cb
                        self._set_F_adjoint(p, Fb, self.v_adj2, self.C_adj2, self.F_adj2)
            for i, j, k in ti.ndrange(3, 3, 3):
                off, dpos, wt = self._node(fx, w, i, j, k)
                gw = self._node_grad(w, dw, i, j, k)
                gv = self.grid_v[base + off]
                Cd = Cbar @ dpos
                self.grid_v_adj[base + off] += wt * (vbar + kq * Cd)
                xbar += gw * (vbar.dot(gv) + kq * gv.dot(Cd)) - (wt * kq) * (Cbar.transpose() @ gv)
                if ti.static(pair):
                    Cd2 = Cbar2 @ dpos
                    self.grid_v_adj2[base + off] += wt * (vbar2 + kq * Cd2)
                    xbar2 += gw * (vbar2.dot(gv) + kq * gv.dot(Cd2)) - (wt * kq) * (Cbar2.transpose() @ gv)
            self.x_adj[p] = xbar
            if ti.static(pair):
                self.x_adj2[p] = xbar2

    @ti.func
    def _g2p_particle_adjoint(self, t, p, xbar_n, vbar_n, Cbar_n, Fbar_n):
        """The particle part of _g2p's reverse for one adjoint set: the adjoints of x, v, C, F of
        state t+1 -> F's of state t and the (x_bar, v_bar, C_bar) that the node loop scatters."""
        s = self.dtype(self.cfg.smoothing)
        dt = self.dtype(self.cfg.dt)
        xn = self.x[t + 1, p]
        for a in ti.static(range(3)):  # the clamp passes no gradient where it is active
            if xn[a] <= self.dtype(self._x_min) or xn[a] >= self.dtype(self._x_max):
                xbar_n[a] = 0.0
        Fh = self.F[t, p]
        Cn = self.C[t + 1, p]
        Fbar_new = (1.0 - s) * Fbar_n
        Fbar = s * Fbar_n
        if ti.static(self.cfg.smoothing_mode == "isochoric"):
            # F' = r Fs, r = (det Fn / det Fs)^(1/3): Fs_bar = r F'_bar - (r r_bar / 3) Fs^-T,
            # Fn_bar += (r r_bar / 3) Fn^-T with r_bar = <F'_bar, Fs> (0 where the floor
            # J_min holds det F' instead of det Fn)
            Fn = (ti.Matrix.identity(self.dtype, 3) + dt * Cn) @ Fh
            Fs = (1.0 - s) * Fn + s * self.F[t, p]
            r = self._volume_scale(Fn, Fs)
            Fs_bar = r * Fbar_n
            Fbar_new = ti.Matrix.zero(self.dtype, 3, 3)
            Jt = self._volume_target(Fn)
            if (Jt / Fs.determinant()) > 0:
                k3 = r * (Fbar_n * Fs).sum() / 3.0
                Fs_bar -= k3 * Fs.inverse().transpose()
                if Jt == Fn.determinant():  # det F' follows det Fn (not held at the floor)
                    Fbar_new = k3 * Fn.inverse().transpose()
            Fbar_new += (1.0 - s) * Fs_bar
            Fbar = s * Fs_bar
        Fh_bar = (ti.Matrix.identity(self.dtype, 3) + dt * Cn).transpose() @ Fbar_new
        Fbar += Fh_bar
        Cbar = Cbar_n + dt * Fbar_new @ Fh.transpose()
        vbar = vbar_n + dt * xbar_n
        return xbar_n, vbar, Cbar, Fbar

    @ti.func
    def _set_F_adjoint(self, p, Fbar, va: ti.template(), Ca: ti.template(), Fa: ti.template()):
        """One set's adjoints of state t after _g2p's particle part: F's written, v's and C's
        consumed (zeroed)."""
        Fa[p] = Fbar
        va[p] = ti.Vector.zero(self.dtype, 3)
        Ca[p] = ti.Matrix.zero(self.dtype, 3, 3)

    @ti.kernel
    def _load_initial(self, x: ti.types.ndarray(), v: ti.types.ndarray(), F: ti.types.ndarray(),
                      C: ti.types.ndarray()):
        for p in range(self.n):
            for a in ti.static(range(3)):
                self.x[0, p][a] = x[p, a]
                self.v[0, p][a] = v[p, a]
                for b in ti.static(range(3)):
                    self.F[0, p][a, b] = F[p, a, b]
                    self.C[0, p][a, b] = C[p, a, b]

    @ti.kernel
    def _export(self, t: ti.i32, x: ti.types.ndarray(), v: ti.types.ndarray(), F: ti.types.ndarray(),
                C: ti.types.ndarray()):
        for p in range(self.n):
            for a in ti.static(range(3)):
                x[p, a] = self.x[t, p][a]
                v[p, a] = self.v[t, p][a]
                for b in ti.static(range(3)):
                    F[p, a, b] = self.F[t, p][a, b]
                    C[p, a, b] = self.C[t, p][a, b]

    def state_at(self, t: int) -> ParticleState:
        """Stored particle state at substep t (0..T) of the last forward, float64."""
        T = self.cfg.substeps
        if not 0 <= t <= T:
            raise IndexError(f"substep t must be in [0, {T}], got {t}")
        self._require_loaded()
        x, v, F, C = self._export_raw(t)
        return ParticleState(x=x.astype(np.float64), v=v.astype(np.float64), F=F.astype(np.float64),
                             C=C.astype(np.float64), Fp=self._Fp.copy(),
                             mass=self.mass.to_numpy().astype(np.float64),
                             volume=self.vol.to_numpy().astype(np.float64))

    def initial_state_gradients(self) -> dict:
        """Adjoints of the initial x, v, C, F after backward(): {"x": [N,3], "v", "C", "F"}."""
        return {"x": self.x_adj.to_numpy().astype(np.float64),
                "v": self.v_adj.to_numpy().astype(np.float64),
                "C": self.C_adj.to_numpy().astype(np.float64),
                "F": self.F_adj.to_numpy().astype(np.float64)}

    def _export_raw(self, t: int):
        n, d = self.n, self.np_dtype
        x, v = np.empty((n, 3), d), np.empty((n, 3), d)
        F, C = np.empty((n, 3, 3), d), np.empty((n, 3, 3), d)
        self._export(t, x, v, F, C)
        return x, v, F, C
