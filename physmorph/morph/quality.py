"""How far a morph got, judged against what is reachable (docs/outputs.md: "share of the reachable gap").

Raw alpha MSE depends on image size, particle count and sigma0, so it cannot be compared across
profiles. The *ceiling* is the alpha MSE (and silhouette IoU) of the target's own particle
sampling rendered at rest (F = I) with the same renderer, cameras and sigma0: no morph of those
particles can do much better. A run reports the share of the reachable gap it closed,

    gap_closed(a_k) = (a_0 - a_k) / (a_0 - a_ceiling),

1 when it renders as well as the target's own particles, 0 when no better than the source,
negative when worse. When the source already renders about as well as the ceiling (e.g. a run
whose source is its target) the gap vanishes and the ratio would blow up, so the starting value is
raised to at least ceiling + tol (tol = ``rel_tol`` x ceiling):

    a0' = max(a_0, a_ceiling + tol),   gap_closed(a_k) = (a0' - a_k) / (a0' - a_ceiling).

This equals the plain ratio whenever the gap exceeds tol, is continuous in a_0, has a
denominator >= tol, and gives 1 for a run that stays at the ceiling.

Silhouettes from a ring of cameras can be matched without the volume behind them (a hollow or
flattened body, particles dragged along the view rays). :func:`volume_metrics` gives the 3D
checks: the IoU of the grid cells the particles fill and the cells the target's own sampling
fills, and the share of the mass packed above twice the target's density.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import numpy as np

from physmorph.base.cameras import Cameras
from physmorph.base.grid import Grid, splat_mass

if TYPE_CHECKING:
    from physmorph.settings.render import RenderConfig

# tol of gap_closed relative to the ceiling.
GAP_REL_TOL = 0.1
# volume_metrics: a node is filled above this share of the target's interior node mass, and
# overfilled above OVERFILL times it ...
VOLUME_FILL = 0.5
OVERFILL = 2.0
# ... which is this percentile of the target's non-empty node masses (deep inside a solid every
# node carries the same mass, density x dx^3; the lower percentiles are the boundary layer)
INTERIOR_PERCENTILE = 90.0


def view_alpha_mse(alpha: np.ndarray,  # [V, H, W]
                   target_alpha: np.ndarray,  # [V, H, W]
                   ) -> np.ndarray:  # [V]
    """Each view's alpha MSE against the target's silhouette."""
    return ((alpha - target_alpha) ** 2).mean(axis=(1, 2))


def silhouette_iou(alpha: np.ndarray,  # [V, H, W]
                   target_alpha: np.ndarray,  # [V, H, W]
                   threshold: float = 0.5) -> np.ndarray:  # [V]
    """Per-view IoU of the silhouettes alpha > threshold; 1 for two empty silhouettes."""
    a = np.asarray(alpha) > threshold
    t = np.asarray(target_alpha) > threshold
    inter = (a & t).sum(axis=(1, 2)).astype(float)
    union = (a | t).sum(axis=(1, 2)).astype(float)
    return np.where(union > 0, inter / np.maximum(union, 1.0), 1.0)


def volume_metrics(x: np.ndarray,  # [N, 3] particle positions
                   mass: np.ndarray,  # [N]
                   target_grid_mass: np.ndarray,  # [R, R, R] the target's own particles splatted (Target.grid_mass)
                   grid: Grid,
                   splat: Callable[[np.ndarray, np.ndarray, Grid], np.ndarray] = splat_mass) -> dict[str, float]:
    """The 3D checks, from the particles' grid mass m_I = sum_p w_Ip m_p (the MPM P2G transfer)
    and the target's m*_I rescaled to the particles' total mass, with m_int the target's interior
    node mass (the INTERIOR_PERCENTILE of its non-empty nodes):

        volume_iou      = |A & B| / |A | B|,  A = {I : m_I > f m_int},  B = {I : m*_I > f m_int},
                          f = VOLUME_FILL: the filled nodes against the target's;
        overfilled_mass = sum_{I : m_I > c m_int} m_I / sum_I m_I,  c = OVERFILL: the share of the
                          mass on nodes packed above c times the target's density (collapsed material).

    One threshold for both fields, so a body stretched to less than half the target's density (a
    loose cloud of particles) does not count as filling its cells, and one collapsed into clumps
    fills few. The target's own sampling scores volume_iou 1 and overfilled_mass 0. A source of
    another volume at the same density cannot reach 1 (it has too little or too much material
    to fill the target's cells), so compare methods on the same experiment. ``splat`` computes m_I
    (physmorph.morph.frame_measures.grid_mass is the morph loop's one-pass form).
    """
    x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
    mass = np.asarray(mass, dtype=np.float64).reshape(-1)
    target = np.asarray(target_grid_mass, dtype=np.float64)
    if target.shape != (grid.res,) * 3:
        raise ValueError(f"target grid mass has shape {target.shape}, expected {(grid.res,) * 3}")
    filled = target[target > 0]
    if filled.size == 0 or not mass.sum() > 0:
        raise ValueError("volume_metrics needs a non-empty target grid mass and particles with mass")
    scale = mass.sum() / filled.sum()
    target = target * scale
    interior = float(np.percentile(filled, INTERIOR_PERCENTILE)) * scale
    m = splat(x, mass, grid)
    a, b = m > VOLUME_FILL * interior, target > VOLUME_FILL * interior
    return {"volume_iou": float((a & b).sum() / max(int((a | b).sum()), 1)),
            "overfilled_mass": float(m[m > OVERFILL * interior].sum() / m.sum())}


def gap_closed(a0: float, a: np.ndarray | float, ceiling: float, rel_tol: float = GAP_REL_TOL) -> np.ndarray | float:
    """Share of the reachable gap closed, (a0' - a) / (a0' - ceiling); see the module docstring."""
    a = np.asarray(a, dtype=float)
    tol = max(rel_tol * float(ceiling), 1e-9)
    start = max(float(a0), float(ceiling) + tol)
    out = (start - a) / (start - float(ceiling))
    return float(out) if out.ndim == 0 else out


def ceiling_metrics(x: np.ndarray,  # [N, 3] the target's own particles at rest
                    sigma0,  # scalar or [N]
                    cameras: Cameras,
                    target_alpha: np.ndarray,  # [V, H, W]
                    render: RenderConfig | None = None) -> dict:
    """alpha MSE and IoU per view of particles x rendered at rest (F = I) against target_alpha
    (``render``: the renderer's settings, RenderConfig() when None)."""
    from physmorph.settings.render import RenderConfig
    from physmorph.render.api import render_views

    render = RenderConfig() if render is None else render
    x = np.asarray(x, dtype=np.float64)
    F = np.broadcast_to(np.eye(3), (len(x), 3, 3))
    alpha, _ = render_views(x, F, sigma0, cameras, render)
    mse = view_alpha_mse(alpha, target_alpha)
    iou = silhouette_iou(alpha, target_alpha)
    return {"alpha_mse": float(mse.mean()), "alpha_mse_views": mse, "iou": float(iou.mean()), "iou_views": iou}
