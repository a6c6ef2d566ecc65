"""How far a morph got, judged against what is reachable (SPEC section 5, issue "convergence").

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
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from physmorph.cameras import Cameras

if TYPE_CHECKING:
    from physmorph.render import RenderConfig

# tol of gap_closed relative to the ceiling.
GAP_REL_TOL = 0.1


def silhouette_iou(alpha: np.ndarray,  # [V, H, W]
                   target_alpha: np.ndarray,  # [V, H, W]
                   threshold: float = 0.5) -> np.ndarray:  # [V]
    """Per-view IoU of the silhouettes alpha > threshold; 1 for two empty silhouettes."""
    a = np.asarray(alpha) > threshold
    t = np.asarray(target_alpha) > threshold
    inter = (a & t).sum(axis=(1, 2)).astype(float)
    union = (a | t).sum(axis=(1, 2)).astype(float)
    return np.where(union > 0, inter / np.maximum(union, 1.0), 1.0)


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
    from physmorph.render import RenderConfig, render_views  # the renderer (torch) only where it is used

    render = RenderConfig() if render is None else render
    x = np.asarray(x, dtype=np.float64)
    F = np.broadcast_to(np.eye(3), (len(x), 3, 3))
    alpha, _ = render_views(x, F, sigma0, cameras, render)
    mse = ((alpha - target_alpha) ** 2).mean(axis=(1, 2))
    iou = silhouette_iou(alpha, target_alpha)
    return {"alpha_mse": float(mse.mean()), "alpha_mse_views": mse, "iou": float(iou.mean()), "iou_views": iou}
