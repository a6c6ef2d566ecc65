"""Typed configuration of the differentiable MPM solver (paper section 4, "Physics rollout").

Defaults are the paper's values (E = 1.4e5, nu = 0.2, rho = 75, dt = 1/240 s, T = 20, grid 64^3
over [-16, 16]^3, drag d = 0.9, smoothing s = 0.955) unless a field says otherwise.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import fields
from typing import Annotated, ClassVar, Literal

from physmorph.grid import BOUNDARY_CELLS, DOMAIN_HI, DOMAIN_LO
from physmorph.settings_base import Bool, Float, Int, Refused, setting, settings_dataclass


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


@settings_dataclass(error=MPMConfigError)
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
    # (physmorph.config_params.without_defaults), so those runs rerun (workflow/schemas/first_defaults.json).
    # step_scales_with_dx: a new field that changes, at its default, every run whose dx is not 1.
    ALWAYS_IN_PARAMS: ClassVar[frozenset[str]] = frozenset({"learning_rate", "smoothing_mode", "min_volume_ratio",
                                                             "step_scales_with_dx", "step_per_volume",
                                                             "step_volume", "step_volume_share",
                                                             "overfill_weight", "overfill_ratio", "mass_loss_blur"})

    grid_res: Annotated[Int, setting("MPM grid cells per axis (set by sampling.grid_res)", "cells",
                                     ge=2 * BOUNDARY_CELLS + 2)] = 64
    domain_lo: Annotated[Float, setting("lower corner of the simulation cube (set by domain)", "domain units")] = DOMAIN_LO
    domain_hi: Annotated[Float, setting("upper corner of the simulation cube (set by domain)", "domain units",
                                        "> domain_lo")] = DOMAIN_HI
    dt: Annotated[Float, setting("MPM time step of one substep (a frame is substeps x dt); refused above the stable "
                                 "step cfl dx / c", "s", "> 0, <= cfl dx / c", gt=0)] = 1.0 / 240.0
    substeps: Annotated[Int, setting("MPM substeps per frame (T)", ge=1)] = 20
    youngs_modulus: Annotated[Float, setting("Young's modulus E", "Pa", gt=0)] = 1.4e5
    poisson_ratio: Annotated[Float, setting("Poisson's ratio nu", gt=-1, lt=0.5)] = 0.2
    density: Annotated[Float, setting("material density rho (set by sampling.density)", "mass / domain unit^3",
                                      gt=0)] = 75.0
    drag: Annotated[Float, setting("velocity drag d; experiments set it with `drag`", "1/s",
                                   "0 <= drag dt <= 1")] = 0.9
    smoothing: Annotated[Float, setting("F smoothing s: the share of F kept from before each substep",
                                        ge=0, lt=1)] = 0.955
    smoothing_mode: Annotated[Literal["full", "isochoric"], setting(
        "full: the paper's blend (also smooths the volume); isochoric: the blend rescaled so det F follows the "
        "motion")] = "isochoric"
    control: Annotated[Literal["per_substep", "per_frame"], setting(
        "per_substep: one control dFc per particle per substep (the paper's code); per_frame: one per "
        "frame")] = "per_substep"
    control_in_F: Annotated[Bool, setting(
        "carry dFc in F as the authors' code does (otherwise it enters the stress only)")] = False
    learning_rate: Annotated[Float, setting(
        "step size: per-entry RMS of each normalised step (normalized_gd) or Adam's lr, at a one-unit cell with "
        "step_scales_with_dx", gt=0)] = 0.004  # history: docs/study/CHANGELOG.md
    step_scales_with_dx: Annotated[Bool, setting(
        "the step is learning_rate x dx (domain units): the same distance per frame at every grid "
        "resolution")] = True
    optimizer: Annotated[Literal["adam", "normalized_gd"], setting(
        "normalized_gd: the authors' normalised descent with line search; adam: the paper's text")] = "normalized_gd"
    line_search_iters: Annotated[Int, setting(
        "normalized_gd: halvings of the step tried before a step is undone", ge=1)] = 10
    sufficient_decrease: Annotated[Float, setting(
        "normalized_gd: Armijo constant c of the line search (a step must lower the objective by c alpha <g, d>; "
        "0: any decrease)", ge=0, lt=1)] = 0.0
    step_clip: Annotated[Float, setting(
        "normalized_gd: clamp of each entry of the normalised step, in multiples of its RMS; 0 = off", ge=0)] = 3.0
    step_per_volume: Annotated[Bool, setting(
        "normalized_gd: the step direction is the gradient per unit of particle volume (a shell-biased "
        "sampling's surface particles are driven as hard as its interior ones)")] = True  # history: docs/study/CHANGELOG.md
    step_volume_power: Annotated[Float, setting(
        "with step_per_volume: the exponent of the per-volume weight, g_p (V_max / V_p)^power (1: per unit volume; "
        "0: the plain step)", ge=0, le=1)] = 1.0
    step_rms: Annotated[Literal["particles", "volume"], setting(
        "what the normalised step's RMS is taken over: every particle once (particles) or each by its volume "
        "(volume: the same for every sampling of a body)")] = "particles"
    step_smoothing: Annotated[Literal["none", "grid"], setting(
        "grid: the weighted gradient replaced by its share on the MPM grid (P2G, then G2P) before the step is "
        "normalised; none: each particle's own")] = "none"
    step_volume: Annotated[Literal["full", "particle", "body"], setting(
        "what the step may do to the volume the stress sees: particle (each particle's step loses its change of "
        "volume), body (only the body's total change is removed), full (the authors' step)")] = "particle"  # history: docs/study/CHANGELOG.md
    step_volume_share: Annotated[Float, setting(
        "with step_volume particle: the share of each particle's change of volume removed from its step (1: all, "
        "0: the full step)", ge=0, le=1)] = 0.75
    grad_iters: Annotated[Int, setting(
        "optimiser iterations per frame (J); experiments set it with `grad_iters`", ge=1)] = 1
    adam_beta1: Annotated[Float, setting("Adam's first-moment decay", ge=0, lt=1)] = 0.9
    adam_beta2: Annotated[Float, setting("Adam's second-moment decay", ge=0, lt=1)] = 0.999
    adam_eps: Annotated[Float, setting("Adam's epsilon", gt=0)] = 1e-8
    mass_loss: Annotated[Literal["squared", "log", "sqrt", "log_bounded", "log_convex"], setting(
        "form of the grid-mass loss: squared difference, log difference, sqrt (Hellinger), log below the target "
        "and sqrt above, or log continued linearly where it turns concave (log_convex)")] = "log"
    log_mass_eps: Annotated[Float, setting("eps of the log and sqrt losses, in mean particle masses",
                                           "particle masses", gt=0)] = 0.1
    mass_loss_levels: Annotated[Int, setting(
        "levels of a grid-mass pyramid the loss is summed over; 1 = the grid alone", "",
        ">= 1, 2^(levels-1) divides grid_res", ge=1)] = 1
    mass_loss_blur: Annotated[Float, setting(
        "sigma of a Gaussian-blurred level of the mass loss, reaching material several cells from the target; "
        "0 = off", "cells", ge=0, le=16)] = 2.0  # history: docs/study/CHANGELOG.md
    mass_loss_blur_weight: Annotated[Float, setting("weight of the blurred level (the grid's own is 1)", ge=0)] = 1.0
    overfill_weight: Annotated[Float, setting(
        "weight of a packing term on nodes holding more than the target (or than overfill_ratio x density, where "
        "that is more); 1 with ratio 0.001: overfill weighed twice; 0 = off", ge=0)] = 1.0  # history: docs/study/CHANGELOG.md
    volume_law: Annotated[Literal["fixed_corotated", "barrier"], setting(
        "volume term of the elastic energy: fixed_corotated (the paper's) or barrier (grows without bound as "
        "det F -> 0)")] = "fixed_corotated"
    overfill_ratio: Annotated[Float, setting(
        "density ratio of the packing term's cap (0.001: the target's own node mass)", gt=0)] = 0.001
    warm_start: Annotated[Bool, setting("keep the control (and Adam's moments) from frame to frame")] = True
    volume_stiffness: Annotated[Float, setting(
        "K of a pressure against packing measured from the particles' density; 0 = off", "Pa", ge=0)] = 0.0
    volume_onset: Annotated[Float, setting("density ratio above which volume_stiffness acts", gt=0)] = 2.0
    min_volume_ratio: Annotated[Float, setting(
        "floor on det F under isochoric smoothing; 0 = off (the paper)", ge=0, lt=1)] = 0.25
    control_clip: Annotated[Float, setting("clamp of every dFc entry after each step; 0 = off", ge=0)] = 0.0
    cfl: Annotated[Float, setting("CFL number: dt above cfl dx / c (c the P-wave speed) is refused",
                                  gt=0, le=1)] = 0.5
    cfl_warn_fraction: Annotated[Float, setting("warn when dt is above this share of the stable step",
                                                gt=0, le=1)] = 0.8
    device: Annotated[Literal["auto", "cpu", "cuda"], setting(
        "where the solver runs (set by device)")] = "cpu"
    precision: Annotated[Literal["float32", "float64"], setting("floating-point type of the solver")] = "float32"
    threads: Annotated[Int | None, setting(
        "the solver's CPU threads (set by the rule's threads); None: Taichi's default")] = None

    def __post_init__(self) -> None:
        """The checks across fields (each field's own range is its declaration's)."""
        if not self.domain_hi > self.domain_lo:
            raise Refused("domain_hi", f"domain needs domain_hi > domain_lo, got {self.domain_lo}, {self.domain_hi}")
        if not 0.0 <= self.drag * self.dt <= 1.0:
            raise Refused("drag", f"drag must satisfy 0 <= drag * dt <= 1 (momentum factor 1 - dt*d in [0, 1]), "
                                  f"got drag={self.drag}, dt={self.dt}")
        if self.grid_res % (1 << (self.mass_loss_levels - 1)):
            raise Refused("mass_loss_levels", f"mass_loss_levels must be an int >= 1 whose blocks 2^(levels-1) "
                                              f"divide grid_res {self.grid_res}, got {self.mass_loss_levels!r}")
        dt_max = self.stable_dt
        if self.dt > dt_max:
            raise Refused("dt",
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
