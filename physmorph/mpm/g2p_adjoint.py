"""The reverse of G2P (physmorph.mpm.transfers' g2p; paper section 4, "Physics rollout"), in two
passes over the particles. The first takes each particle's adjoints of state t+1 back through its
own update (the clamp of x, the F blend and its volume scale, x' = x + dt v'): F's adjoint of state
t, and the (x_bar, v_bar, C_bar) the second pass scatters, left in the adjoint's x, v and C fields.
The second walks the stencil: node I receives w q_I, q_I = v_bar + 4/dx^2 C_bar (x_I - x_p), into
per-thread lanes of the grid on the CPU (physmorph.mpm.lanes), and x_bar gains the weights'
gradients. Apart, the node loop keeps few enough values live to run unrolled over the stencil's
rows at the transfers' scale (``unrolled``); fused with the particle part it ran no faster so.
"""

import taichi as ti

from physmorph.base import taichi_runtime  # noqa: F401  (Taichi's fast class test, before the kernels below)
from .adjoint import Adjoint
from .lanes import LANE_BLOCK
from .model import MPMModel
from .trajectory import Trajectory


@ti.data_oriented
class G2PAdjoint:
    """Reverse of G2P of substep t: adjoints of s_(t+1) -> grid_v_adj and the adjoints of s_t."""

    def __init__(self, model: MPMModel, trajectory: Trajectory, adjoint: Adjoint, unrolled: bool):
        self.model, self.trajectory, self.adjoint = model, trajectory, adjoint
        self.n, self.dtype = model.n, model.dtype
        self.unrolled = bool(unrolled)  # a compile-time constant of the node loop

    def backward(self, t: int, pair: bool) -> None:
        """Reverse of Transfers.g2p: adjoints of state t+1 -> grid_v_adj and the (x, F) adjoints of
        state t (pair: also the second set's). Two passes: each particle's part first, then the
        node loop, which alone keeps few enough values live to run unrolled."""
        self.g2p_backward_particles(t, pair)
        self.g2p_backward_nodes(t, pair)

    @ti.kernel
    def g2p_backward_particles(self, t: ti.i32, pair: ti.template()):
        """The particle part of g2p's reverse for every particle: F's adjoint of state t written,
        and the (x_bar, v_bar, C_bar) the node loop scatters left in x_adj, v_adj and C_adj, which
        that loop consumes. The particle's linearisation (_particle_linearization: its loads, the
        clamp, the volume scale and the inverses) is taken once for both sets with ``pair``."""
        a = self.adjoint
        for p in range(self.n):
            inside, Fh, B, r, Fs, Fs_inv_T, Fn_inv_T = self._particle_linearization(t, p)
            # one call site of the per-set part for both sets (a loop over the sets)
            for which in range(2 if ti.static(pair) else 1):
                xa, va, Ca, Fa = a.x_adj[p], a.v_adj[p], a.C_adj[p], a.F_adj[p]
                if ti.static(pair):
                    if which == 1:
                        xa, va, Ca, Fa = a.x_adj2[p], a.v_adj2[p], a.C_adj2[p], a.F_adj2[p]
                xb, vb, Cb, Fb = self._particle_adjoint(inside, Fh, B, r, Fs, Fs_inv_T, Fn_inv_T, xa, va, Ca, Fa)
                if which == 0:
                    a.x_adj[p], a.v_adj[p], a.C_adj[p], a.F_adj[p] = xb, vb, Cb, Fb
                if ti.static(pair):
                    if which == 1:
                        a.x_adj2[p], a.v_adj2[p], a.C_adj2[p], a.F_adj2[p] = xb, vb, Cb, Fb

    @ti.kernel
    def g2p_backward_nodes(self, t: ti.i32, pair: ti.template()):
        """The node loop of g2p's reverse: each particle's (x_bar, v_bar, C_bar) scattered to
        grid_v_adj, into per-thread lanes on the CPU."""
        lanes = self.model.lanes
        if ti.static(lanes.private):
            ti.loop_config(block_dim=LANE_BLOCK)
            for c in range(lanes.blocks):
                for p in range(lanes.first(c), lanes.first(c + 1)):
                    self._nodes_particle(t, p, c // LANE_BLOCK, pair)
        else:
            for p in range(self.n):
                self._nodes_particle(t, p, 0, pair)

    @ti.func
    def _nodes_particle(self, t, p, lane, pair: ti.template()):
        """Particle p's node loop, its grid adjoints added into lane ``lane``. Node I receives w q_I,
        q_I = v_bar + kq C_bar (x_I - x_p), and x_bar gains grad w (v_I . q_I) - w kq C_bar^T v_I.
        Along a row of the stencil q grows by a column of kq dx C_bar, and sum_I w v_I is the
        forward's v' (stored): the nodes add vectors only."""
        kq = 4.0 * self.dtype(self.model.inv_dx) * self.dtype(self.model.inv_dx)
        a = self.adjoint
        base, fx, w, dw = self.model.stencil(self.trajectory.x[t, p])
        xbar, vbar, Cbar = a.x_adj[p], a.v_adj[p], a.C_adj[p]
        a.v_adj[p], a.C_adj[p] = ti.zero(vbar), ti.zero(Cbar)  # consumed
        xbar2, vbar2, Cbar2 = xbar, vbar, Cbar
        if ti.static(pair):
            xbar2, vbar2, Cbar2 = a.x_adj2[p], a.v_adj2[p], a.C_adj2[p]
            a.v_adj2[p], a.C_adj2[p] = ti.zero(vbar), ti.zero(Cbar)
        Ck = (kq * self.dtype(self.model.dx)) * Cbar
        Ck2 = (kq * self.dtype(self.model.dx)) * Cbar2
        if ti.static(self.unrolled):
            for i, j in ti.static(ti.ndrange(3, 3)):
                xbar, xbar2 = self._row(base, fx, w, dw, i, j, vbar, Ck, vbar2, Ck2, xbar, xbar2, lane, pair)
        else:
            for i, j in ti.ndrange(3, 3):
                xbar, xbar2 = self._row(base, fx, w, dw, i, j, vbar, Ck, vbar2, Ck2, xbar, xbar2, lane, pair)
        v_new = self.trajectory.v[t + 1, p]
        a.x_adj[p] = xbar - kq * (Cbar.transpose() @ v_new)
        if ti.static(pair):
            a.x_adj2[p] = xbar2 - kq * (Cbar2.transpose() @ v_new)

    @ti.func
    def _row(self, base, fx: ti.template(), w: ti.template(), dw: ti.template(), i, j, vbar, Ck, vbar2, Ck2, xbar,
             xbar2, lane, pair: ti.template()):
        """Row (i, j) of a particle's node loop (_nodes_particle): its w q_I added into lane
        ``lane``; returns x_bar (and the second set's) with the row's terms added."""
        lanes, a = self.model.lanes, self.adjoint
        wij, dwi, dwj = w[i, 0] * w[j, 1], dw[i, 0] * w[j, 1], w[i, 0] * dw[j, 1]
        q = vbar + Ck @ (ti.Vector([i, j, 0], self.dtype) - fx)
        q2 = vbar2 + Ck2 @ (ti.Vector([i, j, 0], self.dtype) - fx)
        step_k = ti.Vector([Ck[0, 2], Ck[1, 2], Ck[2, 2]])  # q's change along a row
        step_k2 = ti.Vector([Ck2[0, 2], Ck2[1, 2], Ck2[2, 2]])
        for k in ti.static(range(3)):
            node = base + ti.Vector([i, j, k])
            gv = self.trajectory.grid_v[node]
            gw = ti.Vector([dwi * w[k, 2], dwj * w[k, 2], wij * dw[k, 2]])
            lanes.add(a.grid_v_adj_lanes, a.grid_v_adj, lane, node, (wij * w[k, 2]) * q)
            xbar += gv.dot(q) * gw
            q += step_k
            if ti.static(pair):
                lanes.add(a.grid_v_adj2_lanes, a.grid_v_adj2, lane, node, (wij * w[k, 2]) * q2)
                xbar2 += gv.dot(q2) * gw
                q2 += step_k2
        return xbar, xbar2

    @ti.func
    def _particle_linearization(self, t, p):
        """What the reverse of particle p's G2P update at substep t applies to any adjoint set: the
        clamp's mask on x (1 where x' is inside the domain), F of state t, B = I + dt C' and, under
        isochoric smoothing (F' = r Fs, Fs = (1 - s) Fn + s F, Fn = B F, r = (det Fn / det Fs)^(1/3)),
        r, Fs, Fs^-T and Fn^-T, each inverse zero where its term passes nothing back (below)."""
        dt = self.dtype(self.model.cfg.dt)
        xn = self.trajectory.x[t + 1, p]
        inside = ti.Vector.one(self.dtype, 3)
        for a in ti.static(range(3)):  # the clamp passes no gradient where it is active
            if xn[a] <= self.dtype(self.model.x_min) or xn[a] >= self.dtype(self.model.x_max):
                inside[a] = 0.0
        Fh = self.trajectory.F[t, p]
        B = ti.Matrix.identity(self.dtype, 3) + dt * self.trajectory.C[t + 1, p]
        r = ti.cast(1.0, self.dtype)
        Fs = Fh
        Fs_inv_T = ti.Matrix.zero(self.dtype, 3, 3)
        Fn_inv_T = ti.Matrix.zero(self.dtype, 3, 3)
        if ti.static(self.model.cfg.smoothing_mode == "isochoric"):
            s = self.dtype(self.model.cfg.smoothing)
            Fn = B @ Fh
            Fs = (1.0 - s) * Fn + s * Fh
            r = self.model.volume_scale(Fn, Fs)
            Jt = self.model.volume_target(Fn)
            if (Jt / Fs.determinant()) > 0:  # r follows the ratio (1 where it is not positive)
                Fs_inv_T = Fs.inverse().transpose()
                if Jt == Fn.determinant():  # det F' follows det Fn (not held at the floor J_min)
                    Fn_inv_T = Fn.inverse().transpose()
        return inside, Fh, B, r, Fs, Fs_inv_T, Fn_inv_T

    @ti.func
    def _particle_adjoint(self, inside, Fh, B, r, Fs, Fs_inv_T, Fn_inv_T, xbar_n, vbar_n, Cbar_n, Fbar_n):
        """The particle part of g2p's reverse for one adjoint set, with the particle's
        linearisation (inside .. Fn_inv_T: _particle_linearization): the adjoints of x, v, C, F of
        state t+1 -> F's of state t and the (x_bar, v_bar, C_bar) that the node loop scatters."""
        s = self.dtype(self.model.cfg.smoothing)
        dt = self.dtype(self.model.cfg.dt)
        xbar_n = xbar_n * inside
        Fbar_new = (1.0 - s) * Fbar_n
        Fbar = s * Fbar_n
        if ti.static(self.model.cfg.smoothing_mode == "isochoric"):
            # Fs_bar = r F'_bar - (r r_bar / 3) Fs^-T and Fn_bar += (r r_bar / 3) Fn^-T with
            # r_bar = <F'_bar, Fs> (each inverse zero where its term passes nothing back)
            k3 = r * (Fbar_n * Fs).sum() / 3.0
            Fs_bar = r * Fbar_n - k3 * Fs_inv_T
            Fbar_new = k3 * Fn_inv_T + (1.0 - s) * Fs_bar
            Fbar = s * Fs_bar
        Fh_bar = B.transpose() @ Fbar_new
        Fbar += Fh_bar
        Cbar = Cbar_n + dt * Fbar_new @ Fh.transpose()
        vbar = vbar_n + dt * xbar_n
        return xbar_n, vbar, Cbar, Fbar
