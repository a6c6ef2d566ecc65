"""The config of a user's own morph: two shapes (a mesh file, a point cloud or a shipped shape's
name), sized so the target holds the source's volume inside the grid's particle region and the
target's views (the fit helper's answer, physmorph.meshes.fit), and one full-method experiment.

A shipped shape keeps its configured size. A file target is sized to the source's volume; where
that size does not fit, the target takes the largest size that fits and the source shrinks to the
target's volume (an isosphere, or the user's source mesh). A file source is sized to hold the
shipped target's volume, or the benchmark's (the config's isosphere ``iso``) when the target is a
file too.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from physmorph.meshes.errors import MeshError
from physmorph.meshes.fit import (
    VOLUME_SLACK,
    advise_size_for_file,
    isosphere_size_for_volume,
    isosphere_volume,
    shape_name,
    shape_volume,
    shrunk_source_name,
)

# the shape whose volume a file source holds when the target is a file too (the benchmark's volume)
REFERENCE_SHAPE = "iso"


@dataclass
class OwnShape:
    """One side of the morph: ``name`` in the config, ``entry`` its shapes entry to write (None: a
    shipped shape as configured), ``path`` the user's file (None: shipped)."""

    name: str
    path: Path | None = None
    entry: dict | None = None
    volume: float | None = None  # units^3 at its size, where known before any job
    largest: float = math.inf  # the largest size that fits (file shapes)


@dataclass
class OwnMorph:
    """The experiment and the shapes it adds, and what was found on the way (``notes``)."""

    experiment: str
    source: OwnShape
    target: OwnShape
    frames: int | None = None
    extra_shapes: dict[str, dict] = field(default_factory=dict)  # e.g. a shrunk isosphere source
    notes: list[str] = field(default_factory=list)

    def mapping(self) -> dict:
        shapes = {s.name: s.entry for s in (self.source, self.target) if s.entry is not None}
        shapes.update(self.extra_shapes)
        exp = {"source": self.source.name, "target": self.target.name, "method": "full"}
        if self.frames is not None:
            exp["frames"] = int(self.frames)
        return {"shapes": shapes, "experiments": {self.experiment: exp}}

    def config_text(self) -> str:
        """The config file: what was found as comments, then the shapes and the experiment."""
        head = [f"physmorph morph: {self.source.name} -> {self.target.name}, the experiment {self.experiment}",
                *self.notes]
        return "".join(f"# {line}\n" for line in head) + yaml.safe_dump(
            self.mapping(), default_flow_style=None, sort_keys=False, width=1000)


def is_file_argument(arg: str, settings) -> bool:
    """A file (it exists, or it has a suffix and names no shape) rather than a shipped shape's name."""
    return Path(arg).exists() or (arg not in settings.shapes and bool(Path(arg).suffix))


def _shipped(arg: str, role: str, settings, raw_mesh) -> OwnShape:
    if arg not in settings.shapes:
        raise MeshError(f"{role} '{arg}': no such file, and not a shape of the config (shapes: "
                        f"{', '.join(sorted(settings.shapes))})")
    spec = settings.shape(arg)
    return OwnShape(arg, volume=shape_volume(spec, None, raw_mesh(arg)))


def _fitted(path: Path, volume: float, settings, cameras) -> tuple[dict, float, float]:
    """(shapes entry, its volume, the largest size that fits) of ``path`` sized to hold ``volume``."""
    a = advise_size_for_file(path, volume, settings.sampling.grid_res, settings.domain, cameras=cameras)
    return {"kind": "file", "path": str(path.resolve()), "size": round(a.size, 1)}, a.target_volume, a.largest


def plan_own_morph(source: str, target: str, settings, cameras, raw_mesh, name: str | None = None,
                   size: float | None = None, frames: int | None = None) -> OwnMorph:
    """The morph ``source`` -> ``target`` (each a file or a shape of ``settings``); ``raw_mesh(shape)``
    is a shipped file shape's raw mesh where it is on disk (else None); ``size``: the target's size
    as asked (else fitted); ``name``: the experiment's (else source_target)."""
    taken = set(settings.shapes)
    sides: dict[str, OwnShape] = {}
    for role, arg in (("source", source), ("target", target)):
        if is_file_argument(arg, settings):
            path = Path(arg)
            sides[role] = OwnShape(shape_name(path.stem, taken), path=path)
            taken.add(sides[role].name)
        else:
            sides[role] = _shipped(arg, role, settings, raw_mesh)
    src, tgt = sides["source"], sides["target"]
    reference = isosphere_volume(settings.shape(REFERENCE_SHAPE).size) if REFERENCE_SHAPE in settings.shapes else 1170.0
    morph = OwnMorph(_experiment_name(name, src.name, tgt.name, settings), src, tgt, frames)
    if src.path is not None:  # sized to the shipped target's volume, or the benchmark's
        src.entry, src.volume, src.largest = _fitted(src.path, tgt.volume or reference, settings, cameras)
        morph.notes.append(f"{src.path}: source at size {src.entry['size']:.1f} ({src.volume:.0f} units^3)")
    if tgt.path is not None:
        _size_target(morph, src.volume or reference, settings, cameras, size)
    elif size is not None:
        raise MeshError(f"--size {size:g}: the target '{tgt.name}' is a shipped shape and keeps its configured size "
                        f"({settings.shape(tgt.name).size:g})")
    return morph


def _size_target(morph: OwnMorph, volume: float, settings, cameras, size: float | None) -> None:
    """The file target sized to ``volume`` (or to ``size``), shrinking the source where it cannot hold it."""
    src, tgt = morph.source, morph.target
    tgt.entry, tgt.volume, tgt.largest = _fitted(tgt.path, volume, settings, cameras)
    if size is not None:
        if size > tgt.largest:
            raise MeshError(f"{tgt.path}: size {size:g} does not fit the grid's particle region and the target's views "
                            f"(the largest size that fits: {tgt.largest:.1f})")
        tgt.volume *= (size / tgt.entry["size"]) ** 3
        tgt.entry["size"] = float(size)
        morph.notes.append(f"{tgt.path}: target at the size asked, {size:g} ({tgt.volume:.0f} units^3)")
        return
    morph.notes.append(f"{tgt.path}: target at size {tgt.entry['size']:.1f} ({tgt.volume:.0f} units^3; the largest "
                       f"size that fits: {tgt.largest:.1f})")
    if tgt.volume >= (1.0 - VOLUME_SLACK) * volume:
        return
    # the target cannot hold the source's volume inside the grid: the source shrinks to the target's
    if src.path is not None:
        src.entry, src.volume, src.largest = _fitted(src.path, tgt.volume, settings, cameras)
        morph.notes.append(f"the source shrinks to the target's volume: size {src.entry['size']:.1f}")
    elif settings.shape(src.name).kind == "isosphere":
        shrunk = shrunk_source_name(src.name, tgt.name)
        morph.extra_shapes[shrunk] = {"kind": "isosphere", "size": round(isosphere_size_for_volume(tgt.volume), 1)}
        morph.source = OwnShape(shrunk, entry=None, volume=tgt.volume)
        morph.notes.append(f"the source shrinks to the target's volume: {shrunk}, an isosphere of size "
                           f"{morph.extra_shapes[shrunk]['size']:.1f}")
    else:
        morph.notes.append(f"the target holds {100 * tgt.volume / volume:.0f} % of the source's volume: MPM keeps "
                           "volume, so the body cannot fill it exactly (a smaller source would)")


def _experiment_name(asked: str | None, source: str, target: str, settings) -> str:
    if asked is not None:
        if not re.fullmatch(r"[A-Za-z0-9_]+", asked) or asked == "index":
            raise MeshError(f"--name {asked!r}: an experiment name is letters, digits and _ (and not 'index')")
        if asked in settings.experiments:
            raise MeshError(f"--name {asked!r}: the config already has an experiment of that name")
        return asked
    base = f"{source}_{target}"
    candidates = [base] + [f"{base}_mine"] + [f"{base}_mine{i}" for i in range(2, 100)]
    return next(c for c in candidates if c not in settings.experiments)
