"""The simulation grid shared by sampling, targets and the MPM solver.

Convention (used everywhere in physmorph): the domain is the cube [lo, hi]^3 split into
``res`` cells per axis of size ``dx = (hi - lo) / res``; grid node ``i`` sits at
``lo + i * dx`` for ``i = 0 .. res - 1``. Particles transfer to nodes with the quadratic
B-spline of MLS-MPM (paper section 4, "Physics rollout"; Hu et al. 2018):

    base = floor((x - lo) / dx - 0.5),   f = (x - lo) / dx - base
    w0 = 0.5 (1.5 - f)^2,  w1 = 0.75 - (f - 1)^2,  w2 = 0.5 (f - 0.5)^2

so a particle touches nodes base .. base + 2 on each axis. Particles are kept at least
``BOUNDARY_CELLS`` cells away from the domain faces so the stencil never leaves the grid.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np

BOUNDARY_CELLS = 3
# The simulation domain [DOMAIN_LO, DOMAIN_HI]^3: the one place its default is written (the config's
# `domain:` key overrides it; physmorph.settings.workflow.Settings).
DOMAIN_LO, DOMAIN_HI = -16.0, 16.0


@dataclass(frozen=True)
class Grid:
    """A cubic Eulerian grid over [lo, hi]^3 with ``res`` nodes per axis."""

    res: int
    lo: float = DOMAIN_LO
    hi: float = DOMAIN_HI

    def __post_init__(self) -> None:
        if self.res < 2 * BOUNDARY_CELLS + 2:
            raise ValueError(f"grid res must be >= {2 * BOUNDARY_CELLS + 2}, got {self.res}")
        if not self.hi > self.lo:
            raise ValueError(f"grid domain needs hi > lo, got lo={self.lo}, hi={self.hi}")

    @property
    def dx(self) -> float:
        return (self.hi - self.lo) / self.res

    def node_positions(self) -> np.ndarray:  # [res]
        return self.lo + self.dx * np.arange(self.res)

    def interior_bounds(self) -> tuple[float, float]:
        """Positions particles must stay within so the B-spline stencil stays on the grid."""
        margin = BOUNDARY_CELLS * self.dx
        return self.lo + margin, self.hi - margin


def bspline_weights(x: np.ndarray, grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """Quadratic B-spline stencil: base node index [N, 3] and weights [N, 3 (axis), 3 (offset)]."""
    xg = (np.asarray(x, dtype=np.float64) - grid.lo) / grid.dx
    base = np.floor(xg - 0.5).astype(np.int64)
    f = xg - base
    w = np.stack([0.5 * (1.5 - f) ** 2, 0.75 - (f - 1.0) ** 2, 0.5 * (f - 0.5) ** 2], axis=-1)
    return base, w


def splat_mass(x: np.ndarray, mass: np.ndarray, grid: Grid) -> np.ndarray:
    """Particle mass on grid nodes, m_I = sum_p w_Ip m_p (the MPM P2G mass transfer).

    x: [N, 3] positions, mass: [N]. Returns [res, res, res]. Stencil entries that fall
    outside the grid are dropped (callers keep particles inside ``interior_bounds``).
    """
    x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
    mass = np.asarray(mass, dtype=np.float64).reshape(-1)
    base, w = bspline_weights(x, grid)
    out = np.zeros((grid.res,) * 3, dtype=np.float64)
    # the 27 stencil weights of each particle, [N, 3, 3, 3] in (a, b, c) order
    wt = w[:, 0, :, None, None] * w[:, 1, None, :, None] * w[:, 2, None, None, :] * mass[:, None, None, None]
    scatter_add(out, base, wt)
    return out


def scatter_add(out: np.ndarray,  # [R0, R1, R2], added to in place
                base: np.ndarray,  # [M, 3] the node of offset (0, 0, 0)
                weights: np.ndarray) -> None:  # [M, S, S, S]: weights[m, a, b, c] goes to base[m] + (a, b, c)
    """out[base + (a, b, c)] += weights[:, a, b, c], repeated nodes summed and nodes outside the
    grid dropped: np.add.at's result, by one bincount over the flat node index (several times
    faster at half a million particles)."""
    S = weights.shape[1]
    shape = np.asarray(out.shape)
    off = np.stack(np.meshgrid(*(np.arange(S),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)  # [S^3, 3]
    strides = np.array([out.shape[1] * out.shape[2], out.shape[2], 1])
    flat = (base @ strides)[:, None] + (off @ strides)[None, :]  # [M, S^3]
    w = weights.reshape(len(base), -1)
    if base.min() < 0 or (base.max(axis=0) + S - 1 >= shape).any():  # some stencil leaves the grid
        idx = base[:, None, :] + off[None]
        ok = np.all((idx >= 0) & (idx < shape), axis=-1)
        flat, w = flat[ok], w[ok]
    out += np.bincount(flat.ravel(), weights=w.ravel(), minlength=out.size).reshape(out.shape)


def blur_weights(sigma: float) -> np.ndarray:  # [2 r + 1]
    """The 1D weights of MPMConfig.mass_loss_blur: exp(-k^2 / (2 sigma^2)) for |k| <= r = ceil(3 sigma),
    normalised to sum 1."""
    r = int(np.ceil(3.0 * sigma))
    k = np.arange(-r, r + 1, dtype=np.float64)
    w = np.exp(-k ** 2 / (2.0 * sigma ** 2))
    return w / w.sum()


# How occupied cells link into pieces: through a shared face, an edge or a corner, or a shared face only
CellLinks = Literal["corners", "faces"]
# each one's scipy.ndimage.generate_binary_structure connectivity
CELL_LINKS = dict(zip(get_args(CellLinks), (3, 1)))


def occupied_pieces(x: np.ndarray,  # [N, 3] positions
                    dx: float, links: CellLinks = "corners") -> tuple[np.ndarray, int]:  # [N] piece of each point (1..count), count
    """The connected pieces of the cells of side dx the points occupy (links "corners": 26-connected,
    cells sharing a face, an edge or a corner; "faces": 6-connected, a shared face only),
    scipy.ndimage.label on a grid with a free layer around them; each point's piece label and the
    number of pieces."""
    from scipy import ndimage

    if links not in CELL_LINKS:
        raise ValueError(f"links must be one of {sorted(CELL_LINKS)}, got {links!r}")
    x = np.asarray(x, np.float64)
    cell = np.floor((x - x.min(axis=0)) / dx).astype(np.int64) + 1
    occupied = np.zeros(tuple(cell.max(axis=0) + 2), dtype=bool)
    occupied[tuple(cell.T)] = True
    labels, count = ndimage.label(occupied, structure=ndimage.generate_binary_structure(3, CELL_LINKS[links]))
    return labels[tuple(cell.T)], int(count)
