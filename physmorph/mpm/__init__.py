"""Differentiable MPM solver (paper section 4, "Physics rollout").

Design decisions (documented here and in the docstrings they refer to):

* Transfer: MLS-MPM / APIC with the quadratic B-spline of physmorph.base.grid (the paper's code uses
  cubic); node i at lo + i dx. The end-layer grid mass equals physmorph.base.grid.splat_mass exactly.
* Constitutive model: fixed corotated on Fe = (F + dFc) Fp^-1; Kirchhoff stress P(Fe) Fe^T in
  the MLS-MPM affine term. dFc enters the stress only; F is advected by the grid velocity,
  F <- (I + dt C) F, then smoothed F <- (1 - s) F + s F_prev. Drag scales the P2G momentum by
  (1 - dt d). No gravity.
* Control: one dFc per particle per substep (the paper code), each stepped by the optimiser.
* Warm start: dFc and the Adam moments persist across frames (load_state leaves them); the
  morph loop need not call reset_control.
* Mass loss: "squared" L = sum_I (m_I - m*_I)^2; "log" (default) L = sum_I (log(m_I + e) -
  log(m*_I + e))^2, e = log_mass_eps * mean particle mass. Delta E % = 100 (L_0 - L_J) / L_0.
* Backward: hand-written reverse kernels per substep (no Taichi tape); stored per substep:
  x, v, C, F and the rotation of Fe as a quaternion with its pair sum (29 floats per particle:
  116 B in float32, 232 B in float64; physmorph.settings.solver_memory), and the P2G grid (4 floats per node).
  The rotation derivative floors s_i + s_j at 1e-6 max|s| (singular/inverted guard).
* Boundary: on the 3-cell layer of each face the outward grid velocity component is zeroed;
  particle positions are additionally clamped to [lo + dx, lo + (res - 2) dx] so the stencil
  never leaves the grid.
* Frame API: optimize_control runs J x (forward, backward, Adam) and a last forward with the
  updated dFc, so loss_final is the loss of the trajectory rollout() then returns without
  recomputing it. backward() adds the injected adjoints g^F (on F_T, pre-scaled by gamma) and
  g^x (on x_T) to the mass-loss adjoint. Extra entry points for tests/diagnostics: forward,
  backward, adam_step, control/set_control/control_gradient, initial_state_gradients,
  state_at(t), grid_mass, solver.evaluate_stress.
* float64: Python constants are passed to kernels as typed constants, and the rotation from
  ti.svd (only ~1e-6 accurate, even in f64) is polished by two Newton steps on sym(R^T Fe), so a
  float64 solver is float64-accurate (finite-difference checks agree to ~1e-8).
* Stability: the config refuses dt > cfl dx / c (c = P-wave speed, cfl = 0.5 by default) and
  warns above 80 % of it; a non-finite or exploding (|.| > 1e8) x, v or F after a rollout raises
  MPMDivergenceError naming the quantity, substep and particle.

May import physmorph.settings and physmorph.base; not the renderer, the plasticity or the morph loop.
"""
