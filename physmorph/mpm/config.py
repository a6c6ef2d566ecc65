"""Typed configuration of the differentiable MPM solver (paper section 4, "Physics rollout").

Defaults are the paper's values (E = 1.4e5, nu = 0.2, rho = 75, dt = 1/240 s, T = 20, grid 64^3
over [-16, 16]^3, drag d = 0.9, smoothing s = 0.955) unless a field says otherwise.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, fields
from typing import ClassVar, Literal

from ..grid import BOUNDARY_CELLS, DOMAIN_HI, DOMAIN_LO


class MPMError(RuntimeError):
    """Base class of every solver error."""


class MPMConfigError(ValueError):
    """An invalid solver configuration; the message names the offending quantity."""


class MPMStateError(ValueError):
    """An invalid particle state (shape, NaN/Inf, outside the domain); names the quantity."""


class MPMDivergenceError(MPMError):
    """The simulation or its gradient became non-finite. ``quantity``: what did (x, v, F, the dFc
    gradient, ...); ``substep`` and ``particle`` where they are known. The message says the same
    in words; code reads the attributes."""

    def __init__(self, message: str, quantity: str | None = None, substep: int | None = None,
                 particle: int | None = None):
        super().__init__(message)
        self.quantity, self.substep, self.particle = quantity, substep, particle


class CFLWarning(UserWarning):
    """dt is within a factor of the stable step; the run is allowed but close to the limit."""


CONTROL_MODES = ("per_substep", "per_frame")
SMOOTHING_MODES = ("full", "isochoric")
MASS_LOSSES = ("squared", "log", "sqrt", "log_bounded", "log_convex")
OPTIMIZERS = ("adam", "normalized_gd")
# MPMConfig.step_volume, in the order of the step kernels' volume_mode
STEP_VOLUME_MODES = ("full", "particle", "body")
VOLUME_LAWS = ("fixed_corotated", "barrier")
# Below this J the barrier law's g(J) = lam (1 - 1/J) is continued by its tangent (finite for J <= 0).
BARRIER_J_LINEAR = 0.05
# Fields only the Python driver reads (the optimiser loop, load_state, the config checks): no
# kernel bakes them in, so a built solver takes new values without compiling again
# (MPMSolver.configure, solver_for). tests/test_mpm_solver.py checks no kernel reads them.
DRIVER_FIELDS = frozenset({"learning_rate", "step_scales_with_dx", "optimizer", "line_search_iters", "step_clip",
                           "step_per_volume", "step_volume_power", "step_rms",
                           "step_smoothing", "step_volume", "step_volume_share",
                           "sufficient_decrease", "grad_iters",
                           "log_mass_eps", "warm_start", "cfl", "cfl_warn_fraction"})


@dataclass(frozen=True)
class MPMConfig:
    """Solver configuration.

    control: "per_substep" keeps one dFc per particle per substep (T fields, the paper code's
        choice, Adam steps each one); "per_frame" shares one dFc per particle over the T substeps
        of a frame (T times less memory, gradient summed over substeps).
    mass_loss: "squared": L = sum_I (m_I - m*_I)^2 over all grid nodes I (plain squared
        difference of grid masses, kg^2). "log": L = sum_I (log(m_I + eps) - log(m*_I + eps))^2
        with eps = log_mass_eps * (mean particle mass); it weights thin/low-density regions more,
        but its pull on a node falls as 1/m, so mass packed into a few nodes is cheap.
        "sqrt": L = sum_I (sqrt(m_I + eps) - sqrt(m*_I + eps))^2 (a squared Hellinger distance),
        between the two: a node's pull, (1 - sqrt((m* + eps) / (m + eps))), stays bounded as m grows
        and as it falls to zero (docs/study/log.md part 11).
        "log_bounded": the log loss where m_I <= m*_I (empty and thin nodes), and above it
        (4 / (m*_I + eps)) (sqrt(m_I + eps) - sqrt(m*_I + eps))^2, the sqrt loss scaled to the log
        loss's curvature at m = m* (C^2 there): an overfilled node pulls with up to 4 / (m* + eps)
        instead of the log loss's vanishing 2 log(m / m*) / m.
        "log_convex": the log loss up to r = log((m_I + eps) / (m*_I + eps)) = 1, where r^2 turns
        concave in m, and its tangent line above (the overfill term the same): where the target
        leaves a node (nearly) empty that is from m_I ~ 1.7 eps on, so the log loss rewards packing
        material the target does not hold into fewer nodes; the tangent's pull 2 / ((m* + eps) e)
        is the largest the log loss has, and it no longer falls as 1/m (docs/study/log.md part 40).
    mass_loss_levels: the mass loss summed over a pyramid of grids: level 0 the grid, level l the
        grid mass summed over blocks of 2^l x 2^l x 2^l nodes, each level the same loss form (log:
        eps x 8^l) with weight 1. Coarse levels see a missing feature (an ear) from farther away
        than the 27-node stencil does. 1 = the grid alone (the paper's loss).
    mass_loss_blur: sigma (in cells) of a Gaussian-blurred level added to the mass loss, 0 = off:
        mass_loss_blur_weight x sum_I (log((B m)_I + e) - log((B m*)_I + e))^2 in the log form (each
        form as on the grid), B the separable Gaussian blur of the grid, truncated at 3 sigma, its
        weights summing to 1, zero outside the grid. The grid's loss sees a particle's 27 nodes
        only: material several cells from any node the target fills feels no pull toward it, and
        the pyramid's block sums move only particles on a block's edge; the blur gives every
        particle within ~3 sigma of the target a direction toward it (docs/study/log.md finding
        178: the cow's head 4 cells in front of the bunny). The default, 2 cells, brings the
        far morphs' material in sooner (findings 184-185).
    mass_loss_blur_weight: the blurred level's weight (the grid's own is 1).
    overfill_weight: w of a packing term added to the mass loss, 0 = off (the paper has none):
        w sum_I max(0, log(m_I + eps) - log(c_I + eps))^2 with the cap c_I = max(overfill_ratio x
        density x dx^3, m*_I), the node mass of material at overfill_ratio times its density, or
        the target's own where that is more. It is zero wherever a node holds no more than the
        target or the cap, so it never pulls against the target; where the log loss's pull falls
        as 1/m on a packed node, this adds a pull the optimiser sees within the frame
        (docs/study/log.md part 15). The default, weight 1 with the cap at the target's own node
        mass (ratio 0.001), makes every node holding more than the target pay the log loss's term
        twice: the body spills less past the silhouette (findings 175, 180); MorphConfig's
        overfill_onset starts it when the body has arrived.
    overfill_ratio: the density ratio of that cap (the sampled shapes at rest reach ~2x their
        density at the 99th percentile, on their surface shell; 0.001: the target's own mass).
    warm_start: True keeps dFc and the Adam moments across frames (load_state does not touch
        them; the particles are the same material points from frame to frame); False makes
        load_state call reset_control.
    cfl: the solver refuses dt > cfl * dx / c with c = sqrt((lambda + 2 mu) / rho) the
        P-wave speed, and warns (CFLWarning) above cfl_warn_fraction of that step.
    control_in_F: False: dFc enters the stress only, Fe = (F + dFc) Fp^-1, and F is advected by the
        grid velocity alone (an actuation). True (the authors' published code, DiffMPMLib3D):
        dFc is also carried in the deformation gradient, F_new = (I + dt C') (F + dFc), then
        smoothed with the pre-control F, F' = (1 - s) F_new + s F; the render adjoint on F_T
        then reaches dFc to first order.
    optimizer: "adam" (per-entry normalised steps, moments kept across frames with warm_start)
        or "normalized_gd" (the authors' code: dFc <- dFc - alpha g / rms(g), a step whose
        per-entry RMS is alpha = learning_rate, so relative gradient sizes are kept; a
        backtracking line search halves alpha up to line_search_iters times until the frame's
        objective, mass loss + injected linear terms, decreases, else the step is undone).
    step_scales_with_dx: the step used is learning_rate x dx / (1 domain unit) (``step_size``), so
        learning_rate is the step at a one-unit cell (the default profile's grid) and the same
        setting moves the body the same distance per frame at every grid: a control that differs
        from particle to particle pushes on the grid with a force per unit mass ~ E dFc / (rho dx),
        so a step fixed in F units moves a finer grid's body further (at grid 64 the mid profile's
        cross-shape morphs spray and fall back; docs/study/log.md finding 116). False: the step is
        learning_rate at every grid (until 2026-11-25).
    sufficient_decrease: normalized_gd only: the line search's Armijo constant c: a trial step is
        accepted when the objective falls by at least c alpha <g, d> (d the normalised direction,
        <g, d> its first-order rate), else alpha is halved; 0 accepts any decrease (DiffMPMLib3D's
        rule). A fixed-size normalised step keeps kicking a converged body by the same amount each
        frame; with c > 0 the step shrinks where the loss no longer falls as fast as the gradient
        promises.
    step_clip: normalized_gd only: if > 0, each entry of the normalised step g / rms(g) is clamped
        to [-step_clip, step_clip], so no particle's control moves more than step_clip x alpha per
        iteration (a gradient concentrated on a few particles otherwise moves them by many alpha).
    step_per_volume: normalized_gd only: the step direction is the gradient per unit of particle
        volume, g_p V_max / V_p, normalised by its RMS (and clipped by step_clip). dL/dFc_p carries
        the particle's volume (its stress enters P2G times V_p), so a plain normalised step drives
        a shell-biased sampling's interior particles (PPC 1) harder than its surface ones: 8x at
        PPC 2, 125x at the paper's PPC 5, where 99 % of the particles are in the surface shell
        (docs/study/log.md finding 131). False: g / rms(g), the authors' step (until 2026-11-26).
    step_volume_power: with step_per_volume, the weight's exponent: the direction is
        g_p (V_max / V_p)^power. 1 (the default): the gradient per unit volume; 0: the plain step;
        in between, a light particle is driven harder than the plain step drives it but less than a
        heavy one under the same stress.
    step_rms: normalized_gd only: the mean the step's RMS is taken over. "particles": every particle
        counts once, so the particles of the densest sampling set the step (at the paper's PPC 5/1 the
        surface shell holds 99 % of the particles and 40 % of the volume). "volume": each particle
        counts by its volume, V_p / mean V, so the step's RMS is that of the body's volume whatever
        its sampling.
    step_smoothing: normalized_gd only: "grid" replaces the weighted gradient by its share on the
        MPM grid before the step is normalised (volume-weighted P2G of w_p g_p, then G2P): the part
        that varies from particle to particle within a cell moves no grid node, and only sprays
        particles; "none" (the default) steps along the particles' own gradients.
    step_volume: normalized_gd only: what the step may do to the volume the stress sees (the control
        enters the stress as F + dFc, A = F + dFc at the frame's start, n = A^-T). "particle": each
        particle's step direction d loses its first-order change of det A, d - (<d, n> / <n, n>) n,
        so the control shapes each particle and compresses none. "body": the step loses only its
        first-order change of the body's volume sum_p V_p det A_p (one direction per control slot,
        N_p = V_p det(A_p) n_p), so particles may trade volume and the body keeps its own. The
        target's mass is rescaled to the source's, so a matched shape has the source's volume.
        "full": the authors' step. Measured in docs/study/log.md findings 156-158: "particle"
        lifts mid's runs and, removing all of each particle's change, costs the default profile's
        far and letter morphs; "body" changes nothing. The default: "particle" with a share 0.75.
    step_volume_share: with step_volume "particle", the share beta of each particle's change of
        volume removed, d - beta (<d, n> / <n, n>) n: 1 removes all of it, 0 is the full step
        (default 0.75: mid keeps its gain and the default profile's far morphs their bars).
    smoothing_mode: "full" (the paper): F' = (1 - s) F_new + s F, every part of F follows 1 - s of
        each substep's motion. "isochoric" (the default since 2026-11-24; not in the
        paper): that blend rescaled to the determinant of F_new, F' = (det F_new / det F_s)^(1/3)
        F_s, so the volume ratio J = det F follows the motion exactly (J' = det(I + dt C') J) and
        only the shape is smoothed. With "full", a morph can pack its material at many times its
        density while det F stays near 0.9, since the elastic stress sees 4.5 % of the
        compression (docs/study/log.md findings 62, 69-71 and 74).
    volume_stiffness: K (Pa) of a pressure that resists packing, 0 = off (the paper has none).
        At each frame's start every particle's density rho_p = sum_I w_Ip m_I / dx^3 is measured
        from the P2G mass; where it exceeds volume_onset x density, the particle carries the
        pressure p = K ln(rho_p / (volume_onset density)) through the frame's substeps (Kirchhoff
        stress -p I in the P2G affine term). The F smoothing lets F follow ~4.5 % of the motion, so
        the elastic stress barely sees compression and a morph can pack its material at many
        times its density (docs/study/log.md findings 62 and 67); this term measures the packing
        from the particles' positions instead. Held fixed within the frame, it is a known force
        to that frame's control, so the control gradient is exact (the initial-state gradient
        holds it fixed too).
    volume_onset: the density ratio above which the pressure acts (the sampled source at rest
        reaches ~2x its density at the 99th percentile, on its surface shell).
    volume_law: the volume term of the elastic energy (physmorph.mpm.stress). "fixed_corotated"
        (the paper's): lam/2 (J - 1)^2, whose Kirchhoff pressure lam (J - 1) J peaks at J = 1/2 and
        vanishes as J -> 0, so material compressed past half its volume resists less the more it
        is compressed. "barrier" (not the paper's): lam (J - 1 - ln J), equal to second order at
        J = 1, pressure lam (J - 1) growing with the compression, energy unbounded as J -> 0
        (docs/study/log.md part 15).
    min_volume_ratio: a floor J_min on det F (0.25 since 2026-11-24; 0 = off, the paper has
        none; it acts under isochoric smoothing only, where the rescaled blend takes det F' =
        max(det F_new, J_min); the paper's blend has no det F to hold). The fixed-corotated stress
        stays finite as det F -> 0, so under a strong control a particle can be crushed to a
        singular F, whose smoothed blend the rescale then blows up (docs/study/log.md finding 76).
        The authors' code bounds det F in compression too (a trust region on C).
    control_clip: if > 0, dFc entries are clamped to [-control_clip, control_clip] after each
        Adam step (0 = off, the paper's behaviour).
    """

    # Fields whose default changed after runs were made with the old one: always in a run's params
    # (physmorph.config.without_defaults), so those runs rerun (workflow/schemas/first_defaults.json).
    # step_scales_with_dx: a new field that changes, at its default, every run whose dx is not 1.
    ALWAYS_IN_PARAMS: ClassVar[frozenset[str]] = frozenset({"learning_rate", "smoothing_mode", "min_volume_ratio",
                                                             "step_scales_with_dx", "step_per_volume",
                                                             "step_volume", "step_volume_share",
                                                             "overfill_weight", "overfill_ratio", "mass_loss_blur"})

    grid_res: int = 64
    domain_lo: float = DOMAIN_LO
    domain_hi: float = DOMAIN_HI
    dt: float = 1.0 / 240.0
    substeps: int = 20
    youngs_modulus: float = 1.4e5
    poisson_ratio: float = 0.2
    density: float = 75.0
    drag: float = 0.9
    smoothing: float = 0.955
    smoothing_mode: Literal["full", "isochoric"] = "isochoric"
    control: Literal["per_substep", "per_frame"] = "per_substep"
    control_in_F: bool = False
    learning_rate: float = 0.004  # history: docs/study/CHANGELOG.md
    step_scales_with_dx: bool = True
    optimizer: Literal["adam", "normalized_gd"] = "normalized_gd"
    line_search_iters: int = 10
    sufficient_decrease: float = 0.0
    step_clip: float = 3.0
    step_per_volume: bool = True  # history: docs/study/CHANGELOG.md
    step_volume_power: float = 1.0
    step_rms: Literal["particles", "volume"] = "particles"
    step_smoothing: Literal["none", "grid"] = "none"
    step_volume: Literal["full", "particle", "body"] = "particle"  # history: docs/study/CHANGELOG.md
    step_volume_share: float = 0.75
    grad_iters: int = 1
    adam_beta1: float = 0.9
    adam_beta2: float = 0.999
    adam_eps: float = 1e-8
    mass_loss: Literal["squared", "log", "sqrt", "log_bounded", "log_convex"] = "log"
    log_mass_eps: float = 0.1
    mass_loss_levels: int = 1
    mass_loss_blur: float = 2.0  # history: docs/study/CHANGELOG.md
    mass_loss_blur_weight: float = 1.0
    overfill_weight: float = 1.0  # history: docs/study/CHANGELOG.md
    volume_law: Literal["fixed_corotated", "barrier"] = "fixed_corotated"
    overfill_ratio: float = 0.001
    warm_start: bool = True
    volume_stiffness: float = 0.0
    volume_onset: float = 2.0
    min_volume_ratio: float = 0.25
    control_clip: float = 0.0
    cfl: float = 0.5
    cfl_warn_fraction: float = 0.8
    device: Literal["auto", "cpu", "cuda"] = "cpu"
    precision: Literal["float32", "float64"] = "float32"
    threads: int | None = None

    def __post_init__(self) -> None:
        def need(ok: bool, msg: str) -> None:
            if not ok:
                raise MPMConfigError(msg)

        need(isinstance(self.grid_res, int) and self.grid_res >= 2 * BOUNDARY_CELLS + 2,
             f"grid_res must be an int >= {2 * BOUNDARY_CELLS + 2}, got {self.grid_res!r}")
        need(math.isfinite(self.domain_lo) and math.isfinite(self.domain_hi)
             and self.domain_hi > self.domain_lo,
             f"domain needs finite domain_hi > domain_lo, got {self.domain_lo}, {self.domain_hi}")
        need(math.isfinite(self.dt) and self.dt > 0, f"dt must be finite and > 0, got {self.dt}")
        need(isinstance(self.substeps, int) and self.substeps >= 1,
             f"substeps (T) must be an int >= 1, got {self.substeps!r}")
        need(math.isfinite(self.youngs_modulus) and self.youngs_modulus > 0,
             f"youngs_modulus must be > 0, got {self.youngs_modulus}")
        need(-1.0 < self.poisson_ratio < 0.5,
             f"poisson_ratio must be in (-1, 0.5), got {self.poisson_ratio}")
        need(math.isfinite(self.density) and self.density > 0,
             f"density must be > 0, got {self.density}")
        need(math.isfinite(self.drag) and 0.0 <= self.drag * self.dt <= 1.0,
             f"drag must satisfy 0 <= drag * dt <= 1 (momentum factor 1 - dt*d in [0, 1]), "
             f"got drag={self.drag}, dt={self.dt}")
        need(0.0 <= self.smoothing < 1.0, f"smoothing s must be in [0, 1), got {self.smoothing}")
        need(self.smoothing_mode in SMOOTHING_MODES,
             f"smoothing_mode must be one of {SMOOTHING_MODES}, got {self.smoothing_mode!r}")
        need(self.control in CONTROL_MODES, f"control must be one of {CONTROL_MODES}, got {self.control!r}")
        need(self.mass_loss in MASS_LOSSES, f"mass_loss must be one of {MASS_LOSSES}, got {self.mass_loss!r}")
        need(math.isfinite(self.learning_rate) and self.learning_rate > 0,
             f"learning_rate must be > 0, got {self.learning_rate}")
        need(isinstance(self.grad_iters, int) and self.grad_iters >= 1,
             f"grad_iters (J) must be an int >= 1, got {self.grad_iters!r}")
        need(0 <= self.adam_beta1 < 1 and 0 <= self.adam_beta2 < 1 and self.adam_eps > 0,
             f"Adam needs 0 <= beta1, beta2 < 1 and eps > 0, got {self.adam_beta1}, "
             f"{self.adam_beta2}, {self.adam_eps}")
        need(self.optimizer in OPTIMIZERS, f"optimizer must be one of {OPTIMIZERS}, got {self.optimizer!r}")
        need(self.step_clip >= 0, f"step_clip must be >= 0 (0 = off), got {self.step_clip!r}")
        need(self.step_smoothing in ("none", "grid"), f"step_smoothing must be none or grid, got {self.step_smoothing!r}")
        need(0.0 <= self.step_volume_share <= 1.0, f"step_volume_share must be in [0, 1], got {self.step_volume_share}")
        need(self.step_volume in STEP_VOLUME_MODES,
             f"step_volume must be one of {', '.join(STEP_VOLUME_MODES)}, got {self.step_volume!r}")
        need(self.step_rms in ("particles", "volume"), f"step_rms must be particles or volume, got {self.step_rms!r}")
        need(0 <= self.step_volume_power <= 1, f"step_volume_power must be in [0, 1], got {self.step_volume_power!r}")
        need(math.isfinite(self.sufficient_decrease) and 0.0 <= self.sufficient_decrease < 1.0,
             f"sufficient_decrease must be in [0, 1), got {self.sufficient_decrease}")
        need(isinstance(self.line_search_iters, int) and self.line_search_iters >= 1,
             f"line_search_iters must be an int >= 1, got {self.line_search_iters!r}")
        need(self.volume_law in VOLUME_LAWS, f"volume_law must be one of {VOLUME_LAWS}, got {self.volume_law!r}")
        need(math.isfinite(self.overfill_weight) and self.overfill_weight >= 0,
             f"overfill_weight must be finite and >= 0 (0 = off), got {self.overfill_weight}")
        need(math.isfinite(self.overfill_ratio) and self.overfill_ratio > 0,
             f"overfill_ratio must be > 0, got {self.overfill_ratio}")
        need(self.log_mass_eps > 0, f"log_mass_eps must be > 0, got {self.log_mass_eps}")
        need(math.isfinite(self.mass_loss_blur) and 0 <= self.mass_loss_blur <= 16,
             f"mass_loss_blur must be in [0, 16] cells (0 = off), got {self.mass_loss_blur}")
        need(math.isfinite(self.mass_loss_blur_weight) and self.mass_loss_blur_weight >= 0,
             f"mass_loss_blur_weight must be finite and >= 0, got {self.mass_loss_blur_weight}")
        need(isinstance(self.mass_loss_levels, int) and self.mass_loss_levels >= 1
             and self.grid_res % (1 << (self.mass_loss_levels - 1)) == 0,
             f"mass_loss_levels must be an int >= 1 whose blocks 2^(levels-1) divide grid_res "
             f"{self.grid_res}, got {self.mass_loss_levels!r}")
        need(math.isfinite(self.volume_stiffness) and self.volume_stiffness >= 0,
             f"volume_stiffness must be finite and >= 0 (0 = off), got {self.volume_stiffness}")
        need(math.isfinite(self.volume_onset) and self.volume_onset > 0,
             f"volume_onset must be > 0, got {self.volume_onset}")
        need(math.isfinite(self.min_volume_ratio) and 0 <= self.min_volume_ratio < 1,
             f"min_volume_ratio must be in [0, 1) (0 = off), got {self.min_volume_ratio}")
        need(self.control_clip >= 0, f"control_clip must be >= 0, got {self.control_clip}")
        need(0 < self.cfl <= 1.0, f"cfl must be in (0, 1], got {self.cfl}")
        need(0 < self.cfl_warn_fraction <= 1.0,
             f"cfl_warn_fraction must be in (0, 1], got {self.cfl_warn_fraction}")
        need(self.device in ("cpu", "cuda", "auto"), f"device must be cpu, cuda or auto, got {self.device!r}")
        need(self.precision in ("float32", "float64"),
             f"precision must be float32 or float64, got {self.precision!r}")
        dt_max = self.stable_dt
        if self.dt > dt_max:
            raise MPMConfigError(
                f"dt={self.dt:.6g} exceeds the stable step {dt_max:.6g} = cfl*dx/c for "
                f"E={self.youngs_modulus:g}, rho={self.density:g}, nu={self.poisson_ratio:g}, "
                f"dx={self.dx:g} (P-wave speed c={self.wave_speed:.4g}); lower dt or E, or refine less")
        if self.dt > self.cfl_warn_fraction * dt_max:
            warnings.warn(
                f"dt={self.dt:.6g} is {self.dt / dt_max:.0%} of the stable step {dt_max:.6g} "
                f"(E={self.youngs_modulus:g}, rho={self.density:g}, dx={self.dx:g})", CFLWarning,
                stacklevel=3)

    @property
    def dx(self) -> float:
        return (self.domain_hi - self.domain_lo) / self.grid_res

    @property
    def step_size(self) -> float:
        """The optimiser's step: learning_rate, times dx in domain units with step_scales_with_dx."""
        return self.learning_rate * (self.dx if self.step_scales_with_dx else 1.0)

    @property
    def mu(self) -> float:
        """Lame shear modulus mu = E / (2 (1 + nu))."""
        return self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))

    @property
    def lam(self) -> float:
        """Lame first parameter lambda = E nu / ((1 + nu)(1 - 2 nu))."""
        return self.youngs_modulus * self.poisson_ratio / (
            (1.0 + self.poisson_ratio) * (1.0 - 2.0 * self.poisson_ratio))

    @property
    def wave_speed(self) -> float:
        """P-wave speed sqrt((lambda + 2 mu) / rho) of the linearised material."""
        return math.sqrt((self.lam + 2.0 * self.mu) / self.density)

    @property
    def stable_dt(self) -> float:
        """Largest accepted dt: cfl * dx / c."""
        return self.cfl * self.dx / self.wave_speed

    def kernel_settings(self) -> tuple:
        """The (name, value) pairs a solver's compiled kernels depend on: every field but DRIVER_FIELDS."""
        return tuple((f.name, getattr(self, f.name)) for f in fields(self) if f.name not in DRIVER_FIELDS)

    @property
    def n_control_slots(self) -> int:
        return self.substeps if self.control == "per_substep" else 1
