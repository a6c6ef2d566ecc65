"""The workflow's own config sections (raw meshes, shapes, sampling, target images, experiments,
the speed/accuracy study, the table lists), declared as the library's sections are
(physmorph.settings.base): each field with its default, its range and its meaning. The solver,
renderer, plasticity, mask, morph and export sections are the library's own classes.
"""

from __future__ import annotations

import re
from dataclasses import field, replace
from typing import Annotated, Any, Literal

from physmorph.base.cameras import height_past_a_pole
from physmorph.settings.errors import ConfigError
from physmorph.settings.base import Float, Int, Refused, setting, settings_dataclass

RES_PATTERN = r"(\d+)x(\d+)x(\d+)"


@settings_dataclass
class RawMesh:
    """A raw mesh downloaded from a pinned URL and checked against its SHA-256."""

    url: Annotated[str, setting("where the file is downloaded from (pin a commit)", "URL")]
    sha256: Annotated[str, setting("SHA-256 of the file; a mismatch stops the run", "", "64 lowercase hex digits",
                                   pattern=r"^[0-9a-f]{64}$")]


@settings_dataclass
class ShapeSettings:
    """One shape: a raw mesh (``file``: a raw_meshes entry; ``path``: a mesh on disk), an
    isosphere or an extruded letter, normalised to ``size`` domain units."""

    kind: Annotated[Literal["file", "isosphere", "letter"], setting(
        "file: a mesh; isosphere: a once-subdivided icosahedron; letter: an extruded glyph")]
    file: Annotated[str | None, setting("kind file: a raw_meshes entry (fetched and checked)", "",
                                        "exactly one of file, path")] = None
    path: Annotated[str | None, setting("kind file: a mesh on disk (OBJ, PLY, STL, GLB, ...); its SHA-256 is "
                                        "recorded", "path", "exactly one of file, path")] = None
    glyph: Annotated[str | None, setting("kind letter: the character", "", "one character")] = None
    size: Annotated[Float, setting(
        "longest extent after normalisation; choose it so the shape holds ~1170 units^3 like the benchmark shapes "
        "(MPM keeps volume); python -m physmorph.meshes.fit MESH prints it", "domain units", gt=0)] = 16.0
    depth: Annotated[Float | None, setting("kind letter: extrusion depth", "domain units", gt=0)] = None
    seed: Annotated[Int | None, setting(
        "the seed of this shape's particle sampling (null: the top-level seed); a second entry of a shape with "
        "another seed is a second sample of it, whose runs measure a result's noise (tables.noise)", ge=0)] = None

    def __post_init__(self) -> None:
        """What each kind needs: a file kind exactly one of file and path, a letter one character."""
        if self.kind == "file" and (self.file is None) == (self.path is None):
            raise Refused("file", "file or path: kind 'file' takes exactly one of 'file' (a raw_meshes entry) or "
                                  "'path' (a mesh file on disk)")
        if self.kind != "file" and (self.file or self.path):
            raise Refused("file", f"file or path: only kind 'file' takes them (kind is {self.kind!r})")
        if self.kind == "letter" and (not self.glyph or len(self.glyph) != 1):
            raise Refused("glyph", f"glyph: kind 'letter' needs a single character, got {self.glyph!r}")


@settings_dataclass
class SamplingConfig:
    """Particle sampling on the simulation grid (file tag {grid_res}x{ppc_surface}x{ppc_interior})."""

    grid_res: Annotated[Int, setting("MPM grid cells per axis (also the sampling grid)", "cells", ge=8)] = 32
    ppc_surface: Annotated[Int, setting("particles per cell per axis in the two-cell surface shell", ge=1)] = 2
    ppc_interior: Annotated[Int, setting("particles per cell per axis inside", ge=1)] = 1
    density: Annotated[Float, setting("material density rho", "mass / domain unit^3", gt=0)] = 75.0
    sigma_scale: Annotated[Float, setting("Gaussian size sigma0 as a multiple of the mean nearest-neighbour "
                                          "distance", gt=0)] = 0.7

    @property
    def tag(self) -> str:
        """The resolution tag used in file names: {grid_res}x{ppc_surface}x{ppc_interior}."""
        return f"{self.grid_res}x{self.ppc_surface}x{self.ppc_interior}"

    def with_tag(self, tag: str) -> "SamplingConfig":
        m = re.fullmatch(RES_PATTERN, tag)
        if not m:
            raise ConfigError(f"resolution tag '{tag}' must look like 32x2x1 (grid x ppc_surface x ppc_interior)")
        return replace(self, grid_res=int(m[1]), ppc_surface=int(m[2]), ppc_interior=int(m[3]))


@settings_dataclass
class TargetConfig:
    """Target rasterization: ring cameras, the target's grid mass and surface points."""

    cameras: Annotated[Int, setting("views of the target, evenly spaced on the ring", ge=1)] = 8
    elevation_deg: Annotated[Float, setting("camera elevation above the horizontal", "degrees",
                                            ge=-89, le=89)] = 21.0
    elevation_spread_deg: Annotated[Float, setting("views alternate this far above and below the elevation "
                                                   "(even views above, odd below); 0 = one ring", "degrees",
                                                   ge=0, le=89)] = 0.0
    fov_y_deg: Annotated[Float, setting("vertical field of view", "degrees", gt=0, lt=180)] = 40.0
    distance: Annotated[Float, setting("camera distance from the origin", "domain units", gt=0)] = 36.0
    width: Annotated[Int, setting("image width", "pixels", ge=4)] = 160
    height: Annotated[Int, setting("image height", "pixels", ge=4)] = 90
    supersample: Annotated[Int, setting("rays per pixel per axis for the target's exact coverage alpha",
                                        ge=1, le=8)] = 3
    surface_points: Annotated[Int, setting("target surface samples for Chamfer distances and plasticity",
                                           ge=100)] = 20000

    def __post_init__(self) -> None:
        """Both heights of the ring within the poles (at a pole a view's up is its direction)."""
        past = height_past_a_pole(self.elevation_deg, self.elevation_spread_deg)
        if past is not None:
            raise Refused("elevation_spread_deg", f"elevation_spread_deg: the views at {past:g} degrees "
                                                  f"(elevation {self.elevation_deg:g} ± {self.elevation_spread_deg:g}) "
                                                  "are past a pole; keep elevation ± spread between -90 and 90")


@settings_dataclass
class Experiment:
    """One morph run; unset fields take the global sections' values."""

    source: Annotated[str, setting("shape the particles are sampled from", "", "a shapes key")]
    target: Annotated[str, setting("shape to morph into", "", "a shapes key")]
    method: Annotated[Literal["physics_only", "f_inject", "full", "position_inject"], setting(
        "physics_only: mass loss alone; f_inject: + render gradient on F; full: + plasticity; position_inject: "
        "render gradient on positions")]
    drag: Annotated[Float | None, setting("sets mpm.drag", "1/s", "as mpm.drag")] = None
    frames: Annotated[Int | None, setting("sets morph.frames", ge=1)] = None
    cameras: Annotated[Int | None, setting("sets morph.cameras", "", "<= target.cameras", ge=1)] = None
    gamma: Annotated[Float | None, setting("sets morph.gamma", ge=0)] = None
    gamma_x: Annotated[Float | None, setting("sets morph.gamma_x", ge=0)] = None
    grad_iters: Annotated[Int | None, setting("sets mpm.grad_iters", ge=1)] = None
    plasticity_start: Annotated[Int | None, setting("sets plasticity.start_frame", "frame", ge=0)] = None
    release_frames: Annotated[Int | None, setting("sets morph.release_frames", "frames", ge=0)] = None
    volume: Annotated[Literal["keep", "target"] | None, setting("sets plasticity.volume", "", "keep or target")] = None


# experiment key -> (section, field) it overrides
EXPERIMENT_OVERRIDES = {"drag": ("mpm", "drag"), "grad_iters": ("mpm", "grad_iters"),
                        "plasticity_start": ("plasticity", "start_frame"), "frames": ("morph", "frames"),
                        "cameras": ("morph", "cameras"), "gamma": ("morph", "gamma"), "gamma_x": ("morph", "gamma_x"),
                        "release_frames": ("morph", "release_frames"), "volume": ("plasticity", "volume")}


@settings_dataclass
class Tradeoff:
    """The speed/accuracy study: the base experiment with one knob changed at a time (physmorph.studies.tradeoff)."""

    experiment: Annotated[str, setting("the base experiment", "", "an experiments key")]
    frames: Annotated[Int, setting("frames of the base point (the frames knob changes them)", ge=1)]
    knobs: Annotated[dict[str, tuple[Any, ...]], setting(
        "values tried per knob: grid_res, ppc_surface, ppc_interior, image ([w, h]), cameras, grad_iters, "
        "learning_rate, frames, precision (float32 or float64), threads")] = field(default_factory=dict)
    # The study's own: the workflow's `threads` (which changes no result) neither adds nor removes a
    # point nor changes what the points' times measure.
    threads: Annotated[Int, setting("threads of the base point (the threads knob changes them); the workflow's "
                                    "`threads` does not reach the study", ge=1)] = 2


@settings_dataclass
class Tables:
    """What ``snakemake tables`` builds: the shapes' data and the experiments' runs."""

    shapes: Annotated[tuple[str, ...], setting("shapes whose particles and targets are built", "",
                                               "shapes keys")] = ()
    experiments: Annotated[tuple[str, ...], setting("experiments run for the tables and figures", "",
                                                    "experiments keys")] = ()
    noise: Annotated[tuple[str, ...], setting(
        "two of the experiments, one morph from two particle samples (a shape entry with its own seed): the spread "
        "of each measure between them is the directions table's noise; empty: none measured", "",
        "none or two tables.experiments")] = ()
