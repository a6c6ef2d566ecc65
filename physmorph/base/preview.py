"""Small preview images so a user can see at a glance that a stage's data is right."""

from __future__ import annotations

import os

import numpy as np

SHELL_COLOUR = "#d95f02"
INTERIOR_COLOUR = "#1b9e77"
# Orthographic views as (horizontal axis, vertical axis, title); world +y is up.
_VIEWS = ((0, 1, "front (x, y)"), (2, 1, "side (z, y)"), (0, 2, "top (x, z)"))


def particle_preview(
    x: np.ndarray,  # [N, 3]
    is_surface: np.ndarray,  # [N] bool
    png_path: str | os.PathLike,
    title: str,
    max_points: int = 20000,
) -> None:
    """Write a small PNG: three orthographic scatter views, shell particles vs interior in two colours.

    At most ``max_points`` particles are drawn (a fixed-seed subset) so the image stays cheap.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
    is_surface = np.asarray(is_surface, dtype=bool).reshape(-1)
    if len(x) > max_points:
        keep = np.sort(np.random.default_rng(0).choice(len(x), max_points, replace=False))
        x, is_surface = x[keep], is_surface[keep]
    lim_lo, lim_hi = (x.min(axis=0), x.max(axis=0)) if len(x) else (np.zeros(3) - 1, np.zeros(3) + 1)
    centre, half = 0.5 * (lim_lo + lim_hi), 0.55 * float(np.max(lim_hi - lim_lo) + 1e-9)
    fig, axes = plt.subplots(1, 3, figsize=(9, 3.3), dpi=80)
    for ax, (h, v, name) in zip(axes, _VIEWS):
        # Interior on top: in projection the shell covers everything, so the core would be hidden.
        for mask, colour, label, size in ((is_surface, SHELL_COLOUR, "shell", 0.5), (~is_surface, INTERIOR_COLOUR, "interior", 1.5)):
            ax.scatter(x[mask, h], x[mask, v], s=size, c=colour, alpha=0.5, linewidths=0, label=label)
        ax.set_xlim(centre[h] - half, centre[h] + half)
        ax.set_ylim(centre[v] - half, centre[v] + half)
        ax.set_aspect("equal")
        ax.set_title(name, fontsize=8)
        ax.tick_params(labelsize=6)
    axes[0].legend(loc="lower left", fontsize=6, markerscale=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(png_path, format="png")
    plt.close(fig)
