"""The export stage's settings (config key ``export``): how a run's video looks and how its
surfaces are made. Only the video and viewer jobs read the video keys, only the mesh jobs the
surface keys, so editing one reruns just those jobs."""

from __future__ import annotations

from typing import Annotated, Literal

from physmorph.settings.base import Float, Int, Refused, fields_of_job, setting, settings_dataclass


@settings_dataclass
class ExportConfig:
    """Videos, surface meshes and Gaussian-splat files of the full-method runs (snakemake export)."""

    experiments: Annotated[tuple[str, ...], setting(
        "the full-method runs `snakemake export` exports and its viewer page lists; empty: the tables' full runs and "
        "every full run that a config file beside config/config.yaml adds (a user's own)", "",
        "experiments keys of method full", job="plan")] = ()

    width: Annotated[Int, setting("width of each video panel (the body's, then the target's)", "pixels",
                                  "even, >= 16", ge=16, job="video")] = 384
    height: Annotated[Int, setting("height of the video", "pixels", "even, >= 16", ge=16, job="video")] = 288
    fps: Annotated[Int, setting("video frames per second (one per morph frame)", "1/s", ge=1, le=120,
                                job="video")] = 10
    orbit_deg: Annotated[Float, setting("how far the video's camera turns around the body over the whole run",
                                        "degrees", job="video")] = 120.0
    body: Annotated[Literal["surface", "particles"], setting(
        "what the video draws of the body: surface (the exported closed surface, smoothed without shrinking, as "
        "the paper shows its results; export.refine, export.smooth_iterations and export.pore_closing make it) or "
        "particles (the run's Gaussians, as the render loss sees them)", job="video")] = "surface"
    max_particles: Annotated[Int, setting(
        "above this many particles the video shows the body by an even subsample, each Gaussian widened to keep "
        "it closed", ge=1000, job="video")] = 120_000
    crf: Annotated[Int, setting("H.264 constant rate factor (lower: better and larger)", ge=0, le=51, job="video")] = 23
    refine: Annotated[Float, setting("surface grid cells per MPM cell (the exported meshes' resolution; the "
                                     "video's surface too)", gt=0, job="mesh")] = 2.0
    smooth_iterations: Annotated[Int, setting("Taubin smoothing passes of the exported surface (0: none)",
                                              ge=0, job="mesh")] = 10
    pore_closing: Annotated[Int, setting(
        "the surface's volume fraction grey-closed over this many surface cells a side before its level is found: "
        "its dips narrower than that are filled (at 3: pores and tunnels in the particles up to about two MPM "
        "cells across; 0: none)",
        "surface cells", ge=0, job="mesh")] = 3  # docs/study/log.md finding 306
    frame: Annotated[Literal["domain", "target"], setting(
        "coordinates of the exported meshes and splats: domain (the simulation's) or target (the target's input "
        "mesh frame and units, to overlay it)", job="mesh")] = "domain"

    def __post_init__(self) -> None:
        """The video encoder takes even sizes only."""
        for name in ("width", "height"):
            if getattr(self, name) % 2:
                raise Refused(name, f"{name} must be an even number of pixels >= 16, got {getattr(self, name)}")

    def video(self) -> dict:
        """What the video and viewer jobs read (the fields declared with job="video")."""
        return {k: getattr(self, k) for k in fields_of_job(type(self), "video")}

    def mesh(self) -> dict:
        """What the mesh jobs read (the fields declared with job="mesh")."""
        return {k: getattr(self, k) for k in fields_of_job(type(self), "mesh")}

    def surface(self) -> dict:
        """particle_surface's keywords (physmorph.reports.export.surface): the surface's resolution,
        smoothing and pore closing."""
        return {"refine": self.refine, "smooth_iterations": self.smooth_iterations, "pore_closing": self.pore_closing}

    def video_surface(self) -> dict:
        """The mesh keys the video jobs read too: those that make the surface, when they draw it."""
        return self.mesh() if self.body == "surface" else {}
