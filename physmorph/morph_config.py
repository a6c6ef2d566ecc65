"""The configuration of one morph run (:class:`MorphConfig`): the method, frames and injection
gains, with the MPM, render, plasticity and surface sections. Kept apart from the loop
(physmorph.morph, which imports Taichi and torch) so reading and checking settings stays light:
the workflow builds every experiment's MorphConfig when it parses its config.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import ClassVar, Literal

from physmorph.mpm.config import MPMConfig
from physmorph.plasticity import PlasticityConfig
from physmorph.render.config import RenderConfig
from physmorph.surface import SurfaceMaskConfig

METHODS = ("physics_only", "f_inject", "full", "position_inject")


@dataclass(frozen=True)
class MorphConfig:
    # always in a run's params (physmorph.config.without_defaults), so its record names the method
    # (and, for control_decay, because its default changed since runs were first made)
    ALWAYS_IN_PARAMS: ClassVar[frozenset[str]] = frozenset({"method", "momentum_restart", "control_decay", "overfill_onset",
                                                              "stray_pull", "settle"})
    method: Literal["physics_only", "f_inject", "full", "position_inject"] = "full"
    frames: int = 40
    gamma: float = 0.1  # render-F gain, relative (see calibrate_injection)
    gamma_x: float = 0.1  # render-x gain (position_inject only), relative
    # "first_frame": c = gamma |grad mass| / |grad inject| measured once (see calibrate_injection);
    # "every_frame": measured again each frame, so the injection stays gamma of the mass
    # gradient as the mass loss converges (one more backward pass per frame);
    # "absolute": no calibration, c = gamma (gamma_x): the paper's eq. 3 as printed, in this
    # project's loss units (the F-vs-position comparison at equal gain, docs/study/log.md)
    injection_calibration: Literal["first_frame", "every_frame", "absolute"] = "every_frame"
    cameras: int | None = None  # render-loss views, evenly spaced on the ring (None: all)
    save_every: int = 5  # store x, F, Fp every this many frames (and the first and last)
    metric_all_particles: bool = True  # alpha MSE from all particles (else the masked subset)
    max_F_norm: float = 50.0  # divergence bound on |F|_max entries
    max_Fp_norm: float = 10.0
    # after the last frame, this many frames with the control off (no optimisation, no
    # plasticity): the alpha MSE curve shows how much of the morph the rest state keeps
    release_frames: int = 0
    progress: bool = True
    # Between frames, when the frame's objective rose (mass_loss: the physics loss at the frame's
    # end; alpha_mse: the rendered alpha MSE), keep only restart_keep of every particle's velocity
    # (v and the APIC C): the function-value restart of momentum methods (O'Donoghue & Candes
    # 2015). The physics carries momentum across frames, but each frame's control only sees its
    # own frame, so a shape that reaches its target at speed rings (docs/study/log.md, finding 73).
    # Not in the paper; "off" is the paper's loop.
    momentum_restart: Literal["off", "mass_loss", "alpha_mse"] = "mass_loss"
    restart_keep: float = 0.0
    # What a frame's objective must rise above for a restart: "previous", the frame before's;
    # "two_back", the one before that, so a frame that starts at rest after a restart and falls
    # is not followed by another restart merely for rebounding (near the target the restart
    # otherwise fires every other frame: docs/study/log.md finding 208). The packing term's onset
    # keeps the previous frame's comparison. Not in the paper.
    restart_reference: Literal["previous", "two_back"] = "previous"
    # settle: "after_cycle": once the restart has fired on two frames one apart (the period-two
    # cycle near the target), every later frame starts at rest, and a frame whose objective (the
    # render loss where the method renders, else the physics loss) ends above the last accepted
    # frame's is undone: the body holds still for that frame, and the next frame's step is
    # multiplied by settle_backoff (physmorph.settle). "off": the restart alone. Not in the paper.
    settle: Literal["off", "after_cycle", "after_first_rise"] = "after_first_rise"  # history: docs/study/CHANGELOG.md
    settle_backoff: float = 0.5
    # what the gate judges: "render", the frame's render loss; "alpha_mse", the alpha MSE against
    # the target's images (every view, every particle: the silhouette the tables report); both
    # only where the method renders (physics_only is never gated); "physics", the physics loss
    # (the mass loss, with the full method's stray pull), for every method
    settle_objective: Literal["render", "alpha_mse", "physics"] = "alpha_mse"
    # The step adapts to the run (the "bold driver" rule of Vogl et al. 1988): after a frame whose
    # mass loss rose, the next frame's normalised step (mpm.learning_rate at most) is multiplied
    # by step_backoff; after one whose loss fell it grows by step_growth, back up to
    # mpm.learning_rate. A run that descends keeps mpm.learning_rate throughout. 1.0 and 1.0: a
    # fixed step (the paper's). Not in the paper.
    step_backoff: float = 1.0
    step_growth: float = 1.0
    # A step that follows the run's course: frame k's step is mpm.learning_rate times
    # step_first at the first frame and step_last at the last, linear between (the bold driver's
    # factor on top). 1.0 and 1.0: the same step every frame (the paper's). Not in the paper.
    step_first: float = 1.0
    step_last: float = 1.0
    # restart_control_keep: a restart also scales the carried control dFc by this (the control is
    # a stress offset; under the F smoothing a constant one keeps the body flowing; 1 = carried
    # whole). control_decay: every frame starts with dFc scaled by this (a leaky integrator; 1 =
    # the control is carried whole, warm_start). Neither is in the paper.
    restart_control_keep: float = 1.0
    control_decay: float = 0.975  # history: docs/study/CHANGELOG.md
    # The leak follows the bold driver's step: a frame starts with 1 - (1 - control_decay) x
    # (step / mpm's step) of the control, so as the step backs off the control leaks less and is
    # held rather than lost (docs/study/log.md finding 170: the body still flows under it). Not in
    # the paper; off: the leak is 1 - control_decay at every frame.
    control_decay_follows_step: bool = False
    # Between frames, move this share of each particle's volume ratio det F to its grid average
    # (physmorph.grid.grid_average; F rescaled by (J' / J)^(1/3)): the spread of det F below the
    # cell, which the grid's mass loss cannot see, is taken out of the state. 0 = off. Not in the
    # paper; measured in docs/study/log.md part 34 (it narrows the spread, not the slide).
    volume_averaging: float = 0.0
    # When mpm.overfill_weight's packing term starts to act: "start" from the first frame,
    # "first_restart" from the frame after the run's objective first rose (the momentum restart's
    # signal; the mass loss where the restart is off): the body has arrived and starts to cycle
    # (docs/study/log.md finding 167), so a body still on its way is not slowed by it (findings
    # 177, 180). Not in the paper.
    overfill_onset: Literal["start", "first_restart"] = "first_restart"  # history: docs/study/CHANGELOG.md
    # The stray pull (method full: it belongs to the Chamfer guidance, with the plasticity): a
    # particle outside the target (its grid node holds no target mass) and more than
    # stray_pull_onset cells from the target's surface is pulled toward its nearest surface
    # point by stray_pull x (m_p / (density dx^3)) |x_T,p - s_p|^2 / dx^2 in the physics loss (the
    # anchor s_p taken at the frame's start): a cell of material one cell out costs stray_pull. The
    # grid's mass loss has no direction for a region several cells outside the target, and the
    # plasticity cannot carry a region over (docs/study/log.md). 0 = off. Not in the paper.
    stray_pull: float = 1.0  # history: docs/study/CHANGELOG.md
    stray_pull_onset: float = 1.0
    # Where the stray pull draws a stray particle: "nearest", its nearest target surface point;
    # "transport", its optimal-transport destination in the target's mass (the plasticity's
    # correspondence, physmorph.transport: every destination region receives its own mass, so
    # material from a part the target lacks is sent where the target lacks material, not piled
    # at the nearest stretch of surface); "toward_transport", the point along the way to that
    # destination as far from the particle as its nearest surface point (the nearest anchor's
    # pull, the transport's direction: a far destination's pull would take the normalised
    # step's scale from the rest of the body). Not in the paper.
    stray_pull_anchor: Literal["nearest", "transport", "toward_transport"] = "nearest"
    # A step that follows the body's strain rate: after a frame whose 99th-percentile strain
    # |F_T F_0^-1 - I| (the deformation over the frame, physmorph.frame_measures.frame_strain)
    # exceeded strain_rate_cap, the next frame's step is scaled by cap / strain; after one under
    # it, it grows back by the same ratio, up to mpm.learning_rate (and the bold driver's step). A
    # distant source's body that is strained faster than the cap is slowed where a body that
    # only moves keeps the whole step. Measured, it does not: at twice the step it takes mid's
    # cow -> bunny lower (docs/study/log.md finding 197). 0 = off. Not in the paper.
    strain_rate_cap: float = 0.0
    mpm: MPMConfig = field(default_factory=MPMConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    plasticity: PlasticityConfig = field(default_factory=PlasticityConfig)
    surface: SurfaceMaskConfig = field(default_factory=SurfaceMaskConfig)

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {self.method!r}")
        if self.injection_calibration not in ("first_frame", "every_frame", "absolute"):
            raise ValueError("injection_calibration must be first_frame, every_frame or absolute, "
                             f"got {self.injection_calibration!r}")
        if self.frames < 1:
            raise ValueError(f"frames must be >= 1, got {self.frames}")
        if self.momentum_restart not in ("off", "mass_loss", "alpha_mse"):
            raise ValueError(f"momentum_restart must be off, mass_loss or alpha_mse, got {self.momentum_restart!r}")
        if not 0.0 <= self.restart_keep <= 1.0:
            raise ValueError(f"restart_keep must be in [0, 1], got {self.restart_keep}")
        if self.settle not in ("off", "after_cycle", "after_first_rise"):
            raise ValueError(f"settle must be off, after_cycle or after_first_rise, got {self.settle!r}")
        if self.settle_objective not in ("render", "alpha_mse", "physics"):
            raise ValueError(f"settle_objective must be render, alpha_mse or physics, got {self.settle_objective!r}")
        if not 0.0 < self.settle_backoff <= 1.0:
            raise ValueError(f"settle_backoff must be in (0, 1], got {self.settle_backoff}")
        if self.restart_reference not in ("previous", "two_back"):
            raise ValueError(f"restart_reference must be previous or two_back, got {self.restart_reference!r}")
        if not 0.0 < self.step_backoff <= 1.0:
            raise ValueError(f"step_backoff must be in (0, 1], got {self.step_backoff}")
        if not self.step_growth >= 1.0:
            raise ValueError(f"step_growth must be >= 1, got {self.step_growth}")
        for key in ("step_first", "step_last"):
            if not getattr(self, key) > 0.0:
                raise ValueError(f"{key} must be > 0, got {getattr(self, key)}")
        if not 0.0 <= self.restart_control_keep <= 1.0:
            raise ValueError(f"restart_control_keep must be in [0, 1], got {self.restart_control_keep}")
        if not 0.0 <= self.control_decay <= 1.0:
            raise ValueError(f"control_decay must be in [0, 1], got {self.control_decay}")
        if not 0.0 <= self.volume_averaging <= 1.0:
            raise ValueError(f"volume_averaging must be in [0, 1], got {self.volume_averaging}")
        if self.overfill_onset not in ("start", "first_restart"):
            raise ValueError(f"overfill_onset must be start or first_restart, got {self.overfill_onset!r}")
        if not (math.isfinite(self.stray_pull) and self.stray_pull >= 0.0):
            raise ValueError(f"stray_pull must be finite and >= 0, got {self.stray_pull}")
        if not (math.isfinite(self.stray_pull_onset) and self.stray_pull_onset >= 0.0):
            raise ValueError(f"stray_pull_onset must be finite and >= 0 cells, got {self.stray_pull_onset}")
        if self.stray_pull_anchor not in ("nearest", "transport", "toward_transport"):
            raise ValueError(f"stray_pull_anchor must be nearest, transport or toward_transport, got {self.stray_pull_anchor!r}")
        if not (math.isfinite(self.strain_rate_cap) and self.strain_rate_cap >= 0.0):
            raise ValueError(f"strain_rate_cap must be finite and >= 0 (0 = off), got {self.strain_rate_cap}")
        if self.release_frames < 0:
            raise ValueError(f"release_frames must be >= 0, got {self.release_frames}")

    def step_multiplier(self, frame: int) -> float:
        """The step schedule's factor at ``frame`` (1..frames): step_first to step_last, linear."""
        if self.frames == 1:
            return float(self.step_first)
        t = (frame - 1) / (self.frames - 1)
        return float(self.step_first + t * (self.step_last - self.step_first))

    def to_dict(self) -> dict:
        return asdict(self)
