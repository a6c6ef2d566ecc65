"""The physics loss on the end-layer grid mass (paper section 4, "Physics rollout": the mass
loss L between the grid mass of x_T and the target's), its forms and terms, and its adjoint.

Forms (MPMConfig.mass_loss): "squared" sum_I (m_I - m*_I)^2, "log" (default) sum_I (log(m_I + e)
- log(m*_I + e))^2; terms: a blurred level (mass_loss_blur), the packing term (overfill_weight)
the stray pull's position anchors w_p |x_T,p - a_p|^2 and the volume term (physmorph.mpm.volume_term,
MPMConfig.volume_weight). Steps acting on the model (its target),
the stored end state and the adjoint; the loss's own settings (weights, anchors) and scratch here.
"""

import numpy as np
import taichi as ti

from physmorph.base import taichi_runtime  # noqa: F401  (Taichi's fast class test, before the kernels below)
from physmorph.base.grid import blur_weights
from physmorph.settings.mpm import MPMConfigError, MPMStateError

from .adjoint import Adjoint
from .currency import Currency
from .lanes import LANE_BLOCK
from .model import MPMModel, checked_array
from .state import ParticleState
from .trajectory import Trajectory
from .volume_term import VolumeTerm


@ti.data_oriented
class MassLoss:
    """The mass loss, its terms and its adjoint into the particles' x_T."""

    def __init__(self, model: MPMModel, trajectory: Trajectory, adjoint: Adjoint, current: Currency):
        self.model, self.trajectory, self.adjoint, self.current = model, trajectory, adjoint, current
        self.n, self.dtype, self.np_dtype = model.n, model.dtype, model.np_dtype
        cfg, f, R = model.cfg, model.dtype, model.cfg.grid_res
        self.loss_acc = ti.field(ti.f64, shape=())
        # the blurred level of the mass loss (mass_loss_blur > 0): the blurred grid mass, the blurred
        # target, the level's adjoint and two scratch grids for the separable passes
        self._blur_radius = int(np.ceil(3.0 * cfg.mass_loss_blur)) if cfg.mass_loss_blur > 0 else 0
        self.blur_grids = [ti.field(f, shape=(R, R, R)) for _ in range(5)] if cfg.mass_loss_blur > 0 else []
        if cfg.mass_loss_blur > 0:
            self.blur_w = ti.field(f, shape=2 * self._blur_radius + 1)
            self.blur_w.from_numpy(blur_weights(cfg.mass_loss_blur).astype(self.np_dtype))
        self.splat = GridMassSplat(model, trajectory)
        self.anchors = PositionAnchors(model, trajectory)
        self.volume = VolumeTerm(model, trajectory)
        self.reset()

    def reset(self) -> None:
        """No loss computed yet, the configured packing weight, no anchors."""
        self._last_loss: float | None = None
        self._last_mass_loss: float | None = None  # the last forward's loss without the anchors' term
        self._log_eps = 0.0
        self._overfill_weight = float(self.model.cfg.overfill_weight)
        self.anchors.active = False

    def load_frame(self, st: ParticleState) -> None:
        """The loaded frame's masses set the log form's e = log_mass_eps * mean particle mass, its
        rest state the volume term's V*."""
        self._log_eps = float(self.model.cfg.log_mass_eps * st.mass.mean())
        self.volume.set_rest_volume(st)

    def evaluate(self) -> float:
        """The loss of the stored end state (the grid cleared first by the caller), its adjoint
        dL/dm_I in the grid's; returns it with the anchors' and the volume term (loss()), keeping
        it and the mass loss alone (mass_loss())."""
        self.splat.splat_mass(self.model.cfg.substeps)
        self._loss_with_adjoint()
        self._last_mass_loss = float(self.loss_acc[None])
        if self.anchors.active:
            self.anchors.add_loss(self.loss_acc)
        self._last_loss = float(self.loss_acc[None])
        if self.volume.active:
            self._last_loss += self.volume.loss()
        return self._last_loss

    def backward(self, xa, Fa) -> None:
        """x_bar_T += dL/dx_T and F_bar_T += dL/dF_T of the stored end state's loss into the adjoint
        set ``xa``, ``Fa`` (the grid cleared first by the caller; the kept losses stay as they are)."""
        self.splat.splat_mass(self.model.cfg.substeps)
        self._loss_with_adjoint()
        self._loss_backward(xa)
        if self.anchors.active:
            self.anchors.backward(xa)
        if self.volume.active:
            self.volume.backward(Fa)

    @property
    def last_loss(self) -> float | None:
        """What the last evaluate() returned (None before one)."""
        return self._last_loss

    def no_target(self) -> float:
        """A forward without a target: its loss is nan."""
        self._last_loss = self._last_mass_loss = float("nan")
        return self._last_loss

    @ti.kernel
    def _mass_loss(self, log_eps: ti.f64, overfill_w: ti.f64):
        """Loss and dL/dm_I into grid_m_adj. squared: (m - m*)^2; log: (log(m+e) - log(m*+e))^2;
        plus the packing term _overfill_term with weight overfill_w where the configuration has one
        (overfill_weight > 0)."""
        self.loss_acc[None] = 0.0
        for I in ti.grouped(self.trajectory.grid_m):
            r2, adj = self._node_loss(self.trajectory.grid_m[I], self.model.target_m[I], log_eps)
            if ti.static(self.model.cfg.overfill_weight > 0):
                o2, oadj = self._overfill_term(self.trajectory.grid_m[I], self.model.target_m[I], log_eps, overfill_w)
                r2 += o2
                adj += oadj
            self.loss_acc[None] += r2
            self.adjoint.grid_m_adj[I] = adj

    @ti.func
    def _overfill_term(self, m, mt, log_eps: ti.f64, overfill_w: ti.f64):
        """The packing term of MPMConfig.overfill_weight: w max(0, r)^2 with r = log(m + e) -
        log(c + e), c = max(overfill_ratio density dx^3, m*), and its derivative 2 w max(0, r) / (m + e)."""
        e = ti.cast(log_eps, self.dtype)
        w = ti.cast(overfill_w, self.dtype)
        cap = ti.max(self.dtype(self.model.cfg.overfill_ratio * self.model.cfg.density * self.model.cfg.dx ** 3), mt)
        r = ti.max(ti.log(m + e) - ti.log(cap + e), 0.0)
        r2, adj = ti.cast(r * r, ti.f64), 2.0 * r / (m + e)
        return ti.cast(w, ti.f64) * r2, w * adj

    @ti.func
    def _node_loss(self, m, mt, log_eps: ti.f64):
        """One node's loss term and its derivative dL/dm: squared (m - m*)^2, 2 (m - m*); log
        (log(m + e) - log(m* + e))^2, 2 r / (m + e)."""
        r2 = ti.cast(0.0, ti.f64)
        adj = ti.cast(0.0, self.dtype)
        e = ti.cast(log_eps, self.dtype)
        if ti.static(self.model.cfg.mass_loss == "squared"):
            r = m - mt
            r2 = ti.cast(r * r, ti.f64)
            adj = 2.0 * r
        else:
            r2, adj = self._log_term(m, mt, e)
        return r2, adj

    @ti.func
    def _log_term(self, m, mt, e):
        """(log(m + e) - log(m* + e))^2 and its derivative 2 r / (m + e)."""
        r = ti.log(m + e) - ti.log(mt + e)
        return ti.cast(r * r, ti.f64), 2.0 * r / (m + e)

    @ti.kernel
    def _blur_axis(self, src: ti.template(), dst: ti.template(), axis: ti.template()):
        """One separable pass of MPMConfig.mass_loss_blur: dst_I = sum_k w_k src_(I + k e_axis) over
        |k| <= r, nodes outside the grid counting as zero (so the pass is a symmetric matrix)."""
        R = self.model.cfg.grid_res
        r = ti.static(self._blur_radius)
        for I in ti.grouped(dst):
            acc = ti.cast(0.0, self.dtype)
            for k in ti.static(range(-r, r + 1)):
                J = I + ti.Vector([k if axis == 0 else 0, k if axis == 1 else 0, k if axis == 2 else 0])
                if 0 <= J[axis] < R:
                    acc += self.blur_w[k + r] * src[J]
            dst[I] = acc

    def _blur(self, src, dst) -> None:
        """dst = B src, B the 3D Gaussian blur (three passes through the scratch grids)."""
        t1, t2 = self.blur_grids[3], self.blur_grids[4]
        self._blur_axis(src, t1, 0)
        self._blur_axis(t1, t2, 1)
        self._blur_axis(t2, dst, 2)

    @ti.kernel
    def _blur_level_loss(self, bm: ti.template(), bt: ti.template(), ba: ti.template(), log_eps: ti.f64,
                         weight: ti.f64):
        """The blurred level (MPMConfig.mass_loss_blur): weight x _node_loss of B m against B m* added
        to loss_acc, its adjoint into ba."""
        for I in ti.grouped(bm):
            r2, adj = self._node_loss(bm[I], bt[I], log_eps)
            self.loss_acc[None] += weight * r2
            ba[I] = ti.cast(weight, self.dtype) * adj

    @ti.kernel
    def _add_to_mass_adjoint(self, a: ti.template()):
        """dL/dm_I += a_I (the blurred level's adjoint brought back to the grid)."""
        for I in ti.grouped(a):
            self.adjoint.grid_m_adj[I] += a[I]

    def _loss_with_adjoint(self) -> None:
        """Mass loss of the splatted grid_m into loss_acc, dL/dm_I into grid_m_adj (all levels)."""
        self._mass_loss(self._log_eps, self._overfill_weight)
        if self.blur_grids:
            bm, bt, ba = self.blur_grids[:3]
            self._blur(self.trajectory.grid_m, bm)
            self._blur_level_loss(bm, bt, ba, self._log_eps, self.model.cfg.mass_loss_blur_weight)
            self._blur(ba, bm)  # B is symmetric: dL/dm = B dL/d(B m)
            self._add_to_mass_adjoint(bm)

    @ti.kernel
    def _loss_backward(self, xa: ti.template()):
        """Reverse of splat_mass(T) and _mass_loss: x_bar_T += sum_I grad(w_Ip) m_p dL/dm_I (on top
        of the injected g^x already there)."""
        T = self.model.cfg.substeps
        for p in range(self.n):
            base, fx, w, dw = self.model.stencil(self.trajectory.x[T, p])
            g = ti.Vector.zero(self.dtype, 3)
            if ti.static(self.model.at_scale):  # unrolled (physmorph.mpm.transfers' docstring)
                for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
                    g += self._node_gradient(base, w, dw, i, j, k, p)
            else:
                for i, j, k in ti.ndrange(3, 3, 3):
                    g += self._node_gradient(base, w, dw, i, j, k, p)
            xa[p] += g

    @ti.func
    def _node_gradient(self, base, w: ti.template(), dw: ti.template(), i, j, k, p):
        """grad(w_Ip) m_p dL/dm_I of node (i, j, k) of particle p's stencil."""
        m_bar = self.adjoint.grid_m_adj[base + ti.Vector([i, j, k])]
        return self.model.node_grad(w, dw, i, j, k) * (self.model.mass[p] * m_bar)

    def set_target_grid_mass(self, m: np.ndarray) -> None:  # m: [res, res, res]
        """Target grid mass (physmorph.base.grid.splat_mass convention)."""
        m = np.asarray(m, dtype=np.float64)
        R = self.model.cfg.grid_res
        if m.shape != (R, R, R):
            raise MPMStateError(f"target grid mass must have shape {(R, R, R)}, got {m.shape}")
        if not np.isfinite(m).all() or (m < 0).any():
            raise MPMStateError("target grid mass must be finite and >= 0")
        self.model.target_m.from_numpy(m.astype(self.np_dtype))
        if self.blur_grids:
            self._blur(self.model.target_m, self.blur_grids[1])
        self.volume.set_unit(m)
        self.current.has_target = True
        self.current.stale()  # the cached loss refers to the old target

    def set_overfill_weight(self, weight: float) -> None:
        """The packing term's weight from now on (MorphConfig.overfill_onset switches it on during a
        run): 0 leaves the configured mass loss alone; any weight needs a solver built with
        overfill_weight > 0, whose kernels carry the term."""
        if not (np.isfinite(weight) and weight >= 0):
            raise ValueError(f"overfill weight must be finite and >= 0, got {weight!r}")
        if weight > 0 and not self.model.cfg.overfill_weight > 0:
            raise MPMConfigError("set_overfill_weight > 0 needs a solver built with overfill_weight > 0")
        self._overfill_weight = float(weight)
        self.current.stale()

    def set_position_anchors(self, anchor: np.ndarray | None,  # [N, 3]
                             weight: np.ndarray | None = None) -> None:  # [N]
        """Add sum_p w_p |x_T,p - a_p|^2 to the loss from now on (the morph loop's stray pull,
        MorphConfig.stray_pull); None removes the term."""
        self.anchors.set(anchor, weight)
        self.current.stale()

    @property
    def overfill_weight(self) -> float:
        """The packing term's weight in use (MPMConfig.overfill_weight unless set_overfill_weight)."""
        return self._overfill_weight

    def loss(self) -> float:
        """The last forward's loss: the end-layer mass loss plus the anchors' term
        (set_position_anchors) and the volume term, what forward() returned."""
        if self._last_loss is None:
            raise RuntimeError("loss needs a forward first")
        return self._last_loss

    def mass_loss(self) -> float:
        """The last forward's end-layer mass loss (with the packing term), without the anchors' and
        the volume term."""
        if self._last_mass_loss is None:
            raise RuntimeError("mass_loss needs a forward first")
        return self._last_mass_loss


@ti.data_oriented
class GridMassSplat:
    """The grid mass of the particles at a substep, into the trajectory's working grid_m."""

    def __init__(self, model: MPMModel, trajectory: Trajectory):
        self.model, self.trajectory, self.n = model, trajectory, model.n

    def splat_mass(self, t: int) -> None:
        """m_I += sum_p w_Ip m_p of x_t (the physmorph.base.grid.splat_mass transfer) into grid_m;
        on the CPU through the grid's lanes (physmorph.mpm.lanes), so the loss is the same on
        every run."""
        self._splat_into_lanes(t)
        if self.trajectory.lanes.private:
            self._collect_mass()

    @ti.kernel
    def _collect_mass(self):
        """grid_m = the lanes' sum in lane order (the lanes zeroed)."""
        tr = self.trajectory
        for I in ti.grouped(tr.grid_m):
            tr.grid_m[I], _ = tr.lanes.collect_mass_momentum(tr.grid_mvm_lanes, tr.grid_mv, tr.grid_m, I)

    @ti.kernel
    def _splat_into_lanes(self, t: ti.i32):
        """splat_mass's particle loop: into the lanes (CPU) or grid_m itself (GPU, atomic adds)."""
        lanes = self.trajectory.lanes
        if ti.static(lanes.private):
            ti.loop_config(block_dim=LANE_BLOCK)
            for c in range(lanes.blocks):
                for p in range(lanes.first(c), lanes.first(c + 1)):
                    self._splat_particle(t, p, c // LANE_BLOCK)
        else:
            for p in range(self.n):
                self._splat_particle(t, p, 0)

    @ti.func
    def _splat_particle(self, t, p, lane):
        """Particle p's w_Ip m_p added into the grid's lane ``lane``."""
        base, fx, w, dw = self.model.stencil(self.trajectory.x[t, p])
        if ti.static(self.model.at_scale):  # unrolled (physmorph.mpm.transfers' docstring)
            for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
                self._splat_node(base, w, i, j, k, p, lane)
        else:
            for i, j, k in ti.ndrange(3, 3, 3):
                self._splat_node(base, w, i, j, k, p, lane)

    @ti.func
    def _splat_node(self, base, w: ti.template(), i, j, k, p, lane):
        """w_Ip m_p added into node (i, j, k) of particle p's stencil, in lane ``lane``."""
        lanes, tr = self.trajectory.lanes, self.trajectory
        node = base + ti.Vector([i, j, k])
        wt = w[i, 0] * w[j, 1] * w[k, 2]
        if ti.static(lanes.private):  # the packed lanes of P2G, with no momentum
            lanes.add_mass_momentum(tr.grid_mvm_lanes, tr.grid_mv, tr.grid_m, lane, node,
                                    ti.Vector.zero(self.model.dtype, 3), wt * self.model.mass[p])
        else:
            tr.grid_m[node] += wt * self.model.mass[p]


@ti.data_oriented
class PositionAnchors:
    """The loss's anchors' term w_p |x_T,p - a_p|^2 (the morph loop's stray pull), its fields
    allocated on first use: a_p and the weight w_p."""

    def __init__(self, model: MPMModel, trajectory: Trajectory):
        self.model, self.trajectory = model, trajectory
        self.n, self.dtype = model.n, model.dtype
        self.anchor = self.anchor_w = None
        self.active = False

    def set(self, anchor: np.ndarray | None,  # [N, 3]
            weight: np.ndarray | None = None) -> None:  # [N]
        """The anchors and weights from now on (None: no term)."""
        if anchor is None:
            self.active = False
            return
        a = checked_array(anchor, (self.n, 3), "anchor")
        w = np.asarray(weight, dtype=np.float64)
        if w.shape != (self.n,) or not np.isfinite(w).all() or (w < 0).any():
            raise MPMStateError(f"anchor weights must be [{self.n}], finite and >= 0")
        if self.anchor is None:
            self.anchor = ti.types.vector(3, self.dtype).field(shape=self.n)
            self.anchor_w = ti.field(self.dtype, shape=self.n)
        self.anchor.from_numpy(a.astype(self.model.np_dtype))
        self.anchor_w.from_numpy(w.astype(self.model.np_dtype))
        self.active = bool((w > 0).any())

    @ti.kernel
    def add_loss(self, loss_acc: ti.template()):
        """loss_acc += sum_p w_p |x_T,p - a_p|^2."""
        T = self.model.cfg.substeps
        for p in range(self.n):
            d = self.trajectory.x[T, p] - self.anchor[p]
            loss_acc[None] += ti.cast(self.anchor_w[p] * d.dot(d), ti.f64)

    @ti.kernel
    def backward(self, xa: ti.template()):
        """Reverse of add_loss: x_bar_T,p += 2 w_p (x_T,p - a_p)."""
        T = self.model.cfg.substeps
        for p in range(self.n):
            xa[p] += 2.0 * self.anchor_w[p] * (self.trajectory.x[T, p] - self.anchor[p])
