"""The configuration of one morph run (:class:`MorphConfig`): the method, frames and injection
gains, with the MPM, render, plasticity and surface sections. Kept apart from the loop
(physmorph.morph.loop, which imports Taichi and torch) so reading and checking settings stays light:
the workflow builds every experiment's MorphConfig when it parses its config.
"""

from __future__ import annotations

from dataclasses import asdict, field
from typing import Annotated, ClassVar, Literal

from physmorph.base.grid import CellLinks
from physmorph.settings.mpm import MPMConfig
from physmorph.settings.plasticity import PlasticityConfig
from physmorph.settings.render import RenderConfig
from physmorph.settings.base import Bool, Float, Int, setting, settings_dataclass
from physmorph.settings.surface import SurfaceMaskConfig

METHODS = ("physics_only", "f_inject", "full", "position_inject")


@settings_dataclass
class MorphConfig:
    """The frame loop of one run."""

    # always in a run's params (physmorph.settings.params.without_defaults), so its record names the method
    # (and, for control_decay, because its default changed since runs were first made)
    ALWAYS_IN_PARAMS: ClassVar[frozenset[str]] = frozenset({"method", "momentum_restart", "control_decay", "overfill_onset",
                                                              "stray_pull", "settle",
                                                              "plan_push_speed", "reabsorb_strays", "settle_objective",
                                                              "spray_links", "injection_calibration_every",
                                                              "settle_hold_below"})
    # the paper's method (sections 3-4)
    method: Annotated[Literal["physics_only", "f_inject", "full", "position_inject"], setting(
        "physics_only: mass loss alone; f_inject: + render gradient on F; full: + plasticity; position_inject: "
        "render gradient on positions (set by experiments.<name>.method)")] = "full"
    # relative gains: see calibrate_injection
    gamma: Annotated[Float, setting("gain of the render gradient injected on F, relative to the mass gradient",
                                    ge=0)] = 0.1
    gamma_x: Annotated[Float, setting("position_inject only: gain of the render gradient injected on positions",
                                      ge=0)] = 0.1

    # the run: its length, views, records and guards
    frames: Annotated[Int, setting("frames per run; experiments set it with `frames`", ge=1)] = 40
    cameras: Annotated[Int | None, setting("views the render loss uses (evenly spaced); null: all target.cameras",
                                           "", "<= target.cameras", ge=1)] = None
    save_every: Annotated[Int, setting("store x, F, Fp every this many frames (and the first and last)", "frames",
                                       ge=1)] = 5
    metric_all_particles: Annotated[Bool, setting(
        "alpha MSE from all particles (false: the masked subset)")] = True
    max_F_norm: Annotated[Float, setting("a run stops when an entry of F exceeds this (divergence)", gt=0)] = 50.0
    max_Fp_norm: Annotated[Float, setting("a run stops when an entry of Fp exceeds this", gt=0)] = 10.0
    # no optimisation and no plasticity in these frames: the alpha MSE curve shows how much of the
    # morph the rest state keeps
    release_frames: Annotated[Int, setting(
        "frames with the control off after the run (how much of the morph persists)", "frames", ge=0)] = 0
    progress: Annotated[Bool, setting("log a line per frame; changing it reruns nothing")] = True

    # the named departures from the paper, the frame loop's steering, and the restart's levers (docs/method.md)
    # "every_frame" costs one more backward pass per frame and keeps the injection gamma of the mass
    # gradient as the mass loss converges; "absolute" is eq. 3 in this project's loss units (the
    # F-vs-position comparison at equal gain, docs/study/log.md)
    injection_calibration: Annotated[Literal["first_frame", "every_frame", "absolute"], setting(
        "every_frame: gain re-measured each frame; first_frame: once; absolute: no calibration (eq. 3 as "
        "printed)")] = "every_frame"
    # held for a few frames the gain moves the runs by under a point of their gap, and those frames
    # skip the calibration's second adjoint (docs/study/log.md part 69). Not in the paper.
    injection_calibration_every: Annotated[Int, setting(
        "every_frame: frames between measurements of the injection gain, the last one kept in between "
        "(1: each frame)", "frames", ge=1)] = 5  # history: docs/study/CHANGELOG.md
    # the function-value restart of momentum methods (O'Donoghue & Candes 2015): the physics
    # carries momentum across frames, but each frame's control only sees its own frame, so a shape
    # that reaches its target at speed rings (docs/study/log.md, finding 73). Not in the paper.
    momentum_restart: Annotated[Literal["off", "mass_loss", "alpha_mse"], setting(
        "start the next frame at rest when the frame's physics loss (the mass loss, with the full method's stray "
        "pull) or alpha MSE rose; off: the paper's loop")] = "mass_loss"
    restart_keep: Annotated[Float, setting("share of the velocity a restart keeps", ge=0, le=1)] = 0.0
    # two_back: a frame that starts at rest after a restart and falls is not followed by another
    # restart merely for rebounding (near the target the restart otherwise fires every other
    # frame: docs/study/log.md finding 208). Not in the paper.
    restart_reference: Annotated[Literal["previous", "two_back"], setting(
        "what a frame's objective must rise above for a restart: the previous frame's (previous) or the one "
        "before it (two_back)")] = "previous"
    # the control is a stress offset: under the F smoothing a constant one keeps the body flowing
    restart_control_keep: Annotated[Float, setting("share of the carried control a restart keeps",
                                                   ge=0, le=1)] = 1.0
    control_decay: Annotated[Float, setting("share of the control each frame starts with (1: carried whole)",
                                            ge=0, le=1)] = 0.975  # history: docs/study/CHANGELOG.md
    # first_restart: the body has arrived and starts to cycle (docs/study/log.md finding 167), so a
    # body still on its way is not slowed by it (findings 177, 180). Not in the paper.
    overfill_onset: Annotated[Literal["start", "first_restart"], setting(
        "when mpm.overfill_weight's packing term starts: start, or first_restart (the frame after the objective "
        "first rose, the first momentum restart)")] = "first_restart"  # history: docs/study/CHANGELOG.md
    # physmorph.morph.settle; not in the paper
    settle: Annotated[Literal["off", "after_cycle", "after_first_rise"], setting(
        "the last phase: from the frame after the objective first rose (after_first_rise) or after the restart "
        "fired twice one frame apart (after_cycle) every frame starts at rest, and one whose settle_objective "
        "rises is undone (the body holds still); off: the restart alone")] = "after_first_rise"  # history: docs/study/CHANGELOG.md
    settle_backoff: Annotated[Float, setting("step multiplier after a frame the settle phase undid",
                                             gt=0, le=1)] = 0.5
    # a trust region over frames grows again where its step is accepted: with plan_push the push
    # backs off with the step (physmorph.morph.waypoints.FramePlan.pushed), and without regrowth a
    # body still on its way is frozen by its first undone frame (docs/study/log.md)
    settle_regrow: Annotated[Bool, setting(
        "after a frame the settle phase accepted, the step grows back by 1 / settle_backoff, up to mpm's "
        "step_size (false: it stays backed off)")] = False
    # once the gate has backed the step off this far, every frame it tried was undone in every run
    # measured: those frames' work is skipped (docs/study/log.md part 69)
    settle_hold_below: Annotated[Float, setting(
        "the settle phase: a frame whose step is under this share of mpm's step_size is not run but held, "
        "committed as an undone frame (the last accepted body, still); 0: every frame runs", ge=0, le=1)] = 0.0625
    settle_objective: Annotated[Literal["render", "alpha_mse", "physics", "physics_then_alpha"], setting(
        "what the settle phase judges a frame by: its alpha MSE (every view), its render loss, its physics "
        "loss, or (physics_then_alpha) its physics loss and its alpha MSE together (undone where both rose) "
        "until an accepted frame lowers the physics loss by less than settle_handover, its alpha MSE from then "
        "on; physics_only is gated on the physics loss only")] = "physics_then_alpha"  # history: docs/study/CHANGELOG.md
    # the images' gate holds a body still once its silhouettes match, which a push along the plan
    # reaches long before the body's thin parts are filled (docs/study/log.md)
    settle_handover: Annotated[Float, setting(
        "settle_objective physics_then_alpha: the share by which an accepted frame must lower the physics "
        "loss for the physics loss to go on judging", ge=0, lt=1)] = 0.02
    # The stray pull belongs to the Chamfer guidance, with the plasticity: stray_pull x (m_p /
    # (density dx^3)) |x_T,p - s_p|^2 / dx^2 in the physics loss, the anchor s_p taken at the frame's
    # start. The grid's mass loss has no direction for a region several cells outside the target,
    # and the plasticity cannot carry a region over (docs/study/log.md). Not in the paper.
    stray_pull: Annotated[Float, setting(
        "method full: weight of a pull on particles outside the target toward their nearest target surface point "
        "(a cell of material one cell out costs this; 0: off)", ge=0)] = 1.0  # history: docs/study/CHANGELOG.md
    stray_pull_onset: Annotated[Float, setting(
        "the stray pull acts on particles more than this far from the target's surface", "cells", ge=0)] = 1.0
    stray_pull_density: Annotated[Float, setting(
        "a particle is outside the target for the stray pull where the target's grid density at it (trilinear, in "
        "units of the material's) is at most this; 0: where its nearest grid node holds no target mass", ge=0,
        lt=1)] = 0.0
    # The destination pull: destination_pull x (m_p / (density dx^3)) |x_T,p - T_p|^2 / dx^2 for a
    # particle more than destination_pull_onset cells from T_p, its transport destination (the
    # plasticity's plan, fixed for the run), where the stray pull leaves it unanchored. The grid's loss
    # moves material a few cells at most, and the rest shape carries the plan's destinations only
    # through their Jacobian: a region that must travel through the body (into a letter's tip, a
    # head) is carried by neither (docs/study/log.md). Not in the paper.
    destination_pull: Annotated[Float, setting(
        "method full with correspondence transport: weight of a pull on each particle toward its transport "
        "destination (a cell of material one cell from it costs this; 0: off)", ge=0)] = 0.0
    destination_pull_onset: Annotated[Float, setting(
        "the destination pull and the waypoint target act on particles more than this far from their destination",
        "cells", ge=0)] = 2.0
    # Each frame's physics aimed at the target plus the plan's next step (physmorph.morph.waypoints):
    # the mass loss's residual does not pull material through a region already at the target's
    # density (docs/study/log.md). Not in the paper.
    waypoint_cells: Annotated[Float, setting(
        "method full with correspondence transport: each frame's physics aims at the target's grid mass plus the "
        "mass flux of moving every particle this far along its transport plan (0: at the target itself)", "cells",
        ge=0)] = 0.0
    # The same steps given to the material as velocity at each frame's start, outside the
    # optimisation: the control moves a particle's neighbours, not the particle, so neither the
    # waypoint target nor the destination pull carries a region through the body; the push does
    # (docs/study/log.md part 64). The speed in domain units, as the shapes are sized: the same push
    # moves a body by the same share of itself at every grid; the onset in cells of the grid the
    # plan is made on, whose destinations are about a cell precise (docs/study/log.md part 65).
    # Not in the paper (its future work: particle redistribution).
    plan_push_speed: Annotated[Float, setting(
        "method full with correspondence transport: at each frame's start every particle more than "
        "plan_push_onset from its transport destination is given the velocity that would carry it this far "
        "toward it over the frame (at most onto it; 0: off)", "domain units a frame", ge=0)] = 0.5  # history: docs/study/CHANGELOG.md
    plan_push_onset: Annotated[Float, setting(
        "the plan's push acts on particles more than this far from their transport destination", "cells",
        ge=0)] = 1.0
    # Material outside the target (a lump under a table's top) is what the push has to carry in; the
    # body inside already fills the target, where a faster push only stirs it (docs/study/log.md part 77).
    plan_push_outside: Annotated[Float, setting(
        "the plan's push for particles outside the target (their nearest grid node holds no target mass), "
        "as a multiple of plan_push_speed", "", ge=0)] = 1.0
    # Spray the control cannot move (a lone particle's stress moves it not at all) moved back into the
    # body between frames (physmorph.morph.reabsorb). Not in the paper: its adaptive particle
    # redistribution, the reabsorbing part.
    reabsorb_strays: Annotated[Bool, setting(
        "method full: after each frame, particles torn off the body and outside the target (the stray pull's test) "
        "join the body particle nearest their nearest target surface point, with its state")] = True  # history: docs/study/CHANGELOG.md
    spray_links: Annotated[CellLinks, setting(
        "reabsorb_strays: how the occupied grid cells link into pieces when telling torn-off spray from the body: "
        "through a shared face, edge or corner, or through a shared face only (a bead hanging on the body by an "
        "edge or a corner is then torn off)")] = "faces"  # history: docs/study/CHANGELOG.md

    # the sections
    mpm: Annotated[MPMConfig, setting("the solver (the mpm section)")] = field(default_factory=MPMConfig)
    render: Annotated[RenderConfig, setting("the renderer (the render section)")] = field(default_factory=RenderConfig)
    plasticity: Annotated[PlasticityConfig, setting("the plasticity (the plasticity section)")] = field(
        default_factory=PlasticityConfig)
    surface: Annotated[SurfaceMaskConfig, setting("the surface mask (the surface section)")] = field(
        default_factory=SurfaceMaskConfig)

    def to_dict(self) -> dict:
        return asdict(self)

    def rest_volume_setting(self) -> str | None:
        """plasticity.volume where the run has a plasticity (the full method), else None."""
        return self.plasticity.volume if self.method == "full" else None
