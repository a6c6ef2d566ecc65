"""Torn-off spray put back into the body between frames (MorphConfig.reabsorb_strays; not in the paper).

A particle torn off the body and lying outside the target stays there: the grid's mass loss has no
direction several cells outside the target, and the control acts through the stress, which moves a
lone particle not at all (docs/study/log.md, findings 228-232), so the stray pull's term moves
nothing either. The paper names adaptive particle redistribution as the remedy; this is its
simplest part, reabsorbing what separated.

After a frame's plasticity update a particle is spray when it is

- detached: in a connected piece of the occupied grid cells (side dx; linked through a shared face,
  edge or corner, or with MorphConfig.spray_links "faces" through a shared face only) other than the
  largest, holding less than SPRAY_PIECE_SHARE of the mass (a body torn in two keeps both halves),
- and stray: outside the target by the stray pull's test (its nearest grid node holds no target
  mass) and more than stray_pull_onset cells from the target's surface.

Each is moved to the body particle b nearest its nearest target surface point s_p, half a cell from
x_b toward s_p (or to s_p where that is nearer), and takes b's velocity, affine velocity C, F and Fp:
the state of the material it joins, so it adds no stress of its own. Its mass and volume stay its
own, so the body's mass is conserved; its momentum becomes m_p v_b. The move is between frames, so
each frame's rollout and its gradients are unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from physmorph.base.grid import occupied_pieces
from physmorph.mpm.state import ParticleState

# A detached piece holding at least this share of the material is a part of the body, not spray.
SPRAY_PIECE_SHARE = 0.01


def detached_pieces(x: np.ndarray,  # [N, 3]
                    mass: np.ndarray,  # [N]
                    dx: float, links: str) -> np.ndarray:  # [N] bool
    """Particles in a connected piece of occupied cells (side dx, linked as ``links`` says:
    physmorph.base.grid.occupied_pieces) other than the one of most mass, the piece holding less
    than SPRAY_PIECE_SHARE of the mass."""
    piece, count = occupied_pieces(x, dx, links)
    piece_mass = np.bincount(piece, weights=mass, minlength=count + 1)
    small = piece_mass < SPRAY_PIECE_SHARE * mass.sum()
    small[int(np.argmax(piece_mass))] = False
    return small[piece]


def outside_target(x: np.ndarray,  # [N, 3]
                   nearest_d: np.ndarray,  # [N] distance to the nearest target surface point
                   target, onset_cells: float) -> np.ndarray:  # [N] bool
    """The stray pull's test (physmorph.morph.steering.stray_pull_anchors, its default form): the
    nearest grid node holds no target mass and the target's surface is more than onset_cells away."""
    grid = target.grid
    node = np.clip(np.rint((x - np.asarray(grid.lo)) / grid.dx).astype(np.int64), 0, grid.res - 1)
    return (target.grid_mass[node[:, 0], node[:, 1], node[:, 2]] <= 0.0) & (nearest_d > onset_cells * grid.dx)


@dataclass
class Reabsorbed:
    state: ParticleState  # the state with the spray moved
    moved: np.ndarray  # [M] indices of the moved particles
    mass_share: float  # their share of the mass


def reabsorb_spray(st: ParticleState, nearest_d: np.ndarray,  # [N]
                   nearest_i: np.ndarray,  # [N] index of each particle's nearest target surface point
                   target, onset_cells: float, links: str) -> Reabsorbed:
    """The spray (module docstring) moved into the body; the state unchanged where there is none."""
    from scipy.spatial import cKDTree

    dx = float(target.grid.dx)
    detached = detached_pieces(st.x, st.mass, dx, links)
    spray = np.flatnonzero(detached & outside_target(st.x, nearest_d, target, onset_cells))
    if not len(spray):
        return Reabsorbed(st, spray, 0.0)
    body = np.flatnonzero(~detached)
    aim = np.asarray(target.surface_points)[nearest_i[spray]]  # [M, 3] s_p
    b = body[cKDTree(st.x[body]).query(aim, workers=-1)[1]]  # [M] the joined body particle
    to_aim = aim - st.x[b]
    dist = np.linalg.norm(to_aim, axis=1, keepdims=True)
    step = np.minimum(dist, 0.5 * dx) / np.where(dist > 0, dist, 1.0)
    arrays = {k: np.array(getattr(st, k), copy=True) for k in ("x", "v", "F", "C", "Fp")}
    arrays["x"][spray] = st.x[b] + step * to_aim
    for k in ("v", "F", "C", "Fp"):
        arrays[k][spray] = getattr(st, k)[b]
    moved = ParticleState(**arrays, mass=st.mass, volume=st.volume)
    return Reabsorbed(moved, spray, float(st.mass[spray].sum() / st.mass.sum()))


def reabsorb_frame(fs, nearest_d: np.ndarray,  # [N] kept with the frame's end state, updated in place
                   nearest_i: np.ndarray,  # [N]
                   inputs, cfg) -> float:
    """The frame loop's step (after the plasticity): the spray of the frame state ``fs`` moved into
    the body where the run asks for it (method full, MorphConfig.reabsorb_strays), the moved particles'
    nearest target points, mask flags and held render gradients made theirs; returns the share of the
    mass moved (NaN where off). ``reabsorb_spray`` is looked up at call time (tests wrap it)."""
    if not (cfg.reabsorb_strays and cfg.method == "full"):
        return np.nan
    r = reabsorb_spray(fs.state, nearest_d, nearest_i, inputs.target, cfg.stray_pull_onset, cfg.spray_links)
    if len(r.moved):
        fs.state = r.state
        nearest_d[r.moved], nearest_i[r.moved] = inputs.nearest_target(r.state.x[r.moved])
        # now at the body's surface; the render gradient held for the next frame was of their old place
        fs.mask[r.moved] = inputs.need_mask
        fs.g_F[r.moved] = 0.0
        fs.g_x[r.moved] = 0.0
    return r.mass_share
