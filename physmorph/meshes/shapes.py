"""Shape specifications and the procedural shapes: the paper's isosphere and extruded letters."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from .errors import MeshError

SHAPE_KINDS = ("file", "isosphere", "letter")
LETTER_GLYPHS = ("A", "S", "C")
# Letters are extruded to this fraction of their size unless ShapeSpec.depth says otherwise.
DEFAULT_LETTER_DEPTH_FRACTION = 0.3


@dataclass(frozen=True)
class ShapeSpec:
    """One entry of the config's ``shapes:`` mapping."""

    name: str
    kind: str  # "file" | "isosphere" | "letter"
    file: str | None = None  # raw mesh filename (kind=file)
    glyph: str | None = None  # "A", "S", "C" (kind=letter)
    size: float = 16.0  # longest bounding-box extent after normalisation (isosphere: 2 * radius)
    depth: float | None = None  # letter extrusion depth (default DEFAULT_LETTER_DEPTH_FRACTION * size)

    def __post_init__(self) -> None:
        if self.kind not in SHAPE_KINDS:
            raise MeshError(f"shape '{self.name}': unknown kind {self.kind!r} (expected one of {SHAPE_KINDS})")
        if self.kind == "file" and not self.file:
            raise MeshError(f"shape '{self.name}': kind 'file' needs a 'file'")
        if self.kind == "letter" and (not self.glyph or len(self.glyph) != 1):
            raise MeshError(f"shape '{self.name}': kind 'letter' needs a single-character 'glyph', got {self.glyph!r}")
        if not (np.isfinite(self.size) and self.size > 0):
            raise MeshError(f"shape '{self.name}': size must be a positive number, got {self.size!r}")
        if self.depth is not None and not (np.isfinite(self.depth) and self.depth > 0):
            raise MeshError(f"shape '{self.name}': depth must be a positive number, got {self.depth!r}")


def isosphere(radius: float = 7.0) -> trimesh.Trimesh:
    """The paper's source shape: a once-subdivided icosahedron (80 faces) with vertices at ``radius``."""
    return trimesh.creation.icosphere(subdivisions=1, radius=radius)


def _glyph_polygon(glyph: str, draw_size: float = 1000.0):
    """The glyph's outline as a shapely (Multi)Polygon in the xy plane.

    The glyph is drawn large because matplotlib flattens Bezier curves to segments at a fixed
    absolute tolerance: a small glyph would get a coarse, faceted outline.
    """
    from matplotlib.font_manager import FontProperties
    from matplotlib.textpath import TextPath
    from shapely.geometry import Polygon
    from shapely.ops import unary_union

    path = TextPath((0.0, 0.0), glyph, size=draw_size, prop=FontProperties(family="DejaVu Sans"))
    rings = [Polygon(r) for r in path.to_polygons() if len(r) >= 4]
    rings = [r.buffer(0) if not r.is_valid else r for r in rings]
    rings = [r for r in rings if r.area > 0]
    if not rings:
        raise MeshError(f"letter {glyph!r}: the font has no outline for this glyph")
    # Even-odd nesting: a ring inside an odd number of other rings is a hole (the A's counter).
    depth_of = [sum(1 for j, o in enumerate(rings) if j != i and o.contains(r)) for i, r in enumerate(rings)]
    solids = []
    for i, r in enumerate(rings):
        if depth_of[i] % 2 == 0:
            holes = [h for j, h in enumerate(rings) if depth_of[j] == depth_of[i] + 1 and r.contains(h)]
            solids.append(r.difference(unary_union(holes)) if holes else r)
    return unary_union(solids)


def letter_mesh(glyph: str, size: float, depth: float | None = None) -> trimesh.Trimesh:
    """An extruded letter: the glyph's longest 2D extent is ``size``, extruded ``depth`` along z."""
    from shapely import affinity

    poly = _glyph_polygon(glyph)
    minx, miny, maxx, maxy = poly.bounds
    scale = size / max(maxx - minx, maxy - miny)
    poly = affinity.scale(poly, xfact=scale, yfact=scale, origin=(0.0, 0.0))
    depth = DEFAULT_LETTER_DEPTH_FRACTION * size if depth is None else depth
    parts = list(poly.geoms) if hasattr(poly, "geoms") else [poly]
    meshes = [trimesh.creation.extrude_polygon(p, height=depth) for p in parts]
    return trimesh.util.concatenate(meshes) if len(meshes) > 1 else meshes[0]
