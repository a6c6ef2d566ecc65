"""Settings the code no longer has, each with the one value at which the shipped method always ran.

These were off by default, set by no profile and of no use in the study (docs/study/runs.csv
keeps the rows that tried them; docs/study/log.md says what each did). A run file or a generated
page made before they went records them; :func:`physmorph.records.provenance.differing_keys` counts such
a key as the shipped method's where it holds the value below, and as a difference otherwise (a
page made with one switched on ran a method this code cannot run). A config that sets one is
refused like any unknown key.

Keys are dotted as in physmorph.records.provenance.method_settings: MorphConfig's own fields bare, the
solver's under ``mpm.``, the plasticity's under ``plasticity.``.
"""

from __future__ import annotations

RETIRED_METHOD_SETTINGS: dict[str, object] = {
    # the solver (MPMConfig)
    "mpm.control": "per_substep",  # per_frame: one dFc a frame shared by its substeps
    "mpm.control_in_F": False,  # dFc also carried in F, as the authors' code does
    "mpm.warm_start": True,  # False: the control reset every frame
    "mpm.control_clip": 0.0,  # a clamp of every dFc entry after each Adam step
    "mpm.volume_stiffness": 0.0,  # a packing pressure measured from the particles' density
    "mpm.volume_onset": 2.0,  # ... above this density ratio
    "mpm.volume_law": "fixed_corotated",  # barrier: lam (J - 1 - ln J)
    "mpm.mass_loss_levels": 1,  # the mass loss over a pyramid of block sums
    "mpm.sufficient_decrease": 0.0,  # an Armijo constant of the line search
    "mpm.step_rms": "particles",  # volume: the step's RMS weighted by particle volume
    "mpm.step_smoothing": "none",  # grid: the step replaced by its share on the MPM grid
    "mpm.step_volume_power": 1.0,  # an exponent of the per-volume step weight
    # the frame loop (MorphConfig)
    "step_backoff": 1.0,  # the step's factor after a frame whose loss rose
    "step_growth": 1.0,  # ... after a frame whose loss fell
    "step_first": 1.0,  # a linear ramp of the step over the frames
    "step_last": 1.0,
    "control_decay_follows_step": False,  # the control's decay scaled with a backed-off step
    "volume_averaging": 0.0,  # the next frame's volume blended with the grid-averaged one
    "stray_pull_anchor": "nearest",  # transport / toward_transport anchors of the stray pull
    "strain_rate_cap": 0.0,  # a cap on a frame's strain through the next step
    # the plasticity (PlasticityConfig)
    "plasticity.jacobian": "paper",  # least_squares: a fitted displacement Jacobian
    "plasticity.update": "incremental",  # target_rest: relax toward the rest state on the target
    "plasticity.absorb_rate": 1.0,  # a share of the control moved into Fp at each absorbing update
}

# Settings added since some pages and run files were made, each with the value at which the method
# runs as it did before the setting existed: a record without the key counts as holding that value
# (physmorph.records.provenance.differing_keys), so adding a setting off by default marks no page as made
# with other settings.
ADDED_METHOD_SETTINGS: dict[str, object] = {
    "stray_pull_density": 0.0,  # the stray pull's outside test: the nearest grid node's target mass
    "plasticity.volume": "keep",  # the rest volume stayed the source's (target the default since 2026-12-01)
    "plasticity.volume_rate": 0.05,
    "mpm.volume_weight": 0.0,  # no volume term in the physics loss
    "destination_pull": 0.0,  # no pull toward the transport destinations
    "destination_pull_onset": 2.0,
    "reabsorb_strays": False,  # spray left where it tore off
    "injection_calibration_every": 1,  # the injection gain measured every frame
    "settle_hold_below": 0.0,  # every settling frame run, however small its step
    "spray_links": "corners",  # spray's pieces: cells linked through a face, an edge or a corner
    "waypoint_cells": 0.0,  # each frame's physics aims at the target itself
    "plan_push_speed": 0.0,  # no velocity along the transport plan
    "plan_push_onset": 1.0,
    "plan_push_outside": 1.0,  # the push as fast outside the target as inside
    "settle_regrow": False,  # the settle phase's step stays backed off
    "plasticity.transport_projection": "barycentric",  # each destination the mean of its plan row
    # read only by settle_objective physics_then_alpha, which did not exist before it: any value ran
    # as the shipped one does
    "settle_handover": 0.02,
    "mpm.frame_end": "stepped",  # each frame ended at the rollout of its stepped control
}
