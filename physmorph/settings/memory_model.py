"""The memory and time model of the stages: what each stage's peak memory is estimated at (checked
against the machine before any job runs, and the rules' resources.mem_mb) and how long a morph's
particle-frame takes."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

from physmorph.settings.sections import SamplingConfig, ShapeSettings, TargetConfig
from physmorph.settings.solver_memory import (PACKED_STRESS_FLOATS_PER_PARTICLE, PACKED_STRESS_MIN_PARTICLES,
                                              PAIR_MIN_PARTICLE_STEPS, bytes_per_particle_substep, float_bytes,
                                              grid_lane_bytes_per_node)


BASE_PROCESS_MB = 600.0  # python + numpy + torch + taichi runtime, measured ~500 MB
# Per particle in the morph, besides what the solver stores per substep and per control slot
# (morph_memory): the per-frame work arrays (plasticity neighbours, renderer, mask); calibrated on
# the paper profile with its real particle count (iso, 471,282 particles, 8 x 960x540: 7.04 GB
# peak RSS; the estimate with this constant 7.1 GB).
MORPH_BYTES_PER_PARTICLE = 10000.0
# Seconds a morph's particle-frame takes on a 2-core CPU (measured 1.4-2e-4): the morph rule's
# runtime request and the stability map's wall-clock limits
SECONDS_PER_PARTICLE_FRAME = 2e-4


@dataclass(frozen=True)
class MemoryEstimate:
    stage: str
    mb: float
    detail: str


def physical_memory_mb() -> float:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**20
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        return float("inf")


def particle_estimate(shape: ShapeSettings, sampling: SamplingConfig, domain) -> int:
    """Particles of a shape normalised to ``shape.size``: a shell two cells deep at ppc_surface^3
    per cell and the interior at ppc_interior^3, for a solid of volume ~0.15 size^3 (the benchmark
    shapes are ~1170 units^3 at sizes 14-20) and the area of a sphere of that volume x 1.5."""
    dx = (domain[1] - domain[0]) / sampling.grid_res
    volume = 0.15 * shape.size ** 3
    area = 1.5 * (36 * math.pi) ** (1 / 3) * volume ** (2 / 3)
    shell = 2 * area / dx ** 2
    interior = max(volume / dx ** 3 - shell, 0.0)
    return int(shell * sampling.ppc_surface ** 3 + interior * sampling.ppc_interior ** 3)


def sampling_memory(shape, sampling: SamplingConfig, domain, stage: str) -> MemoryEstimate:
    n = particle_estimate(shape, sampling, domain)
    # candidates (3 float64 + flags) and inside tests for every particle, a float64 voxel grid
    mb = BASE_PROCESS_MB + (n * 400 + sampling.grid_res ** 3 * 16) / 2**20
    return MemoryEstimate(stage, mb, f"~{n:,} particles x 400 B + grid {sampling.grid_res}^3 x 16 B")


def target_memory(sampling: SamplingConfig, target: TargetConfig, stage: str) -> MemoryEstimate:
    rays = target.width * target.height * target.supersample ** 2
    pixels = target.cameras * target.width * target.height
    mb = BASE_PROCESS_MB + (rays * 64 + pixels * 48 + sampling.grid_res ** 3 * 16) / 2**20
    return MemoryEstimate(stage, mb, f"{target.cameras} x {target.width}x{target.height} images, "
                                     f"{rays:,} rays per view, grid {sampling.grid_res}^3")


def morph_memory(source: ShapeSettings, sampling: SamplingConfig, target: TargetConfig, mpm, domain,
                 stage: str, n_particles: int | None = None, threads: int = 1) -> MemoryEstimate:
    """A morph's peak memory; ``n_particles``: the sampled count when the particles exist (a
    scheduler's request then follows the real run), else estimated from the shape's size;
    ``threads``: the job's CPU threads, each with its lanes' copy of the grid (none on a GPU)."""
    n = particle_estimate(source, sampling, domain) if n_particles is None else int(n_particles)
    scale = 2 if mpm.precision == "float64" else 1
    slots = mpm.substeps  # one control slot per substep
    # stored per substep: what the solver keeps for its backward (physmorph.settings.solver_memory); per
    # control slot dFc and its gradient (72 B in float32), and Adam's two moments when Adam runs (72 B)
    moments = 72 if mpm.optimizer == "adam" else 0
    lanes = 0 if getattr(mpm, "device", "cpu") == "cuda" else max(1, int(threads))
    # what P2G's stress on packs leaves for its particle loop (CPU only)
    packs = PACKED_STRESS_FLOATS_PER_PARTICLE * float_bytes(mpm.precision) if lanes and n >= PACKED_STRESS_MIN_PARTICLES else 0
    per_particle = (mpm.substeps * bytes_per_particle_substep(mpm) + slots * (72 + moments) * scale + packs
                    + MORPH_BYTES_PER_PARTICLE)
    pixels = target.cameras * target.width * target.height
    per_node = (64 + 16 * mpm.substeps) * scale + grid_lane_bytes_per_node(
        mpm.precision, lanes, n * mpm.substeps >= PAIR_MIN_PARTICLE_STEPS)  # the P2G grid kept per substep, the lanes
    grid = sampling.grid_res ** 3 * per_node
    mb = BASE_PROCESS_MB + (n * per_particle + grid + pixels * 64) / 2**20
    return MemoryEstimate(stage, mb, f"~{n:,} particles x {per_particle:,.0f} B + grid {sampling.grid_res}^3 x "
                                     f"{per_node:,.0f} B ({lanes} lanes) + {target.cameras} x {target.width}x{target.height} "
                                     f"images x 64 B")
