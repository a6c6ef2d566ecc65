"""The optimisers' steps on dFc as kernels (paper section 4, "Physics rollout": the control update):
the normalised gradient step with its step-volume projections and per-volume weights, the step
smoothing on the grid, and Adam's update. The optimisers in physmorph.mpm.optimiser drive them.
A mixin of MPMSolver.
"""

import taichi as ti


class StepKernels:
    """Kernels of a step on dFc: direction, projections, norms, smoothing, Adam."""

    @ti.func
    def _step_direction(self, direction: ti.template(), s, p, use_weight: ti.i32, volume_mode: ti.template()):
        """w_p d_sp (w the particle's step weight, 1 unless step_per_volume or use_weight 0), less
        its first-order change of volume (MPMConfig.step_volume; A = F_0 + dFc with dFc the
        iteration's base control and F_0 the frame's start, n = A^-T). volume_mode 1 ("particle"):
        the share beta (step_volume_share) of each particle's, d - beta (<d, n> / <n, n>) n;
        2 ("body"): the body's, d - lambda_s N with N = V_p det(A) n, the gradient of
        sum_p V_p det(A_p), and lambda_s from _body_volume_coefficients."""
        wp = self.step_weight[p] if use_weight else self.dtype(1.0)
        d = direction[s, p] * wp
        # volume_mode is a compile-time constant: the full step's kernels carry no 3x3 inverse
        if ti.static(volume_mode != 0):
            A = self.F[0, p] + self.ctrl_base[s, p]
            n = A.inverse().transpose()
            if ti.static(volume_mode == 1):
                d -= (ti.cast(self.step_volume_share[None], self.dtype) * (d * n).sum() / (n * n).sum()) * n
            else:
                d -= ti.cast(self.step_volume_coef[s], self.dtype) * (self.vol[p] * A.determinant()) * n
        return d

    @ti.kernel
    def _body_volume_coefficients(self, direction: ti.template(), use_weight: ti.i32):
        """lambda_s = <d_s, N_s> / <N_s, N_s> over every particle of slot s (d = w g, N as in
        _step_direction): the step's component that changes the body's volume to first order."""
        for s in self.step_volume_acc:
            self.step_volume_acc[s] = ti.Vector([0.0, 0.0], ti.f64)
        for s, p in self.ctrl:
            wp = self.step_weight[p] if use_weight else self.dtype(1.0)
            d = direction[s, p] * wp
            A = self.F[0, p] + self.ctrl_base[s, p]
            N = (self.vol[p] * A.determinant()) * A.inverse().transpose()
            self.step_volume_acc[s] += ti.Vector([ti.cast((d * N).sum(), ti.f64), ti.cast((N * N).sum(), ti.f64)])
        for s in self.step_volume_coef:
            acc = self.step_volume_acc[s]
            self.step_volume_coef[s] = acc[0] / acc[1] if acc[1] > 0 else 0.0

    @ti.kernel
    def _normalized_step(self, direction: ti.template(), alpha: ti.f64, inv_rms: ti.f64, clip: ti.f64,
                         use_weight: ti.i32, volume_mode: ti.template()):
        """dFc = base - alpha clip(d / rms(d), -clip, clip) (clip <= 0: unclipped), d the step's
        direction (_step_direction: the weighted gradient w g, or the smoothed direction with
        use_weight 0, less its change of volume where asked): the normalised gradient step of
        DiffMPMLib3D's optimiser, in place (tests: the NumPy formula, test_mpm)."""
        for s, p in self.ctrl:
            d = self._step_direction(direction, s, p, use_weight, volume_mode) * ti.cast(inv_rms, self.dtype)
            if clip > 0:
                d = ti.math.clamp(d, -ti.cast(clip, self.dtype), ti.cast(clip, self.dtype))
            self.ctrl[s, p] = self.ctrl_base[s, p] - ti.cast(alpha, self.dtype) * d

    @ti.kernel
    def _direction_dot_gradient(self, direction: ti.template(), inv_rms: ti.f64, clip: ti.f64, use_weight: ti.i32,
                                volume_mode: ti.template()):
        """norm_acc = <g, d>, d = clip(d / rms(d), -clip, clip) as in _normalized_step: the
        objective's first-order fall per unit alpha along the normalised step (the Armijo test's
        rate)."""
        self.norm_acc[None] = 0.0
        for s, p in self.ctrl_grad:
            g = self.ctrl_grad[s, p]
            d = self._step_direction(direction, s, p, use_weight, volume_mode) * ti.cast(inv_rms, self.dtype)
            if clip > 0:
                d = ti.math.clamp(d, -ti.cast(clip, self.dtype), ti.cast(clip, self.dtype))
            self.norm_acc[None] += ti.cast((g * d).sum(), ti.f64)

    @ti.kernel
    def _direction_norm_sq(self, direction: ti.template(), use_weight: ti.i32, volume_mode: ti.template(),
                           by_volume: ti.i32, inv_mean_volume: ti.f64):
        """norm_acc = sum_sp c_p |d_sp|^2, d the step's direction (_step_direction), c_p = 1 or,
        by_volume (MPMConfig.step_rms = "volume"), V_p / mean V: each particle counted by its volume."""
        self.norm_acc[None] = 0.0
        for s, p in direction:
            d = self._step_direction(direction, s, p, use_weight, volume_mode)
            c = ti.cast(self.vol[p], ti.f64) * inv_mean_volume if by_volume else 1.0
            self.norm_acc[None] += ti.cast((d * d).sum(), ti.f64) * c

    @ti.kernel
    def _smooth_step_slot(self, s: ti.i32):
        """Slot s of step_dir: the grid's share of the weighted gradient
        (MPMConfig.step_smoothing = "grid"): G_I = sum_p w_Ip V_p w_p g_p / sum_p w_Ip V_p on the
        MPM grid, with the B-spline weights w_Ip of x at the frame's start, then back to the
        particles, d_p = sum_I w_Ip G_I over the nodes that hold material (a partition of unity
        there). What varies from particle to particle within a cell, which the grid the body
        moves on does not see, is removed."""
        for I in ti.grouped(self.step_grid_w):
            self.step_grid[I] = ti.Matrix.zero(self.dtype, 3, 3)
            self.step_grid_w[I] = 0.0
        for p in range(self.n):
            base, fx, w, dw = self._stencil(self.x[0, p])
            g = self.ctrl_grad[s, p] * self.step_weight[p]
            for i, j, k in ti.ndrange(3, 3, 3):
                off, dpos, wip = self._node(fx, w, i, j, k)
                wv = wip * self.vol[p]
                self.step_grid[base + off] += wv * g
                self.step_grid_w[base + off] += wv
        for p in range(self.n):
            base, fx, w, dw = self._stencil(self.x[0, p])
            acc = ti.Matrix.zero(self.dtype, 3, 3)
            for i, j, k in ti.ndrange(3, 3, 3):
                off, dpos, wip = self._node(fx, w, i, j, k)
                m = self.step_grid_w[base + off]
                if m > 0:
                    acc += wip * self.step_grid[base + off] / m
            self.step_dir[s, p] = acc

    @ti.kernel
    def _adam(self, lr_t: ti.f64):
        """Adam (Kingma & Ba) on dFc; lr_t already carries the bias corrections."""
        b1 = self.dtype(self.cfg.adam_beta1)
        b2 = self.dtype(self.cfg.adam_beta2)
        for s, p in self.ctrl:
            g = self.ctrl_grad[s, p]
            m = b1 * self.adam_m[s, p] + (1.0 - b1) * g
            v = b2 * self.adam_v[s, p] + (1.0 - b2) * g * g
            self.adam_m[s, p] = m
            self.adam_v[s, p] = v
            step = ti.Matrix.zero(self.dtype, 3, 3)
            for a, b in ti.static(ti.ndrange(3, 3)):
                step[a, b] = m[a, b] / (ti.sqrt(v[a, b]) + self.dtype(self._eps_hat))
            c = self.ctrl[s, p] - ti.cast(lr_t, self.dtype) * step
            if ti.static(self._clip_on):
                c = ti.math.clamp(c, -self.dtype(self.cfg.control_clip), self.dtype(self.cfg.control_clip))
            self.ctrl[s, p] = c

    @property
    def _eps_hat(self) -> float:
        # a compile-time constant of _adam: eps without the step-dependent factor (a tiny
        # difference from textbook Adam, whose eps is added after the bias correction)
        return self.cfg.adam_eps
