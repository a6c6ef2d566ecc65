"""Choosing ``size`` for a user's mesh: the volume of the source, inside the particles' region.

MPM keeps volume, so a target reachable from a source holds the source's volume (the benchmark
shapes hold ~1170 units^3). A long, thin mesh scaled to that volume can be wider than the part of
the domain particles may occupy (``BOUNDARY_CELLS`` cells from each face, so it depends on the
grid), and sampling then refuses it. The way out is to shrink both: the target to the largest size
that fits, and the source to the target's volume.

    python -m physmorph.meshes.fit path/to/mesh.obj [--configfile config/config.yaml ...] [--source iso]

prints a config file (``> mine.yaml``): as comments, the size for the source's volume and the
largest size that fits the configured grid (and the target's camera views, so the render loss sees
all of it); then the shapes and the experiment, with a volume-matched isosphere where the first
size does not fit. The shape is named after the file (or ``--name``), made a valid shape name
that no shape of the config has (``bunny.obj`` gives ``bunnymine``), and the path is quoted where
YAML needs it.
The mesh is repaired exactly as the prepare_mesh stage repairs it, so the volume is the one the
workflow will see (a mesh that is not watertight still gets a size). A mesh that cannot be used
(missing, unreadable, empty, flat, enclosing no volume, irreparable, too large) is refused in one
line on stderr naming the file and the reason, with exit status 2.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from dataclasses import dataclass, replace
from pathlib import Path

from typing import TYPE_CHECKING

import numpy as np
import yaml

from physmorph.base.grid import DOMAIN_HI, DOMAIN_LO, Grid

from .errors import REFUSED_STATUS, MeshError, exit_on_refusal, refusal_line
from .mesh_record import letter_volume, mesh_record

if TYPE_CHECKING:  # trimesh, the repair and the shapes load when a mesh is sized: the workflow's
    import trimesh  # volume warnings, asked at every snakemake start, need none of them


# Sizes are rounded down to this many domain units, so a printed size always fits.
SIZE_STEP = 0.1
# A target that fits at this share of the source's volume keeps the source as it is (a few per cent
# is inside what the morph's mass loss already forgives: the repair tolerance is the same 3 %).
VOLUME_SLACK = 0.03
# The silhouette keeps this many pixels from the image edge, so the edge pixels stay empty and the
# target stage's crop warning (physmorph.morph.targets.cropped_views) stays silent at the advised size.
VIEW_MARGIN_PX = 1.0


@dataclass(frozen=True)
class SizeAdvice:
    """What size a mesh needs: ``size_for_volume`` holds ``volume``; ``max_size`` is the largest
    size whose normalised mesh (volume centroid at the origin, as prepare_mesh places it) stays in
    the particles' region of a ``grid_res`` grid. ``size`` is the one to use; where the volume's
    size does not fit, ``source_size`` is the isosphere size that holds the target's volume at
    ``size``."""

    volume: float  # units^3 the target should hold (the source's)
    unit_volume: float  # the mesh's volume at size 1
    size_for_volume: float
    max_size: float
    grid_res: int
    region: tuple[float, float]  # the particles' region on each axis
    repair: tuple[str, ...]  # the repair steps prepare_mesh will log
    view_size: float = math.inf  # the largest size whose every vertex is inside every target view
    bodies: int = 1  # separate closed bodies after the repair

    @property
    def largest(self) -> float:
        """The largest size that fits both the particles' region and the target's views."""
        return min(self.max_size, self.view_size)

    @property
    def keeps_source(self) -> bool:
        """Whether the source can stay: the target fits at the source's volume, or within VOLUME_SLACK of it."""
        return self.target_volume >= (1.0 - VOLUME_SLACK) * self.volume

    @property
    def size(self) -> float:
        return min(self.size_for_volume, self.largest)

    @property
    def target_volume(self) -> float:
        """The target's volume at ``size``."""
        return self.unit_volume * self.size ** 3

    @property
    def source_size(self) -> float | None:
        return None if self.keeps_source else isosphere_size_for_volume(self.target_volume)


# A morph whose target holds more than this share more or less than its source's volume warns.
VOLUME_MISMATCH = 0.10


def volume_mismatch(experiment: str, source_volume: float, target_volume: float,
                    target_size: float | None = None, largest: float = math.inf,
                    volume_setting: str | None = None) -> str | None:
    """One line when a target holds more than VOLUME_MISMATCH more or less than its source's volume
    (None otherwise): MPM keeps volume, so such a target cannot be filled exactly. It names the
    experiment, the ratio and, with the target's configured ``target_size``, the size that holds the
    source's volume (the fit helper's ``size_for_volume``: volume scales with size^3), or where that
    is above ``largest`` (the largest size that fits the particles' region), a smaller source.
    ``volume_setting``: the run's plasticity.volume (None: a run without plasticity): keep names
    the setting that moves the body's rest volume to the target's; target says it does (the size
    that would hold the source's volume is named in every case)."""
    ratio = float(target_volume) / float(source_volume)
    if abs(ratio - 1.0) <= VOLUME_MISMATCH:
        return None
    head = (f"{experiment}: the target holds {100 * ratio:.0f} % of the source's volume ({target_volume:.0f} against "
            f"{source_volume:.0f} units^3)")
    if volume_setting == "target":
        text = f"{head}; plasticity.volume: target moves the body's rest volume there"
    else:
        text = f"{head}; MPM keeps volume, so the body cannot fill it exactly"
    if volume_setting == "keep":
        text += " (plasticity.volume: target, or an experiment's volume: target, moves its rest volume there)"
    if target_size:
        match = round(float(target_size) * ratio ** (-1.0 / 3.0) / SIZE_STEP) * SIZE_STEP
        if match > largest:
            held = 100 * ratio * (largest / float(target_size)) ** 3
            text += (f"; the largest target size that fits the grid, {largest:.1f}, holds {held:.0f} % of it: a smaller "
                     "source would match (python -m physmorph.meshes.fit MESH)")
        else:
            text += (f"; a target size of {match:.1f} (now {float(target_size):g}) would hold the source's volume "
                     "(python -m physmorph.meshes.fit MESH)")
    return text


def shape_volume(spec, prepared_h5: str | os.PathLike | None = None,
                 raw_path: str | os.PathLike | None = None) -> float | None:
    """A shape's volume at its configured size (``spec``: physmorph.settings.workflow.ShapeSettings) before any
    job: the prepared mesh's when ``prepared_h5`` exists and was made at that size, an isosphere's
    or a letter's from its formula and mesh, a raw mesh's when ``raw_path`` is on disk and closed
    (before the repair prepare_mesh applies; None when it is not, or not there yet)."""
    if prepared_h5 is not None and Path(prepared_h5).is_file():
        import h5py
        import json

        with h5py.File(prepared_h5, "r") as f:
            made = json.loads(str(f.attrs.get("config", "{}"))).get("shape", {})
            if made.get("size") == spec.size and made.get("kind") == spec.kind and "volume" in f.attrs:
                return float(f.attrs["volume"])
    if spec.kind == "isosphere":
        return isosphere_volume(spec.size)
    if spec.kind == "letter":
        return letter_volume(spec.glyph, spec.size, spec.depth)
    if raw_path is None or not Path(raw_path).is_file():
        return None
    unit = mesh_record(raw_path).unit_volume
    return None if unit is None else unit * spec.size ** 3


def raw_mesh_on_disk(settings, shape: str, root: str | os.PathLike = ".") -> Path | None:
    """The raw mesh of file shape ``shape`` where it is on disk before any job: its ``path``, the
    download in ``root``/resources/meshes/, or the mirror (``mesh_dir``); None for other kinds."""
    spec = settings.shape(shape)
    if spec.kind != "file":
        return None
    if spec.path is not None:
        return Path(spec.path)
    local = Path(root) / "resources" / "meshes" / spec.file
    return local if local.is_file() or not settings.mesh_dir else Path(settings.mesh_dir) / spec.file


def volume_warnings(settings, experiments, prepared_h5, raw_path, volumes: dict | None = None) -> list[str]:
    """volume_mismatch's line for each of ``experiments`` whose source and target volumes are known
    before any job (shape_volume; ``prepared_h5(shape)`` and ``raw_path(shape)`` give its files;
    ``volumes``: shape -> volume already found, filled in): what the workflow prints at DAG time."""
    volumes = {} if volumes is None else volumes
    lines = []
    for name in experiments:
        exp = settings.experiment(name)
        for shape in (exp.source, exp.target):
            if shape not in volumes:
                volumes[shape] = shape_volume(settings.shape(shape), prepared_h5(shape), raw_path(shape) or None)
        src, tgt = volumes[exp.source], volumes[exp.target]
        if src and tgt:
            raw = raw_path(exp.target)
            record = mesh_record(raw) if raw and Path(raw).is_file() else None
            largest = (region_size(record.unit_lo, record.unit_hi, settings.sampling.grid_res, settings.domain)
                       if record is not None and record.refusal is None else math.inf)
            line = volume_mismatch(name, src, tgt, settings.shape(exp.target).size, largest,
                                   settings.experiment_config(name).rest_volume_setting())
            if line:
                lines.append(line)
    return lines


def _floor_step(x: float) -> float:
    return math.floor(x / SIZE_STEP + 1e-9) * SIZE_STEP


def isosphere_volume(size: float) -> float:
    """Volume of the source isosphere of longest extent ``size`` (it scales as size^3)."""
    return isosphere_unit_volume() * size ** 3


def isosphere_unit_volume() -> float:
    """The volume of physmorph.meshes.shapes.isosphere at size 1 (radius 0.5): its 80 faces, the
    icosahedron's 20 each cut into 4 at the edges' midpoints pushed out to the sphere, summed as
    tetrahedra from the centre (the divergence theorem); numpy only, so no mesh library loads."""
    phi = (1.0 + 5.0 ** 0.5) / 2.0
    v = np.array([[-1, phi, 0], [1, phi, 0], [-1, -phi, 0], [1, -phi, 0], [0, -1, phi], [0, 1, phi], [0, -1, -phi],
                  [0, 1, -phi], [phi, 0, -1], [phi, 0, 1], [-phi, 0, -1], [-phi, 0, 1]], dtype=np.float64)
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
             (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11),
             (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    unit = lambda p: 0.5 * p / np.linalg.norm(p)  # noqa: E731  (on the sphere of radius 0.5)
    volume = 0.0
    for a, b, c in faces:
        A, B, C = unit(v[a]), unit(v[b]), unit(v[c])
        ab, bc, ca = unit(A + B), unit(B + C), unit(C + A)
        for tri in ((A, ab, ca), (ab, B, bc), (ca, bc, C), (ab, bc, ca)):
            volume += abs(float(np.linalg.det(np.array(tri)))) / 6.0
    return volume


def isosphere_size_for_volume(volume: float) -> float:
    """The isosphere size holding ``volume``, rounded to ``SIZE_STEP`` (nearest: a source is not
    bound by the region the way a long target is)."""
    s = (volume / isosphere_volume(1.0)) ** (1.0 / 3.0)
    return round(s / SIZE_STEP) * SIZE_STEP


def largest_size_in_views(unit: trimesh.Trimesh, cameras, upper: float, iterations: int = 40) -> float:
    """The largest size s <= ``upper`` at which every vertex of ``unit`` (the mesh at size 1, placed
    as prepare_mesh places it) scaled by s projects inside every view of ``cameras``, VIEW_MARGIN_PX
    from its edges (and in front of it). Perspective makes the test non-linear in s, so it is bisected; it is monotone because the
    cameras look at the origin, which the scaled mesh grows from."""
    m = VIEW_MARGIN_PX
    rotated = cameras.rotate(unit.vertices)  # [V, N, 3]: the camera frame of the scaled mesh is s R x + t
    shift = cameras.translation[:, None, :]

    def inside(size: float) -> bool:
        uv, z = cameras.project_camera(size * rotated + shift)
        return bool(np.all(z > 0) and np.all((uv[..., 0] >= m) & (uv[..., 0] <= cameras.width - m)
                                              & (uv[..., 1] >= m) & (uv[..., 1] <= cameras.height - m)))

    if inside(upper):
        return math.inf
    lo, hi = 0.0, upper
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if inside(mid) else (lo, mid)
    return _floor_step(lo)


def particle_region(grid_res: int, domain: tuple[float, float]) -> tuple[float, float]:
    """The part of each axis particles may occupy on a ``grid_res`` grid over ``domain``."""
    return Grid(int(grid_res), float(domain[0]), float(domain[1])).interior_bounds()


def region_limit(unit_lo, unit_hi, grid_res: int, domain: tuple[float, float] = (DOMAIN_LO, DOMAIN_HI)) -> float:
    """The size at which a shape whose size-1 bounds are ``unit_lo``..``unit_hi`` (3 values each,
    placed as prepare_mesh places it) touches the particles' region: at size s its bounds are s
    times those, and both faces of every axis must stay inside."""
    region = particle_region(grid_res, domain)
    return min([region[0] / v for v in unit_lo if v < 0] + [region[1] / v for v in unit_hi if v > 0])


def region_size(unit_lo, unit_hi, grid_res: int, domain: tuple[float, float] = (DOMAIN_LO, DOMAIN_HI)) -> float:
    """region_limit rounded down to a SIZE_STEP multiple: the largest size to advise."""
    return _floor_step(region_limit(unit_lo, unit_hi, grid_res, domain))


def advise_size(
    mesh: trimesh.Trimesh,
    volume: float,
    grid_res: int,
    domain: tuple[float, float] = (DOMAIN_LO, DOMAIN_HI),
    repair: tuple[str, ...] = (),
    cameras=None,
) -> SizeAdvice:
    """Size advice for a watertight ``mesh`` (any scale): see :class:`SizeAdvice`. With ``cameras``
    (physmorph.base.cameras.Cameras: the target's views) the size is also kept inside every view, so
    the render loss sees the whole target."""
    if not volume > 0:
        raise ValueError(f"volume must be > 0, got {volume!r}")
    from .prepare import normalize_mesh

    unit, _, _ = normalize_mesh(mesh, 1.0)
    unit_volume = abs(float(unit.volume))
    if not unit_volume > 0:
        raise ValueError("the mesh encloses no volume")
    region = particle_region(grid_res, domain)
    size_for_volume = _floor_step((volume / unit_volume) ** (1.0 / 3.0))
    max_size = region_size(*unit.bounds, grid_res, domain)
    view_size = math.inf if cameras is None else largest_size_in_views(unit, cameras, max(size_for_volume, max_size))
    return SizeAdvice(volume=float(volume), unit_volume=unit_volume, size_for_volume=size_for_volume,
                      max_size=max_size, grid_res=int(grid_res), region=region, repair=tuple(repair),
                      view_size=view_size)


def advise_size_for_file(
    path: str | os.PathLike,
    volume: float,
    grid_res: int,
    domain: tuple[float, float] = (DOMAIN_LO, DOMAIN_HI),
    volume_tolerance: float | None = None,
    cameras=None,
) -> SizeAdvice:
    """Load and repair ``path`` as prepare_mesh does, then :func:`advise_size`."""
    from .repair import DEFAULT_VOLUME_TOLERANCE, load_raw_mesh, repair_mesh

    raw = load_raw_mesh(path)
    repaired, steps, _ = repair_mesh(raw, str(path), volume_tolerance=volume_tolerance or DEFAULT_VOLUME_TOLERANCE)
    advice = replace(advise_size(repaired, volume, grid_res, domain, tuple(steps), cameras),
                     bodies=len(repaired.split(only_watertight=False)))
    if advice.largest < SIZE_STEP:  # a size of 0.0 would be printed, and refused by every stage after
        room = "the particles' region" + (" and the target's views" if math.isfinite(advice.view_size) else "")
        raise MeshError(f"{path}: too large for grid {int(grid_res)} in [{domain[0]:g}, {domain[1]:g}]^3: even at size "
                        f"{SIZE_STEP:g} it does not fit {room}")
    return advice


def shape_name(stem: str, taken=()) -> str:
    """A valid shape name (letters and digits, starting with a letter) from a file's stem (or a
    name asked for), not one of ``taken`` (the config's shapes): a clash gets "mine", then a number."""
    name = "".join(c for c in stem if c.isascii() and c.isalnum())
    name = name if name[:1].isalpha() else "mesh" + name
    if name not in taken:
        return name
    candidates = [f"{name}mine"] + [f"{name}mine{i}" for i in range(2, 100)]
    return next(c for c in candidates if c not in taken)


def shrunk_source_name(source: str, target: str) -> str:
    """The name of the isosphere ``source`` shrunk to ``target``'s volume: both run together, a valid
    shape name for valid ``source`` and ``target``, and one per target."""
    return f"{source}{target}"


def advice_text(advice: SizeAdvice, path: str, name: str, source: str, notes: tuple[str, ...] = ()) -> str:
    """The advice as a config file: what the helper found as YAML comments, then the shapes and the
    experiment (``notes``: further comment lines, e.g. a name that was changed)."""
    a = advice
    lines = [f"{path}: {'repaired (' + '; '.join(a.repair) + ')' if a.repair else 'watertight as read'}",
             f"  size for the source's volume ({a.volume:.0f} units^3): {a.size_for_volume:.1f}",
             f"  largest size that fits grid {a.grid_res} (particles stay in [{a.region[0]:g}, {a.region[1]:g}]^3): "
             f"{a.max_size:.1f}"]
    if math.isfinite(a.view_size):
        lines.append(f"  largest size every target view shows whole: {a.view_size:.1f}")
    if a.bodies > 1:
        lines.append(f"  warning: {a.bodies} separate bodies; the morph fills them as one shape, and one body morphs best")
    shapes = {name: {"kind": "file", "path": str(path), "size": round(a.size, 1)}}
    if a.keeps_source:
        if a.size < a.size_for_volume:
            lines.append(f"  at size {a.size:.1f} it holds {a.target_volume:.0f} units^3, within "
                         f"{100 * VOLUME_SLACK:.0f} % of the source's: the source stays")
        experiment_source = source
    else:
        # Named after its target, so two targets' blocks merge without one source overwriting the
        # other (shape names are letters and digits: isohomer, isorocker in config/outside.yaml).
        experiment_source = shrunk_source_name(source, name)
        lines.append(f"  the volume's size does not fit: at size {a.size:.1f} the mesh holds {a.target_volume:.0f} "
                     f"units^3, so the source shrinks to it (an isosphere of size {a.source_size:.1f})")
        shapes[experiment_source] = {"kind": "isosphere", "size": round(a.source_size, 1)}
    config = {"shapes": shapes,
              "experiments": {f"{experiment_source}_{name}": {"source": experiment_source, "target": name,
                                                               "method": "full"}}}
    comments = "".join(f"# {line}\n" for line in [*notes, *lines])
    # flow style per shape and experiment, quoted where YAML needs it (a path with ',' or '#')
    return comments + yaml.safe_dump(config, default_flow_style=None, sort_keys=False, width=1000)


def target_cameras(settings):
    """The target's views of ``settings`` (physmorph.settings.workflow.Settings): what a size must fit."""
    from physmorph.base.cameras import ring_cameras

    t = settings.target
    return ring_cameras(t.cameras, t.elevation_deg, t.fov_y_deg, t.width, t.height, t.distance, t.elevation_spread_deg)


def main(argv: list[str] | None = None) -> int:
    from physmorph.settings.errors import ConfigError
    from physmorph.settings.workflow import load_settings

    ap = argparse.ArgumentParser(prog="python -m physmorph.meshes.fit", description=__doc__.split("\n\n")[0])
    ap.add_argument("mesh", help="the mesh file (anything trimesh reads)")
    ap.add_argument("--configfile", nargs="+", default=["config/config.yaml"],
                    help="the profile's config files, merged as the workflow merges them (default: config/config.yaml)")
    ap.add_argument("--source", default="iso", help="the source shape whose volume the target should hold (default: iso)")
    ap.add_argument("--name", default=None, help="the shape's name in the printed YAML (default: the file's stem)")
    args = ap.parse_args(argv)

    try:
        settings = load_settings(*args.configfile)
    except ConfigError as exc:  # one line too, like a refused mesh
        print(refusal_line(exc, " + ".join(args.configfile)), file=sys.stderr)
        raise SystemExit(REFUSED_STATUS) from None
    if args.source not in settings.shapes:
        ap.error(f"--source {args.source!r} is not a shape of {' + '.join(args.configfile)} "
                 f"(shapes: {', '.join(sorted(settings.shapes))})")
    src = settings.shapes[args.source]
    if src.kind != "isosphere":
        ap.error(f"--source {args.source!r} is a {src.kind}; name an isosphere (the advice shrinks it when the mesh "
                 "does not fit)")
    volume = isosphere_volume(src.size)
    asked = args.name or Path(args.mesh).stem
    name = shape_name(asked, taken=set(settings.shapes))
    notes = () if name == asked else (
        f"the shape is named {name}: {asked!r} {'is a shape of the config' if asked in settings.shapes else 'is not a shape name (letters and digits, starting with a letter)'}",)
    cameras = target_cameras(settings)
    # A mesh that cannot be used ends in one line naming the file and the check it failed, status 2.
    advice = exit_on_refusal(lambda: advise_size_for_file(args.mesh, volume, settings.sampling.grid_res,
                                                          settings.domain, cameras=cameras), path=args.mesh)
    print(advice_text(advice, args.mesh, name, args.source, notes), end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
