"""Differentiable MPM solver (paper section 4, "Physics rollout"; SPEC section 4A).

Design decisions (documented here and in the docstrings they refer to):

* Transfer: MLS-MPM / APIC with the quadratic B-spline of physmorph.grid (the paper's code uses
  cubic); node i at lo + i dx. The end-layer grid mass equals physmorph.grid.splat_mass exactly.
* Constitutive model: fixed corotated on Fe = (F + dFc) Fp^-1; Kirchhoff stress P(Fe) Fe^T in
  the MLS-MPM affine term. dFc enters the stress only; F is advected by the grid velocity,
  F <- (I + dt C) F, then smoothed F <- (1 - s) F + s F_prev. Drag scales the P2G momentum by
  (1 - dt d). No gravity.
* Control: ``MPMConfig.control`` = "per_substep" (default, the paper code: one dFc per particle
  per substep, Adam on each) or "per_frame" (one dFc per particle shared by the T substeps).
* Warm start: dFc and the Adam moments persist across frames by default
  (``MPMConfig.warm_start=True``); the morph loop need not call reset_control. With
  warm_start=False, load_state resets them every frame.
* Mass loss: "squared" (default) L = sum_I (m_I - m*_I)^2; "log" L = sum_I (log(m_I + e) -
  log(m*_I + e))^2, e = log_mass_eps * mean particle mass. Delta E % = 100 (L_0 - L_J) / L_0.
* Backward: hand-written reverse kernels per substep (no Taichi tape); stored per substep:
  x, v, C, F (24 floats per particle: 96 B in float32, 192 B in float64); grids are recomputed.
  The rotation derivative floors s_i + s_j at 1e-6 max|s| (singular/inverted guard).
* Boundary: on the 3-cell layer of each face the outward grid velocity component is zeroed;
  particle positions are additionally clamped to [lo + dx, lo + (res - 2) dx] so the stencil
  never leaves the grid.
* Stability: the config refuses dt > cfl dx / c (c = P-wave speed, cfl = 0.5 by default) and
  warns above 80 % of it; a non-finite or exploding (|.| > 1e8) x, v or F after a rollout raises
  MPMDivergenceError naming the quantity, substep and particle.
"""

from .config import (CFLWarning, MPMConfig, MPMConfigError, MPMDivergenceError, MPMError,
                     MPMStateError)
from .solver import MPMSolver
from .state import ParticleState, elastic_energy, fixed_corotated_energy_density, total_volume

__all__ = ["CFLWarning", "MPMConfig", "MPMConfigError", "MPMDivergenceError", "MPMError",
           "MPMStateError", "MPMSolver", "ParticleState", "elastic_energy",
           "fixed_corotated_energy_density", "total_volume"]
