"""What the solver keeps per particle and substep, from its config alone: no Taichi, no solver.

The backward restores each substep's forward state instead of recomputing it, so a frame holds,
per particle and substep, x and v (3 floats each), C and F (9 each), and the forward's polar
rotation of Fe as a unit quaternion (4) with its smallest pair sum (1): 29 floats in the solver's
precision. The memory estimate of a morph (physmorph.settings.memory_model.morph_memory) asks this module, as
the solver does, so the two cannot disagree.
"""

from __future__ import annotations

from physmorph.settings.mpm import MPMConfig

FLOATS_PER_PARTICLE_SUBSTEP = 3 + 3 + 9 + 9 + 4 + 1  # x, v, C, F, the rotation's quaternion, the pair sum
# the injection calibration's backward_pair from this many particle-substeps on (n x substeps;
# below, its kernels' compilation costs more than it saves in a run: docs/performance.md)
PAIR_MIN_PARTICLE_STEPS = 1_000_000
# P2G's stress on packs of particles (physmorph.mpm.stress_packs) from this many particles on, on the
# CPU: its kernel's compilation (~8 s) costs more than it saves in a run of fewer particles
PACKED_STRESS_MIN_PARTICLES = 100_000
# what the packs leave for P2G per particle: A, a 3x3 matrix
PACKED_STRESS_FLOATS_PER_PARTICLE = 9
# Per grid node and CPU thread, the lanes' copies of the grid (physmorph.mpm.lanes): P2G's (momentum,
# mass) and the reverse of G2P's velocity adjoint; with backward_pair a second velocity adjoint
LANE_FLOATS_PER_NODE = 4 + 3
PAIR_LANE_FLOATS_PER_NODE = 3
# Per grid node, backward_pair's second set of grid adjoints (velocity, momentum, mass)
PAIR_GRID_FLOATS_PER_NODE = 3 + 3 + 1


def float_bytes(precision: str) -> int:
    """Bytes of one float of the solver at ``precision`` (MPMConfig.precision)."""
    return 8 if precision == "float64" else 4


def grid_lane_bytes_per_node(precision: str, threads: int, pair: bool) -> int:
    """Bytes per grid node of the CPU lanes at ``threads`` threads, and of backward_pair's second
    grid adjoints where ``pair`` (none of the lanes on a GPU: pass threads=0)."""
    floats = threads * (LANE_FLOATS_PER_NODE + (PAIR_LANE_FLOATS_PER_NODE if pair else 0))
    return (floats + (PAIR_GRID_FLOATS_PER_NODE if pair else 0)) * float_bytes(precision)


def bytes_per_particle_substep(cfg: MPMConfig) -> int:
    """Bytes stored per particle per substep by a solver built from ``cfg`` (only its precision is
    read, so anything with a ``precision`` will do)."""
    return FLOATS_PER_PARTICLE_SUBSTEP * float_bytes(cfg.precision)
