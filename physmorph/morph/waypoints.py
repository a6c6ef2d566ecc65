"""Each frame's physics aimed at a waypoint along the transport plan (MorphConfig.waypoint_cells).

The grid's mass loss pulls only where a node's mass differs from the target's: material that has
to cross a region already at the target's density (into a letter's tip, a duck's head) sees no
pull, and the mid bodies stop with their heads hollow and their bays full (docs/study/log.md,
finding 253). The plasticity's transport plan says where each particle's mass belongs. The
waypoint target adds the plan's next step to the target the physics aims at:

    m*_I = max(0, m_target,I + sum_p w_Ip m_p (y_p) - sum_p w_Ip m_p (x_p)),
    y_p = x_p + min(1, s dx / |d_p - x_p|) (d_p - x_p)  where |d_p - x_p| > onset dx, else x_p,

x_p the particle at the frame's start, d_p its transport destination, s = waypoint_cells: the
residual m_target - m(x) is what the plain loss sees, and m(y) - m(x) is the mass flux of moving
every far particle s cells along its plan. Where every particle is within the onset of its
destination m* is the target itself. Not in the paper (its future work: topology-aware
correspondences).

The physics loss of a frame then aims at a field that changes from frame to frame, so the
momentum restart, the packing term's onset and the settle phase, which compare the physics loss
between frames, read it against the target itself: the end state's loss is evaluated again with
the target set back (``physics_loss_to_target``).

The push moves the material along the plan directly: at each frame's start every particle farther
than ``plan_push_onset`` cells from its destination is given the velocity that would carry it
``plan_push_speed`` (domain units) toward it over the frame,
outside the optimisation (no gradient passes through it). The waypoint target reaches the material
only through the control's one-frame rollout, which moves a particle's neighbours rather than the
particle, and carries nothing; the push does (docs/study/log.md, findings 264-265).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from physmorph.base.grid import Grid, splat_mass
from physmorph.mpm.state import ParticleState
from physmorph.plasticity.transport import destinations_in_grid_mass
from physmorph.settings.morph import MorphConfig

# the frame's scalar the restart reads where the waypoints are on (physmorph.records.runfile.SCALARS)
TO_TARGET = "physics_loss_to_target"


def waypoint_positions(x: np.ndarray,  # [N, 3] the particles at the frame's start
                       destination: np.ndarray,  # [N, 3] their transport destinations
                       step: float | np.ndarray,  # scalar or [N]
                       onset: float) -> np.ndarray:  # [N, 3]
    """y_p: each particle farther than ``onset`` from its destination moved ``step`` toward it
    (at most onto it); every other particle where it is (lengths in domain units)."""
    to = destination - x
    dist = np.linalg.norm(to, axis=1)
    share = np.where(dist > onset, np.minimum(1.0, step / np.maximum(dist, 1e-300)), 0.0)
    return x + share[:, None] * to


def waypoint_grid_mass(x: np.ndarray,  # [N, 3]
                       mass: np.ndarray,  # [N]
                       destination: np.ndarray,  # [N, 3]
                       target_mass: np.ndarray,  # [R, R, R] the target's grid mass, at the source's total mass
                       grid: Grid, step_cells: float, onset_cells: float) -> np.ndarray:  # [R, R, R]
    """m* = max(0, target + m(y) - m(x)) of the module docstring: the target plus the plan's
    next step of ``step_cells`` for every particle more than ``onset_cells`` from its destination."""
    y = waypoint_positions(x, destination, step_cells * grid.dx, onset_cells * grid.dx)
    moving = np.any(y != x, axis=1)
    if not moving.any():
        return np.asarray(target_mass, dtype=np.float64).copy()
    # only the moving particles contribute to the flux m(y) - m(x)
    flux = splat_mass(y[moving], mass[moving], grid) - splat_mass(x[moving], mass[moving], grid)
    return np.maximum(0.0, target_mass + flux)


def plan_push(x: np.ndarray,  # [N, 3] the particles at the frame's start
              destination: np.ndarray,  # [N, 3] their transport destinations
              length: float | np.ndarray,  # scalar or [N]
              onset: float, frame_time: float) -> np.ndarray:  # [N, 3]
    """MorphConfig.plan_push_speed: the velocity added to each particle more than ``onset`` from its
    destination that would carry it ``length`` toward it over the frame (at most onto it), zero for
    every other particle: (y_p - x_p) / frame_time with y_p its waypoint (lengths in domain units)."""
    return (waypoint_positions(x, destination, length, onset) - x) / frame_time


def outside_target(x: np.ndarray,  # [N, 3]
                   target_mass: np.ndarray,  # [R, R, R] the target's grid mass
                   grid: Grid) -> np.ndarray:  # [N] bool
    """Particles whose nearest grid node holds no target mass (the stray pull's outside test)."""
    node = np.clip(np.rint((x - np.asarray(grid.lo)) / grid.dx).astype(np.int64), 0, grid.res - 1)
    return np.asarray(target_mass)[node[:, 0], node[:, 1], node[:, 2]] <= 0.0


def plan_distance(x: np.ndarray,  # [N, 3]
                  mass: np.ndarray,  # [N]
                  destination: np.ndarray,  # [N, 3]
                  dx: float) -> float:
    """The mass-weighted mean distance of the particles to their transport destinations, in cells
    (the run file's plan_distance: how far the material is from where the plan sends it)."""
    return float(np.average(np.linalg.norm(x - destination, axis=1), weights=mass) / dx)


def plan_exists(cfg: MorphConfig) -> bool:
    """Whether a run has a transport plan (the full method with transport correspondences)."""
    return cfg.method == "full" and cfg.plasticity.correspondence == "transport"


def waypoints_on(cfg: MorphConfig) -> bool:
    """Whether a run aims its frames at waypoints (a plan and a step > 0)."""
    return cfg.waypoint_cells > 0 and plan_exists(cfg)


def physics_objective(cfg: MorphConfig) -> str:
    """The frame's scalar that compares the physics loss between frames: against the target itself."""
    return TO_TARGET if waypoints_on(cfg) else "physics_loss"


class FramePlan:
    """The transport plan over a run (method full, correspondence transport): each particle's
    destination, computed at first use (a function of the inputs alone, so a resumed run computes
    the same), and what the frames do with it: the push (MorphConfig.plan_push_speed), the waypoint
    target (MorphConfig.waypoint_cells) and the distance the run file records."""

    def __init__(self, cfg: MorphConfig, inputs):  # inputs: physmorph.morph.inputs.MorphInputs
        self.cfg, self.inputs = cfg, inputs
        self.exists = plan_exists(cfg)
        self.on = waypoints_on(cfg)  # the waypoint target
        self._destination = None

    def destinations(self) -> np.ndarray:  # [N, 3]
        if self._destination is None:
            inputs = self.inputs
            self._destination = destinations_in_grid_mass(inputs.parts.x, inputs.parts.mass, inputs.target.grid_mass,
                                                          inputs.target.grid, self.cfg.plasticity.transport_blur,
                                                          device=inputs.device,
                                                          projection=self.cfg.plasticity.transport_projection)
        return self._destination

    def pushed(self, st: ParticleState, share: float = 1.0) -> ParticleState:
        """The frame's start state with the plan's push added to its velocity (where plan_push_speed > 0),
        ``share`` of it: the settle phase's back-off (the step's share of mpm.step_size). A frame the
        settle gate undid starts again at rest from the same state; with the same push it would end
        where it did and be undone again however small the step, so the push backs off with it."""
        cfg = self.cfg
        if not (self.exists and cfg.plan_push_speed > 0 and share > 0):
            return st
        length = share * cfg.plan_push_speed
        if cfg.plan_push_outside != 1.0:
            target = self.inputs.target
            outside = outside_target(st.x, target.grid_mass, target.grid)
            length = np.where(outside, cfg.plan_push_outside * length, length)
        dv = plan_push(st.x, self.destinations(), length,
                       cfg.plan_push_onset * self.inputs.target.grid.dx, cfg.mpm.substeps * cfg.mpm.dt)
        return dataclasses.replace(st, v=st.v + dv)

    def aim(self, solver, st: ParticleState) -> None:
        """The frame's waypoint target on the solver, before its physics (where the waypoints are on)."""
        if self.on:
            solver.set_target_grid_mass(waypoint_grid_mass(st.x, st.mass, self.destinations(), self.inputs.target_mass,
                                                           self.inputs.target.grid, self.cfg.waypoint_cells,
                                                           self.cfg.destination_pull_onset))

    def loss_to_target(self, solver) -> float:
        """After the physics: the target set back on the solver and the end state's physics loss
        against it, what the frames compare (NaN where the waypoints are off)."""
        if not self.on:
            return float("nan")
        solver.set_target_grid_mass(self.inputs.target_mass)
        return solver.end_loss()

    def distance(self, st: ParticleState) -> float:
        """plan_distance of the state (NaN where the run has no plan)."""
        if not self.exists:
            return float("nan")
        return plan_distance(st.x, st.mass, self.destinations(), self.inputs.target.grid.dx)
