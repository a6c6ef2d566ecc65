"""The morph loop's steering rules, each a small named policy over the frames (physmorph.morph.loop).

MomentumRestart: a frame whose objective rose hands the next frame its state at rest (restart_keep
of v and C) and, optionally, a scaled control (MorphConfig.momentum_restart, restart_reference,
restart_keep, restart_control_keep). StepSchedule: the optimiser's step per frame, mpm's step
backed off after each frame the settle phase undid (settle_backoff) and, with settle_regrow, grown
back after each it accepted.
ControlDecay: dFc <- decay dFc at each frame's start (control_decay).
OverfillOnset: the packing term waits for the objective's first rise (overfill_onset).
StrayPull: anchors for particles that stray off the target (stray_pull, the full method's), and
for those far from their transport destination (destination_pull).
"""

from __future__ import annotations

import numpy as np

from physmorph.settings.morph import MorphConfig
from physmorph.morph.waypoints import outside_target, physics_objective, plan_exists
from physmorph.mpm.state import ParticleState


class MomentumRestart:
    """Whether the objective rose over a frame, and whether the momentum restarts after it."""

    def __init__(self, cfg: MorphConfig, previous: float = float("nan"), before_previous: float = float("nan")):
        # the objective whose rise restarts the momentum, and starts the packing term (the mass loss
        # where the restart is off, so the onset does not depend on it)
        # (against the target itself where the frames aim at waypoints: physmorph.morph.waypoints)
        physics = physics_objective(cfg)
        self.on = {"mass_loss": physics, "alpha_mse": "alpha_mse"}.get(cfg.momentum_restart)
        self.rise_on = self.on or physics
        self.two_back = cfg.restart_reference == "two_back"
        self.keep, self.control_keep = cfg.restart_keep, cfg.restart_control_keep
        self.previous, self.before_previous = previous, before_previous

    def observe(self, now: float) -> tuple[bool, bool]:
        """(the objective rose over this frame, the momentum restarts): a restart is judged
        against the previous frame's level, or two frames back (restart_reference)."""
        rose = bool(np.isfinite(self.previous) and now > self.previous)
        reference = self.before_previous if self.two_back and np.isfinite(self.before_previous) else self.previous
        restart = bool(np.isfinite(reference) and now > reference)
        self.before_previous, self.previous = self.previous, now
        return rose, restart

    def at_rest(self, st: ParticleState) -> ParticleState:
        """The state handed on after a restart (or in the settle phase): restart_keep of v and C."""
        return ParticleState(x=st.x, v=self.keep * st.v, F=st.F, C=self.keep * st.C, Fp=st.Fp,
                             mass=st.mass, volume=st.volume)


class StepSchedule:
    """The optimiser's step from frame to frame (``step``: the one the next frame takes): mpm's
    step, multiplied by settle_backoff after each frame the settle phase undid."""

    def __init__(self, step: float):
        self.step = step

    def back_off(self, factor: float) -> None:
        self.step *= factor

    def regrow(self, factor: float, most: float) -> None:
        """The step after an accepted frame (MorphConfig.settle_regrow): divided by ``factor``, at most ``most``."""
        self.step = min(most, self.step / factor)


class ControlDecay:
    """dFc leaks toward zero at each frame's start (MorphConfig.control_decay)."""

    def __init__(self, cfg: MorphConfig):
        self.decay = cfg.control_decay

    def apply(self, solver) -> None:
        if self.decay < 1.0:
            # 1 - the leak: decay itself from 0.5 up (Sterbenz), and below it rounded as it always was
            solver.scale_control(1.0 - (1.0 - self.decay))


class OverfillOnset:
    """The packing term (MPMConfig.overfill_weight) from the frame after the objective first rose
    (overfill_onset "first_restart"), or from the start."""

    def __init__(self, cfg: MorphConfig):
        self.waits = cfg.overfill_onset == "first_restart"
        self.weight = cfg.mpm.overfill_weight

    def initial_weight(self) -> float:
        return 0.0 if self.waits else self.weight

    def begin(self, solver, weight: float) -> None:
        """The weight a run starts or resumes with (a waiting term: 0 until its onset)."""
        if self.waits:
            solver.set_overfill_weight(weight)

    def after_frame(self, solver, objective_rose: bool) -> bool:
        """Switch the term on after the first rise; True when it did so now."""
        if objective_rose and solver.overfill_weight != self.weight:
            solver.set_overfill_weight(self.weight)
            return True
        return False


class StrayPull:
    """The stray and destination pulls' anchors on the solver's loss (component C with the
    plasticity: the full method's): see stray_pull_anchors and destination_pull_anchors."""

    def __init__(self, cfg: MorphConfig):
        self.cfg = cfg
        self.to_destination = cfg.destination_pull > 0 and plan_exists(cfg)
        self.on = (cfg.stray_pull > 0 and cfg.method == "full") or self.to_destination

    def anchor(self, solver, st: ParticleState, nearest_d, nearest_i, target,
               destination: np.ndarray | None = None) -> None:  # destination: [N, 3]
        anchors, weight = stray_pull_anchors(st.x, st.mass, nearest_d, nearest_i, target, self.cfg)
        if self.to_destination:
            to, w_to = destination_pull_anchors(st.x, st.mass, destination, target.grid, self.cfg)
            take = (weight == 0.0) & (w_to > 0.0)  # a stray keeps its own anchor
            anchors, weight = np.where(take[:, None], to, anchors), np.where(take, w_to, weight)
        solver.set_position_anchors(anchors, weight)


def destination_pull_anchors(x: np.ndarray,  # [N, 3]
                             mass: np.ndarray,  # [N]
                             destination: np.ndarray,  # [N, 3] each particle's transport destination
                             grid, cfg: MorphConfig) -> tuple[np.ndarray, np.ndarray]:  # [N, 3], [N]
    """The destination pull's anchors and weights (MorphConfig.destination_pull): a particle more
    than destination_pull_onset cells from its destination T_p gets the anchor T_p and the weight
    destination_pull m_p / (density dx^3) / dx^2 (the solver adds w_p |x_T,p - T_p|^2); every
    other particle weight 0."""
    cell_mass = cfg.mpm.density * grid.dx ** 3
    far = np.linalg.norm(x - destination, axis=1) > cfg.destination_pull_onset * grid.dx
    weight = np.where(far, cfg.destination_pull * mass / cell_mass / grid.dx ** 2, 0.0)
    return np.asarray(destination, dtype=np.float64), weight


def stray_pull_anchors(x: np.ndarray,  # [N, 3]
                       mass: np.ndarray,  # [N]
                       nearest_d: np.ndarray,  # [N] distance to the nearest target surface point
                       nearest_i: np.ndarray,  # [N] its index in target.surface_points
                       target, cfg: MorphConfig) -> tuple[np.ndarray, np.ndarray]:  # [N, 3], [N]
    """The stray pull's anchors and weights (MorphConfig.stray_pull): a particle outside the target
    (its nearest grid node holds no target mass, or with stray_pull_density > 0 the target's grid
    density interpolated at it is at most that share of the material's: the target's splat reaches
    about a cell beyond its surface, where the node test sees no particle as outside) and more than
    stray_pull_onset cells from the target's surface gets the anchor s_p, its nearest surface point,
    and the weight stray_pull m_p / (density dx^3) / dx^2 (the solver adds w_p |x_T,p - s_p|^2);
    every other particle weight 0."""
    grid = target.grid
    cell_mass = cfg.mpm.density * grid.dx ** 3
    if cfg.stray_pull_density > 0:
        from scipy.ndimage import map_coordinates

        at = map_coordinates(np.asarray(target.grid_mass, dtype=np.float64) / cell_mass,
                             ((x - np.asarray(grid.lo)) / grid.dx).T, order=1, mode="constant", cval=0.0)
        outside = at <= cfg.stray_pull_density
    else:
        outside = outside_target(x, target.grid_mass, grid)
    stray = outside & (nearest_d > cfg.stray_pull_onset * grid.dx)
    weight = np.where(stray, cfg.stray_pull * mass / cell_mass / grid.dx ** 2, 0.0)
    return np.asarray(target.surface_points)[nearest_i], weight
