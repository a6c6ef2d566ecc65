"""What the solver keeps per particle and substep, from its config alone: no Taichi, no solver.

The backward restores each substep's forward state instead of recomputing it, so a frame holds,
per particle and substep, x and v (3 floats each), C and F (9 each), and the forward's polar
rotation of Fe as a unit quaternion (4) with its smallest pair sum (1): 29 floats in the solver's
precision. The memory estimate of a morph (physmorph.settings.workflow.morph_memory) asks this module, as
the solver does, so the two cannot disagree.
"""

from __future__ import annotations

from physmorph.settings.mpm import MPMConfig

FLOATS_PER_PARTICLE_SUBSTEP = 3 + 3 + 9 + 9 + 4 + 1  # x, v, C, F, the rotation's quaternion, the pair sum


def float_bytes(precision: str) -> int:
    """Bytes of one float of the solver at ``precision`` (MPMConfig.precision)."""
    return 8 if precision == "float64" else 4


def bytes_per_particle_substep(cfg: MPMConfig) -> int:
    """Bytes stored per particle per substep by a solver built from ``cfg`` (only its precision is
    read, so anything with a ``precision`` will do)."""
    return FLOATS_PER_PARTICLE_SUBSTEP * float_bytes(cfg.precision)
