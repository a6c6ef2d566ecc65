"""The render injection's gain (paper section 3.3, eq. 3): gamma relative to the mass gradient, and
the morph loop's choice of when to measure it (MorphConfig.injection_calibration)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from physmorph.morph.frame_state import FrameState
from physmorph.mpm.solver import MPMSolver
from physmorph.settings.morph import MorphConfig


@dataclass(frozen=True)
class InjectionCalibration:
    """The gain c and the norms of the two dFc gradients it was measured from (one rollout, one
    state); the gradients themselves stay in the solver (MPMSolver.calibration_gradients)."""

    scale: float
    mass_gradient_norm: float  # |d(mass loss)/d(dFc)|
    injected_gradient_norm: float  # |d<g, final state>/d(dFc)| of the unscaled adjoint


def calibrate_injection(solver: MPMSolver, gamma: float, g_F: np.ndarray | None,
                        g_x: np.ndarray | None, pair: bool | None = None) -> InjectionCalibration:
    """Scale c such that the injected adjoint's dFc gradient has norm gamma x the mass loss's.

    The paper injects gamma * dL_render/dF with gamma = 0.1 in its own code's loss units, which
    we do not share (our mass loss is in kg^2, our DT loss is per pixel and per image height).
    To make gamma mean the same thing at every resolution both adjoints are pulled back to dFc
    through the same rollout (backward is linear in the injected adjoint) and c = gamma
    |grad_mass| / |grad_inject|. The solver keeps the two gradients: the optimiser's first
    iteration needs exactly mass + c x injected on the rollout this leaves current
    (MPMSolver.combine_calibration, then optimize_control(gradient_ready=True)). pair: see
    MPMSolver.calibration_gradients (by default chosen by the solver's size).
    """
    n_mass, n_inj = solver.calibration_gradients(g_F, g_x, pair)
    ok = n_inj > 0 and np.isfinite(n_inj) and np.isfinite(n_mass)
    return InjectionCalibration(gamma * n_mass / n_inj if ok else 0.0, n_mass, n_inj)


def frame_calibration(cfg: MorphConfig, fs: FrameState, solver: MPMSolver, inject_F: bool, inject_x: bool,
                      k: int, log) -> InjectionCalibration | None:
    """Frame k's injection scale into ``fs`` (MorphConfig.injection_calibration; with every_frame,
    measured at the frames k that injection_calibration_every divides, and wherever none is
    measured yet, the last one kept in between); the calibration when one ran (its rollout and
    gradients are then the optimiser's first). ``log`` takes a line."""
    if not (inject_F or inject_x):
        return None
    if cfg.injection_calibration == "absolute":
        fs.injection_scale = cfg.gamma if inject_F else cfg.gamma_x
        return None
    due = cfg.injection_calibration == "every_frame" and k % cfg.injection_calibration_every == 0
    recalibrate = np.isnan(fs.injection_scale) or due
    if not (recalibrate and (np.any(fs.g_F) or np.any(fs.g_x))):
        return None
    calibration = calibrate_injection(solver, cfg.gamma if inject_F else cfg.gamma_x,
                                      fs.g_F if inject_F else None, fs.g_x if inject_x else None)
    fs.injection_scale = calibration.scale
    if cfg.injection_calibration == "first_frame":
        log(f"injection scale calibrated at frame {k}: {calibration.scale:.4g}")
    return calibration
