"""The export stage's settings (config key ``export``): how a run's video looks and how its
surfaces are made. Only the video and viewer jobs read the video keys, only the mesh jobs the
surface keys, so editing one reruns just those jobs."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

VIDEO_KEYS = ("width", "height", "fps", "orbit_deg", "max_particles", "crf")
MESH_KEYS = ("refine", "smooth_iterations", "frame")


@dataclass(frozen=True)
class ExportConfig:
    """Videos, surface meshes and Gaussian-splat files of the full-method runs (snakemake export)."""

    width: int = 384  # each video panel's width in pixels (the body's, then the target's)
    height: int = 288
    fps: int = 10
    orbit_deg: float = 120.0  # how far the video's camera turns over the whole run
    max_particles: int = 120_000  # above this the video shows the body by an even subsample
    crf: int = 23  # H.264 quality (lower: better and larger)
    refine: float = 2.0  # surface grid cells per MPM cell
    smooth_iterations: int = 10  # Taubin smoothing passes of the surface
    frame: Literal["domain", "target"] = "domain"  # coordinates of meshes and splats: the simulation's or the target mesh's

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            if getattr(self, name) < 16 or getattr(self, name) % 2:
                raise ValueError(f"{name} must be an even number of pixels >= 16, got {getattr(self, name)}")
        if not 1 <= self.fps <= 120:
            raise ValueError(f"fps must be in [1, 120], got {self.fps}")
        if self.max_particles < 1000:
            raise ValueError(f"max_particles must be >= 1000, got {self.max_particles}")
        if not 0 <= self.crf <= 51:
            raise ValueError(f"crf must be in [0, 51], got {self.crf}")
        if not self.refine > 0:
            raise ValueError(f"refine must be > 0, got {self.refine}")
        if self.smooth_iterations < 0:
            raise ValueError(f"smooth_iterations must be >= 0, got {self.smooth_iterations}")
        if self.frame not in ("domain", "target"):
            raise ValueError(f"frame must be 'domain' or 'target', got {self.frame!r}")

    def video(self) -> dict:
        return {k: getattr(self, k) for k in VIDEO_KEYS}

    def mesh(self) -> dict:
        return {k: getattr(self, k) for k in MESH_KEYS}
