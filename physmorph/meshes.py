"""Stages 1-2: fetch raw benchmark meshes and turn them into clean, watertight, normalised solids.

fetch_mesh
    Download (or copy from a local mirror) one raw mesh file and verify its SHA-256. The file is
    written to ``<dest>.partial`` and renamed only after the checksum matches, so a failure never
    leaves a file that looks finished.

prepare_mesh
    Load an OBJ/GLB (or build a procedural shape: the isosphere, extruded letters), repair it into
    a watertight solid, centre its bounding box on the origin and scale its longest extent to
    ``ShapeSpec.size`` (the paper's assets are ~14-20 units across in the [-16, 16]^3 domain).

Repair order (the first step that yields a watertight mesh wins; every step is logged in the
output's ``repair`` attribute):

1. merge vertices ignoring UV/normal differences (Spot and Duck are split along UV seams),
   drop degenerate and duplicate faces, fix winding/normals, fill small holes (trimesh);
2. MeshFix (pymeshfix) for holes trimesh cannot close (the Bunny's base);
3. a generalized-winding-number remesh: marching cubes of the winding-number field of the
   triangle soup, which is well defined for open or self-intersecting input.

A repaired mesh must keep its volume within ``volume_tolerance`` of the raw mesh's
(divergence-theorem) volume, so a repair that silently drops components or caps a shape wrongly
is an error, not a quiet change of shape.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from physmorph.grid import DOMAIN_HI, DOMAIN_LO
from physmorph.h5io import StageInputError, atomic_h5, open_h5, read_attr, read_field

SHAPE_KINDS = ("file", "isosphere", "letter")
LETTER_GLYPHS = ("A", "S", "C")
# Letters are extruded to this fraction of their size unless ShapeSpec.depth says otherwise.
DEFAULT_LETTER_DEPTH_FRACTION = 0.3
# A repair may change the enclosed volume by at most this fraction (MeshFix on the Bunny: < 1 %).
DEFAULT_VOLUME_TOLERANCE = 0.03


class MeshError(ValueError):
    """A mesh cannot be used: the message names the file/shape and why."""


class FetchError(RuntimeError):
    """A raw mesh could not be fetched: unreachable URL, missing mirror file or checksum mismatch."""


# --------------------------------------------------------------------------------------------
# Stage 1: fetch
# --------------------------------------------------------------------------------------------

def sha256_of(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def fetch_mesh(
    filename: str,
    url: str,
    sha256: str,
    dest_dir: str | os.PathLike,
    mesh_dir: str | os.PathLike | None = None,
    timeout: float = 60.0,
) -> Path:
    """Put the raw mesh ``filename`` into ``dest_dir`` with its SHA-256 verified.

    With ``mesh_dir`` the file is copied from that local mirror; otherwise it is downloaded
    from ``url`` (any scheme urllib understands, file:// included). An existing destination
    with the right checksum is kept as is. Raises FetchError; nothing is left behind on failure.
    """
    if not filename or Path(filename).name != filename:
        raise FetchError(f"mesh filename must be a plain file name, got {filename!r}")
    expected = sha256.strip().lower()
    dest_dir = Path(dest_dir)
    dest = dest_dir / filename
    if dest.exists() and sha256_of(dest) == expected:
        return dest
    dest_dir.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(dest.name + ".partial")
    try:
        if mesh_dir is not None:
            src = Path(mesh_dir) / filename
            if not src.is_file():
                raise FetchError(f"{filename}: not found in mesh mirror {Path(mesh_dir)} (looked for {src})")
            shutil.copyfile(src, tmp)
            origin = str(src)
        else:
            origin = url
            try:
                with urllib.request.urlopen(url, timeout=timeout) as response, open(tmp, "wb") as out:
                    shutil.copyfileobj(response, out, length=1 << 20)
            except (urllib.error.URLError, OSError, ValueError) as exc:
                raise FetchError(f"{filename}: could not download {url} ({exc})") from exc
        actual = sha256_of(tmp)
        if actual != expected:
            raise FetchError(
                f"{filename}: checksum mismatch for {origin}: expected sha256 {expected}, got {actual}"
            )
        os.replace(tmp, dest)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return dest


# --------------------------------------------------------------------------------------------
# Stage 2: shapes
# --------------------------------------------------------------------------------------------

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


def load_raw_mesh(path: str | os.PathLike) -> trimesh.Trimesh:
    """Load an OBJ/GLB/... as one triangle mesh with scene transforms applied (the Duck's 0.01 scale)."""
    path = Path(path)
    if not path.is_file():
        raise MeshError(f"{path}: mesh file not found")
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise MeshError(f"{path}: cannot be read as a mesh ({type(exc).__name__}: {exc})") from exc
    if isinstance(loaded, trimesh.Scene):
        loaded = loaded.to_geometry() if len(loaded.geometry) else trimesh.Trimesh()
    if not isinstance(loaded, trimesh.Trimesh):
        raise MeshError(f"{path}: contains no triangle mesh (got {type(loaded).__name__})")
    if len(loaded.faces) == 0 or len(loaded.vertices) == 0:
        raise MeshError(f"{path}: mesh is empty (no faces)")
    if not np.all(np.isfinite(loaded.vertices)):
        raise MeshError(f"{path}: mesh has non-finite vertex coordinates")
    return trimesh.Trimesh(np.asarray(loaded.vertices, np.float64), np.asarray(loaded.faces, np.int64), process=False)


# --------------------------------------------------------------------------------------------
# Repair
# --------------------------------------------------------------------------------------------

def _solid_angles(query: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Signed solid angle of each triangle seen from each query point (Van Oosterom & Strackee 1983).

    query: [Q, 3], tri: [F, 3, 3]. Returns [Q, F]:
        tan(Omega / 2) = a.(b x c) / (|a||b||c| + (a.b)|c| + (b.c)|a| + (c.a)|b|),  a, b, c = v_k - q.
    """
    a = tri[None, :, 0, :] - query[:, None, :]
    b = tri[None, :, 1, :] - query[:, None, :]
    c = tri[None, :, 2, :] - query[:, None, :]
    la, lb, lc = (np.linalg.norm(v, axis=-1) for v in (a, b, c))
    det = np.einsum("qfi,qfi->qf", a, np.cross(b, c))
    den = la * lb * lc + np.einsum("qfi,qfi->qf", a, b) * lc + np.einsum("qfi,qfi->qf", b, c) * la \
        + np.einsum("qfi,qfi->qf", c, a) * lb
    return 2.0 * np.arctan2(det, den)


def winding_number(mesh: trimesh.Trimesh, query: np.ndarray, budget: int = 2_000_000) -> np.ndarray:
    """Generalized winding number w(q) = sum_f Omega_f(q) / (4 pi) (Jacobson et al. 2013).

    query: [Q, 3]. Returns [Q]: ~1 inside a closed outward-oriented surface, ~0 outside, and a
    smooth, still meaningful field for open or self-intersecting triangle soups.
    """
    query = np.asarray(query, dtype=np.float64).reshape(-1, 3)
    tri = np.asarray(mesh.triangles, dtype=np.float64)  # [F, 3, 3]
    out = np.zeros(len(query))
    step = max(1, budget // max(1, len(tri)))
    for s in range(0, len(query), step):
        out[s:s + step] = _solid_angles(query[s:s + step], tri).sum(axis=1) / (4.0 * np.pi)
    return out


# Directions for the ray-parity vote: irrational-ish so rays rarely graze edges or vertices.
_VOTE_DIRECTIONS = np.array([
    [0.5773, 0.5774, 0.5774], [-0.6325, 0.3162, 0.7071], [0.2673, -0.8018, 0.5345],
    [0.8165, 0.4082, -0.4082], [-0.3015, -0.3015, -0.9045], [0.1104, 0.9933, -0.0331],
    [-0.9487, 0.0, 0.3162],
])


def ray_parity_vote(mesh: trimesh.Trimesh, query: np.ndarray) -> np.ndarray:
    """Inside fraction [Q] of query: [Q, 3] over several ray directions (odd hit count = inside).

    For a mesh with holes a ray escaping through a hole miscounts; a majority over directions
    that mostly do not pass through the holes is robust. Uses Embree when embreex is installed.
    """
    query = np.asarray(query, dtype=np.float64).reshape(-1, 3)
    votes = np.zeros(len(query))
    for d in _VOTE_DIRECTIONS:
        d = d / np.linalg.norm(d)
        _, index_ray, _ = mesh.ray.intersects_location(query, np.broadcast_to(d, query.shape), multiple_hits=True)
        votes += np.bincount(index_ray, minlength=len(query)) % 2
    return votes / len(_VOTE_DIRECTIONS)


def remesh_winding_number(mesh: trimesh.Trimesh, resolution: int = 64, exact_budget: float = 5e7) -> trimesh.Trimesh:
    """Robust fallback repair: the 0.5 level set of an inside-ness field, by marching cubes.

    The field is sampled on a cubic lattice of ``resolution`` cells along the longest extent,
    padded by two cells so the extracted surface is closed. It is the exact generalized winding
    number when (lattice points x faces) <= ``exact_budget`` (cost O(points x faces)), otherwise
    the Embree ray-parity vote, its cheap approximation for large meshes.
    """
    from skimage.measure import marching_cubes

    lo, hi = mesh.bounds
    h = float(np.max(hi - lo)) / resolution
    if not h > 0:
        raise MeshError("winding-number remesh: mesh has zero extent")
    axes = [np.arange(lo[k] - 2 * h, hi[k] + 2.5 * h, h) for k in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    if len(pts) * len(mesh.faces) <= exact_budget:
        inside = winding_number(mesh, pts)
    else:
        inside = ray_parity_vote(mesh, pts)
    field = inside.reshape(tuple(len(a) for a in axes))
    if not (field.max() > 0.5 and field.min() < 0.5):
        raise MeshError("winding-number remesh: the surface encloses no volume (inside-ness never crosses 0.5)")
    verts, faces, _, _ = marching_cubes(field, level=0.5, spacing=(h, h, h))
    out = trimesh.Trimesh(verts + np.array([a[0] for a in axes]), faces, process=True)
    out.merge_vertices()
    trimesh.repair.fix_normals(out)
    return out


def _enclosed_volume(mesh: trimesh.Trimesh) -> float:
    """Volume enclosed by the mesh with every open boundary loop capped by a fan to its centroid.

    For a closed mesh this is the divergence-theorem volume sum_f det[v0, v1, v2] / 6. An open
    mesh's plain sum depends on the origin; capping each hole (as a repair would) makes it the
    well-defined reference the repaired volume is checked against.
    """
    if len(mesh.faces) == 0:
        return 0.0
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces, np.int64)
    volume = float(np.einsum("fi,fi->f", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0)
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])  # [3F, 2] oriented edges
    key = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = directed[counts[inverse.reshape(-1)] == 1]  # [B, 2] edges used by one face only
    if len(boundary):
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        n = len(v)
        graph = coo_matrix((np.ones(len(boundary)), (boundary[:, 0], boundary[:, 1])), shape=(n, n))
        _, label = connected_components(graph, directed=False)
        loop = label[boundary[:, 0]]
        sums = np.zeros((label.max() + 1, 3))
        cnt = np.zeros(label.max() + 1)
        np.add.at(sums, loop, v[boundary[:, 0]])
        np.add.at(cnt, loop, 1.0)
        centre = sums[loop] / cnt[loop][:, None]  # [B, 3] centroid of each edge's loop
        # Cap triangle (v1, v0, c) runs the boundary edge opposite to its face, as a closed surface needs.
        p0, p1 = v[boundary[:, 1]], v[boundary[:, 0]]
        volume += float(np.einsum("bi,bi->b", p0, np.cross(p1, centre)).sum() / 6.0)
    return abs(volume)


def repair_mesh(
    mesh: trimesh.Trimesh,
    label: str,
    volume_tolerance: float = DEFAULT_VOLUME_TOLERANCE,
    allow_remesh: bool = True,
) -> tuple[trimesh.Trimesh, list[str], float]:
    """Make ``mesh`` a watertight, consistently outward-oriented solid.

    Returns (repaired mesh, list of the repair steps applied, raw volume). Raises MeshError naming
    ``label`` when the mesh is empty, encloses no volume, or cannot be repaired without changing
    its volume by more than ``volume_tolerance``.
    """
    if len(mesh.faces) == 0:
        raise MeshError(f"{label}: mesh is empty (no faces)")
    extent = float(np.max(mesh.extents))
    if not extent > 0 or np.min(mesh.extents) <= 1e-9 * extent:
        raise MeshError(f"{label}: irreparable, mesh is flat (bounding box extents {mesh.extents.tolist()}), it encloses no volume")
    steps: list[str] = []
    m = mesh.copy()
    n_before = len(m.vertices)
    m.merge_vertices(merge_tex=True, merge_norm=True)
    if len(m.vertices) < n_before:
        steps.append(f"merge_vertices: {n_before} -> {len(m.vertices)} vertices")
    # Measured after merging: UV-seam splits are open boundaries in the raw file, not holes, and
    # capping them would distort the reference volume. Merging moves no vertex.
    raw_volume = _enclosed_volume(m)
    if raw_volume <= 1e-4 * extent ** 3:
        raise MeshError(
            f"{label}: irreparable, the raw mesh encloses no volume ({raw_volume:.3g} for a bounding box "
            f"{np.round(mesh.extents, 4).tolist()}); it is not the surface of a solid"
        )
    n_before = len(m.faces)
    m.update_faces(m.nondegenerate_faces())
    m.update_faces(m.unique_faces())
    m.remove_unreferenced_vertices()
    if len(m.faces) < n_before:
        steps.append(f"remove degenerate/duplicate faces: {n_before} -> {len(m.faces)}")
    if len(m.faces) == 0:
        raise MeshError(f"{label}: no non-degenerate faces")
    if not m.is_watertight:
        trimesh.repair.fill_holes(m)
        steps.append("fill_holes (trimesh)")
    trimesh.repair.fix_normals(m)

    if not _is_solid(m):
        import pymeshfix

        try:
            # Keep every component: dropping parts is caught below as lost volume, never silent.
            v, f = pymeshfix.clean_from_arrays(
                np.ascontiguousarray(m.vertices, np.float64), np.ascontiguousarray(m.faces, np.int32),
                remove_smallest_components=False,
            )
            fixed = trimesh.Trimesh(v, f, process=True)
            steps.append("pymeshfix")
            if len(fixed.faces):
                trimesh.repair.fix_normals(fixed)
                m = fixed
        except Exception as exc:  # MeshFix failing is an expected route to the fallback
            steps.append(f"pymeshfix failed ({type(exc).__name__})")
        if not _is_solid(m) or not _volume_ok(m, raw_volume, volume_tolerance):
            if not allow_remesh:
                raise MeshError(f"{label}: not watertight after trimesh and MeshFix repair")
            m = remesh_winding_number(mesh)
            steps.append("winding-number remesh (marching cubes)")

    if not _is_solid(m):
        raise MeshError(f"{label}: irreparable, still not watertight after {', '.join(steps)}")
    if not _volume_ok(m, raw_volume, volume_tolerance):
        raise MeshError(
            f"{label}: irreparable, repair changed the volume from {raw_volume:.6g} to {m.volume:.6g} "
            f"(more than {100 * volume_tolerance:.0f} %; steps: {', '.join(steps) or 'none'})"
        )
    return m, steps, raw_volume


def _is_solid(m: trimesh.Trimesh) -> bool:
    return bool(len(m.faces) and m.is_watertight and m.is_winding_consistent and m.volume > 0)


def _volume_ok(m: trimesh.Trimesh, raw_volume: float, tol: float) -> bool:
    return raw_volume > 0 and abs(float(m.volume) - raw_volume) <= tol * raw_volume


def normalize_mesh(mesh: trimesh.Trimesh, size: float) -> tuple[trimesh.Trimesh, float, np.ndarray]:
    """Put the volume centroid at the origin and scale the longest extent to ``size``.

    The centroid, not the bounding-box centre: the morph's control acts through internal
    stress, which cannot move a body's centre of mass, so source and target must share it.
    Returns (mesh, scale, translation) with x_new = scale * x_old + translation.
    """
    lo, hi = mesh.bounds
    scale = float(size / np.max(hi - lo))
    centroid = np.asarray(mesh.center_mass if mesh.is_volume else 0.5 * (lo + hi), dtype=np.float64)
    translation = -scale * centroid
    out = mesh.copy()
    out.apply_transform(np.diag([scale, scale, scale, 1.0]))
    out.apply_translation(translation)
    return out, scale, translation


def prepare_mesh(
    spec: ShapeSpec,
    raw_path: str | os.PathLike | None,
    out_h5: str | os.PathLike,
    domain: tuple[float, float] = (DOMAIN_LO, DOMAIN_HI),
    volume_tolerance: float = DEFAULT_VOLUME_TOLERANCE,
    raw_sha256: str | None = None,
) -> dict:
    """Stage prepare_mesh: raw mesh or procedural shape -> watertight normalised mesh HDF5.

    ``raw_sha256``: the raw mesh's published checksum; the file is verified against it before it
    is read (it may have changed since it was fetched). Output layout: /vertices [V, 3] f64,
    /faces [F, 3] i64; attrs shape, kind, source, volume, raw_volume (in normalised units),
    scale, translation, repair (JSON list), watertight, domain_lo, domain_hi. Returns a summary dict.
    """
    prepared_sha256 = ""
    if spec.kind == "file":
        if raw_path is None:
            raise MeshError(f"shape '{spec.name}': kind 'file' needs the raw mesh path")
        if raw_sha256 is not None:
            expected, actual = raw_sha256.strip().lower(), sha256_of(raw_path)
            if actual != expected:
                raise MeshError(f"{raw_path} (shape '{spec.name}'): no longer matches its checksum (expected sha256 "
                                f"{expected}, got {actual}): it changed after it was fetched; delete it and rerun, "
                                "and it is fetched again")
        label = f"{raw_path} (shape '{spec.name}')"
        raw = load_raw_mesh(raw_path)
        source = Path(raw_path).name
        prepared_sha256 = sha256_of(raw_path)  # provenance: which bytes were prepared (a mesh given by path has no pinned sum)
    elif spec.kind == "isosphere":
        label = f"shape '{spec.name}' (isosphere)"
        raw = isosphere(radius=spec.size / 2.0)
        source = "procedural:isosphere(subdivisions=1)"
    else:
        label = f"shape '{spec.name}' (letter {spec.glyph!r})"
        raw = letter_mesh(spec.glyph, spec.size, spec.depth)
        source = f"procedural:letter({spec.glyph}, DejaVu Sans)"

    repaired, steps, raw_volume = repair_mesh(raw, label, volume_tolerance=volume_tolerance)
    mesh, scale, translation = normalize_mesh(repaired, spec.size)
    lo, hi = float(domain[0]), float(domain[1])
    if np.any(mesh.bounds[0] < lo) or np.any(mesh.bounds[1] > hi):
        raise MeshError(f"{label}: normalised mesh (size {spec.size}) does not fit the domain [{lo}, {hi}]^3")
    if not mesh.is_watertight:  # scaling cannot break this; cheap guard against future edits
        raise MeshError(f"{label}: not watertight after normalisation")

    summary = {
        "shape": spec.name,
        "kind": spec.kind,
        "source": source,
        "raw_sha256": prepared_sha256,
        "volume": float(mesh.volume),
        "raw_volume": float(raw_volume * scale ** 3),
        "scale": scale,
        "watertight": bool(mesh.is_watertight),
        "n_vertices": int(len(mesh.vertices)),
        "n_faces": int(len(mesh.faces)),
        "n_components": int(len(mesh.split(only_watertight=False))),
        "repair": steps,
    }
    config = {"shape": {k: getattr(spec, k) for k in ("name", "kind", "file", "glyph", "size", "depth")},
              "domain": [lo, hi], "volume_tolerance": volume_tolerance}
    with atomic_h5(out_h5, config=config) as f:
        f.create_dataset("vertices", data=np.asarray(mesh.vertices, np.float64))
        f.create_dataset("faces", data=np.asarray(mesh.faces, np.int64))
        for key in ("shape", "kind", "source", "raw_sha256", "volume", "raw_volume", "scale", "watertight", "n_components"):
            f.attrs[key] = summary[key]
        f.attrs["translation"] = np.asarray(translation, np.float64)
        f.attrs["repair"] = json.dumps(steps)
        f.attrs["domain_lo"] = lo
        f.attrs["domain_hi"] = hi
    return summary


def load_mesh(path: str | os.PathLike) -> trimesh.Trimesh:
    """The mesh stored by prepare_mesh; StageInputError on a missing/corrupt file or field.

    The shape name and domain are put in ``mesh.metadata`` ("shape", "domain").
    """
    with open_h5(path) as f:
        vertices = read_field(f, "vertices", (3,)).astype(np.float64)
        faces = read_field(f, "faces", (3,)).astype(np.int64)
        shape = str(read_attr(f, "shape"))
        domain = (float(f.attrs.get("domain_lo", DOMAIN_LO)), float(f.attrs.get("domain_hi", DOMAIN_HI)))
    if vertices.ndim != 2 or faces.ndim != 2 or len(faces) == 0:
        raise StageInputError(f"{path}: field 'faces' is empty or malformed")
    if not np.all(np.isfinite(vertices)):
        raise StageInputError(f"{path}: field 'vertices' has non-finite values")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise StageInputError(f"{path}: field 'faces' indexes outside 'vertices'")
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    mesh.metadata["shape"] = shape
    mesh.metadata["domain"] = domain
    return mesh
