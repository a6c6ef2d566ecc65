"""Typed configuration of the differentiable MPM solver (paper section 4, "Physics rollout").

Defaults are the paper's values (E = 1.4e5, nu = 0.2, rho = 75, dt = 1/240 s, T = 20, grid 64^3
over [-16, 16]^3, drag d = 0.9, smoothing s = 0.955) unless a field says otherwise.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import fields
from typing import Annotated, ClassVar, Literal

from physmorph.base.grid import BOUNDARY_CELLS, DOMAIN_HI, DOMAIN_LO
from physmorph.settings.base import Bool, Float, Int, Refused, setting, settings_dataclass


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


# MPMConfig.step_volume, in the order of the step kernels' volume_mode
STEP_VOLUME_MODES = ("full", "particle")
# Fields only the Python driver reads (the optimiser loop, load_state, the config checks): no
# kernel bakes them in, so a built solver takes new values without compiling again
# (MPMSolver.configure, solver_for). tests/mpm/test_mpm_solver.py checks no kernel reads them.
DRIVER_FIELDS = frozenset({"learning_rate", "step_scales_with_dx", "optimizer", "line_search_iters", "step_clip",
                           "step_per_volume", "step_volume", "step_volume_share", "grad_iters", "frame_end",
                           "log_mass_eps", "cfl", "cfl_warn_fraction", "volume_weight"})


@settings_dataclass(error=MPMConfigError)
class MPMConfig:
    """Solver configuration.

    mass_loss: "squared": L = sum_I (m_I - m*_I)^2 over all grid nodes I (plain squared
        difference of grid masses, kg^2). "log": L = sum_I (log(m_I + eps) - log(m*_I + eps))^2
        with eps = log_mass_eps * (mean particle mass); it weights thin/low-density regions more,
        but its pull on a node falls as 1/m, so mass packed into a few nodes is cheap.
    mass_loss_blur: sigma (in cells) of a Gaussian-blurred level added to the mass loss, 0 = off:
        mass_loss_blur_weight x sum_I (log((B m)_I + e) - log((B m*)_I + e))^2 in the log form (each
        form as on the grid), B the separable Gaussian blur of the grid, truncated at 3 sigma, its
        weights summing to 1, zero outside the grid. The grid's loss sees a particle's 27 nodes
        only: material several cells from any node the target fills feels no pull toward it, and
        a coarser grid would move only particles on a block's edge; the blur gives every
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
    volume_weight: w of a volume term added to the physics loss, 0 = off (the paper has none; its
        limits name a global volume penalty as future work): w u (V_T / V* - 1)^2 with V_T =
        sum_p V0_p det F_T,p the body's volume at the frame's end, V* = sum_p V0_p det Fp_p its rest
        volume and u the number of grid nodes the target fills (the squared form: the sum of their
        squared masses), so a body whose volume is off by a share pays what a target whose every
        node is off by that share would (physmorph.mpm.volume_term). The step's volume projection
        (step_volume) keeps most of each particle's own change of volume; this term acts on the
        whole body's.
    overfill_ratio: the density ratio of that cap (the sampled shapes at rest reach ~2x their
        density at the 99th percentile, on their surface shell; 0.001: the target's own mass).
    cfl: the solver refuses dt > cfl * dx / c with c = sqrt((lambda + 2 mu) / rho) the
        P-wave speed, and warns (CFLWarning) above cfl_warn_fraction of that step.
    optimizer: "adam" (per-entry normalised steps, moments kept across frames)
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
    step_clip: normalized_gd only: if > 0, each entry of the normalised step g / rms(g) is clamped
        to [-step_clip, step_clip], so no particle's control moves more than step_clip x alpha per
        iteration (a gradient concentrated on a few particles otherwise moves them by many alpha).
    step_per_volume: normalized_gd only: the step direction is the gradient per unit of particle
        volume, g_p V_max / V_p, normalised by its RMS (and clipped by step_clip). dL/dFc_p carries
        the particle's volume (its stress enters P2G times V_p), so a plain normalised step drives
        a shell-biased sampling's interior particles (PPC 1) harder than its surface ones: 8x at
        PPC 2, 125x at the paper's PPC 5, where 99 % of the particles are in the surface shell
        (docs/study/log.md finding 131). False: g / rms(g), the authors' step (until 2026-11-26).
    step_volume: normalized_gd only: what the step may do to the volume the stress sees (the control
        enters the stress as F + dFc, A = F + dFc at the frame's start, n = A^-T). "particle": each
        particle's step direction d loses its first-order change of det A, d - (<d, n> / <n, n>) n,
        so the control shapes each particle and compresses none. The target's mass is rescaled to
        the source's, so a matched shape has the source's volume. "full": the authors' step.
        Measured in docs/study/log.md findings 156-158: "particle" lifts mid's runs and, removing
        all of each particle's change, costs the default profile's far and letter morphs. The
        default: "particle" with a share 0.75.
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
    min_volume_ratio: a floor J_min on det F (0.25 since 2026-11-24; 0 = off, the paper has
        none; it acts under isochoric smoothing only, where the rescaled blend takes det F' =
        max(det F_new, J_min); the paper's blend has no det F to hold). The fixed-corotated stress
        stays finite as det F -> 0, so under a strong control a particle can be crushed to a
        singular F, whose smoothed blend the rescale then blows up (docs/study/log.md finding 76).
        The authors' code bounds det F in compression too (a trust region on C).
    """

    # Fields whose default changed after runs were made with the old one: always in a run's params
    # (physmorph.settings.params.without_defaults), so those runs rerun (workflow/schemas/first_defaults.json).
    # step_scales_with_dx: a new field that changes, at its default, every run whose dx is not 1.
    ALWAYS_IN_PARAMS: ClassVar[frozenset[str]] = frozenset({"learning_rate", "smoothing_mode", "min_volume_ratio",
                                                             "step_scales_with_dx", "step_per_volume",
                                                             "step_volume", "step_volume_share",
                                                             "overfill_weight", "overfill_ratio", "mass_loss_blur",
                                                             "volume_weight"})

    # the run: its size and hardware (a profile or the workflow sets them)
    grid_res: Annotated[Int, setting("MPM grid cells per axis (set by sampling.grid_res)", "cells",
                                     ge=2 * BOUNDARY_CELLS + 2)] = 64
    domain_lo: Annotated[Float, setting("lower corner of the simulation cube (set by domain)", "domain units")] = DOMAIN_LO
    domain_hi: Annotated[Float, setting("upper corner of the simulation cube (set by domain)", "domain units",
                                        "> domain_lo")] = DOMAIN_HI
    device: Annotated[Literal["auto", "cpu", "cuda"], setting(
        "where the solver runs (set by device)")] = "cpu"
    precision: Annotated[Literal["float32", "float64"], setting("floating-point type of the solver")] = "float32"
    threads: Annotated[Int | None, setting(
        "the solver's CPU threads (set by the rule's threads); None: Taichi's default")] = None

    # the paper's physics (section 4), with the stable-step check
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
    cfl: Annotated[Float, setting("CFL number: dt above cfl dx / c (c the P-wave speed) is refused",
                                  gt=0, le=1)] = 0.5
    cfl_warn_fraction: Annotated[Float, setting("warn when dt is above this share of the stable step",
                                                gt=0, le=1)] = 0.8

    # the optimiser of the control
    optimizer: Annotated[Literal["adam", "normalized_gd"], setting(
        "normalized_gd: the authors' normalised descent with line search; adam: the paper's text")] = "normalized_gd"
    learning_rate: Annotated[Float, setting(
        "step size: per-entry RMS of each normalised step (normalized_gd) or Adam's lr, at a one-unit cell with "
        "step_scales_with_dx", gt=0)] = 0.004  # history: docs/study/CHANGELOG.md
    line_search_iters: Annotated[Int, setting(
        "normalized_gd: halvings of the step tried before a step is undone", ge=1)] = 10
    grad_iters: Annotated[Int, setting(
        "optimiser iterations per frame (J); experiments set it with `grad_iters`", ge=1)] = 1
    frame_end: Annotated[Literal["stepped", "last_forward"], setting(
        "the state a frame ends in: stepped, the rollout of the frame's updated control (the line search's "
        "accepted trial, Adam's last forward); last_forward, the end of the rollout its last gradient was "
        "taken on, one forward fewer (Algorithm 1 as printed: the step acts from the next frame)")] = "stepped"
    adam_beta1: Annotated[Float, setting("Adam's first-moment decay", ge=0, lt=1)] = 0.9
    adam_beta2: Annotated[Float, setting("Adam's second-moment decay", ge=0, lt=1)] = 0.999
    adam_eps: Annotated[Float, setting("Adam's epsilon", gt=0)] = 1e-8

    # the named departures from the paper (docs/method.md gives each one's measured effect and the paper's value)
    smoothing_mode: Annotated[Literal["full", "isochoric"], setting(
        "full: the paper's blend (also smooths the volume); isochoric: the blend rescaled so det F follows the "
        "motion")] = "isochoric"
    min_volume_ratio: Annotated[Float, setting(
        "floor on det F under isochoric smoothing; 0 = off (the paper)", ge=0, lt=1)] = 0.25
    step_scales_with_dx: Annotated[Bool, setting(
        "the step is learning_rate x dx (domain units): the same distance per frame at every grid "
        "resolution")] = True
    step_clip: Annotated[Float, setting(
        "normalized_gd: clamp of each entry of the normalised step, in multiples of its RMS; 0 = off", ge=0)] = 3.0
    step_per_volume: Annotated[Bool, setting(
        "normalized_gd: the step direction is the gradient per unit of particle volume (a shell-biased "
        "sampling's surface particles are driven as hard as its interior ones)")] = True  # history: docs/study/CHANGELOG.md
    step_volume: Annotated[Literal["full", "particle"], setting(
        "what the step may do to the volume the stress sees: particle (each particle's step loses a share of its "
        "change of volume) or full (the authors' step)")] = "particle"  # history: docs/study/CHANGELOG.md
    step_volume_share: Annotated[Float, setting(
        "with step_volume particle: the share of each particle's change of volume removed from its step (1: all, "
        "0: the full step)", ge=0, le=1)] = 0.75
    mass_loss: Annotated[Literal["squared", "log"], setting(
        "form of the grid-mass loss: squared difference (the paper's) or log difference")] = "log"
    log_mass_eps: Annotated[Float, setting("eps of the log loss, in mean particle masses",
                                           "particle masses", gt=0)] = 0.1
    mass_loss_blur: Annotated[Float, setting(
        "sigma of a Gaussian-blurred level of the mass loss, reaching material several cells from the target; "
        "0 = off", "cells", ge=0, le=16)] = 2.0  # history: docs/study/CHANGELOG.md
    mass_loss_blur_weight: Annotated[Float, setting("weight of the blurred level (the grid's own is 1)", ge=0)] = 1.0
    overfill_weight: Annotated[Float, setting(
        "weight of a packing term on nodes holding more than the target (or than overfill_ratio x density, where "
        "that is more); 1 with ratio 0.001: overfill weighed twice; 0 = off", ge=0)] = 1.0  # history: docs/study/CHANGELOG.md
    overfill_ratio: Annotated[Float, setting(
        "density ratio of the packing term's cap (0.001: the target's own node mass)", gt=0)] = 0.001
    volume_weight: Annotated[Float, setting(
        "weight of a volume term on the body's volume against its rest volume, per node the target fills; "
        "0 = off (the paper)", ge=0)] = 30.0  # history: docs/study/CHANGELOG.md

    def __post_init__(self) -> None:
        """The checks across fields (each field's own range is its declaration's)."""
        if not self.domain_hi > self.domain_lo:
            raise Refused("domain_hi", f"domain needs domain_hi > domain_lo, got {self.domain_lo}, {self.domain_hi}")
        if not 0.0 <= self.drag * self.dt <= 1.0:
            raise Refused("drag", f"drag must satisfy 0 <= drag * dt <= 1 (momentum factor 1 - dt*d in [0, 1]), "
                                  f"got drag={self.drag}, dt={self.dt}")
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
        """One control dFc per particle per substep (the paper code's choice; Adam or the normalised
        step moves each one)."""
        return self.substeps
