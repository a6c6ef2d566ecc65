"""Loading raw meshes and repairing them into watertight solids (the order is in
physmorph.meshes' docstring); a repair that changes the volume by more than its tolerance fails."""

from __future__ import annotations

import os
import sys
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import trimesh

from .errors import MeshError

# A repair may change the enclosed volume by at most this fraction (MeshFix on the Bunny: < 1 %).
DEFAULT_VOLUME_TOLERANCE = 0.03
# Coordinates beyond this cannot be cubed into a volume in double precision (~1.8e308).
MAX_COORDINATE = 1e100


def load_raw_mesh(path: str | os.PathLike) -> trimesh.Trimesh:
    """Load an OBJ/GLB/... as one triangle mesh with scene transforms applied (the Duck's 0.01 scale)."""
    path = Path(path)
    if path.is_dir():
        raise MeshError(f"{path}: is a folder, not a mesh file")
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
        return _surface_of_points(path)
    if not np.all(np.isfinite(loaded.vertices)):
        raise MeshError(f"{path}: mesh has non-finite vertex coordinates")
    return trimesh.Trimesh(np.asarray(loaded.vertices, np.float64), np.asarray(loaded.faces, np.int64), process=False)


def _surface_of_points(path: Path) -> trimesh.Trimesh:
    """A file with points and no faces is a point cloud: its closed surface (physmorph.meshes.point_cloud),
    with ``metadata["points"]`` its point count; a file with nothing in it says so (trimesh's text
    readers skip bytes that are not a mesh, rather than raise)."""
    from .point_cloud import surface_from_points

    try:
        points = np.asarray(getattr(trimesh.load(path, process=False), "vertices", ()), np.float64).reshape(-1, 3)
    except Exception:  # the first read succeeded; a second one failing says no more
        points = np.zeros((0, 3))
    if not len(points):
        raise MeshError(f"{path}: cannot be read as a mesh (no vertices or faces in its {path.stat().st_size} bytes)")
    if not np.all(np.isfinite(points)):
        raise MeshError(f"{path}: point cloud has non-finite coordinates")
    mesh = surface_from_points(points, str(path))
    mesh.metadata["points"] = len(points)
    return mesh


def _solid_angles(query: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed solid angle of each triangle seen from each query point (Van Oosterom & Strackee 1983).

    query: [Q, 3], tri: [F, 3, 3]. Returns (Omega [Q, F], on [Q]: the point lies on a triangle):
        tan(Omega / 2) = a.(b x c) / (|a||b||c| + (a.b)|c| + (b.c)|a| + (c.a)|b|),  a, b, c = v_k - q.
    """
    a = tri[None, :, 0, :] - query[:, None, :]
    b = tri[None, :, 1, :] - query[:, None, :]
    c = tri[None, :, 2, :] - query[:, None, :]
    la, lb, lc = (np.linalg.norm(v, axis=-1) for v in (a, b, c))
    det = np.einsum("qfi,qfi->qf", a, np.cross(b, c))
    den = la * lb * lc + np.einsum("qfi,qfi->qf", a, b) * lc + np.einsum("qfi,qfi->qf", b, c) * la \
        + np.einsum("qfi,qfi->qf", c, a) * lb
    # In the triangle's plane den > 0 outside it, < 0 inside, 0 on its edges: there the angle is
    # +-2 pi by the sign of a rounding error, so it is taken as 0 (a point on a smooth closed surface
    # then gets w = 1/2) and the point is reported, for callers that know better what it is.
    scale = 1e-12 * la * lb * lc
    on = (np.abs(det) <= scale) & (den <= scale)
    return np.where(on, 0.0, 2.0 * np.arctan2(det, den)), on.any(axis=1)


def winding_number(mesh: trimesh.Trimesh, query: np.ndarray, budget: int = 2_000_000,
                   surface_value: float | None = None) -> np.ndarray:
    """Generalized winding number w(q) = sum_f Omega_f(q) / (4 pi) (Jacobson et al. 2013).

    query: [Q, 3]. Returns [Q]: ~1 inside a closed outward-oriented surface, ~0 outside, and a
    smooth, still meaningful field for open or self-intersecting triangle soups. A point on the
    surface itself gets ``surface_value`` when given (else 1/2 on a smooth part, less at an edge).
    """
    query = np.asarray(query, dtype=np.float64).reshape(-1, 3)
    tri = np.asarray(mesh.triangles, dtype=np.float64)  # [F, 3, 3]
    out = np.zeros(len(query))
    step = max(1, budget // max(1, len(tri)))
    for s in range(0, len(query), step):
        omega, on = _solid_angles(query[s:s + step], tri)
        out[s:s + step] = omega.sum(axis=1) / (4.0 * np.pi)
        if surface_value is not None:
            out[s:s + step][on] = surface_value
    return out


# Directions for the ray vote: irrational-ish so rays rarely graze edges or vertices.
_VOTE_DIRECTIONS = np.array([
    [0.5773, 0.5774, 0.5774], [-0.6325, 0.3162, 0.7071], [0.2673, -0.8018, 0.5345],
    [0.8165, 0.4082, -0.4082], [-0.3015, -0.3015, -0.9045], [0.1104, 0.9933, -0.0331],
    [-0.9487, 0.0, 0.3162],
])
# Field values this close to the remesh's 0.5 level are pushed off it: a lattice point on the surface
# (w = 0.5 exactly on a face, e.g. a box's side on the lattice) makes marching cubes put vertices on
# lattice points, where triangles of neighbouring cells meet degenerate and non-manifold.
_LEVEL_GAP = 1e-3


def ray_crossings(mesh: trimesh.Trimesh, query: np.ndarray) -> np.ndarray:
    """Signed surface crossings [Q, D] of a ray from each of query: [Q, 3] along each _VOTE_DIRECTIONS.

    A hit through a face whose normal points along the ray is an exit (+1), against it an entry (-1):
    from an outward-oriented surface the sum is the winding number (0 outside, 1 inside, 2 inside two
    overlapping shells, where hit parity says "outside"). A ray escaping through a hole miscounts, so
    callers vote over the directions. Uses Embree when embreex is installed.
    """
    query = np.asarray(query, dtype=np.float64).reshape(-1, 3)
    normals = np.asarray(mesh.face_normals, np.float64)  # [F, 3]
    out = np.zeros((len(query), len(_VOTE_DIRECTIONS)))
    for k, d in enumerate(_VOTE_DIRECTIONS):
        d = d / np.linalg.norm(d)
        _, index_ray, index_tri = mesh.ray.intersects_location(query, np.broadcast_to(d, query.shape),
                                                                multiple_hits=True)
        out[:, k] = np.bincount(index_ray, weights=np.sign(normals[index_tri] @ d), minlength=len(query))
    return out


def ray_winding_vote(mesh: trimesh.Trimesh, query: np.ndarray) -> np.ndarray:
    """Inside fraction [Q] of query: [Q, 3]: the share of ray directions along which the point is
    inside (ray_crossings > 0). For a mesh with holes a majority over directions that mostly miss
    the holes is robust; for self-intersecting shells the signed count, unlike parity, stays inside."""
    return (ray_crossings(mesh, query) > 0.5).mean(axis=1)


def _oriented(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """A copy with coincident vertices merged, each connected patch wound consistently and the whole
    turned so its capped volume is positive. The winding number and the signed ray crossings count
    with the faces' orientation: an inside-out file would read as all outside (w ~ -1), and a patch
    split along UV seams cannot be made consistent until its seams are merged."""
    m = trimesh.Trimesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64), process=False)
    m.merge_vertices(merge_tex=True, merge_norm=True)
    trimesh.repair.fix_winding(m)
    if _enclosed_volume(m, signed=True) < 0:
        m.invert()
    return m


def _inside_field(mesh: trimesh.Trimesh, resolution: int, exact_budget: float
                  ) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The inside-ness of an outward-oriented ``mesh`` on a cubic lattice of ``resolution`` cells
    along its longest extent, two cells beyond its bounds: (field [X, Y, Z] whose 0.5 level is the
    surface, lattice origin [3], spacing h, multiplicity excess). The excess is the integral of
    w - clip(w, 0, 1): the volume the divergence-theorem volume counts twice where shells overlap
    (or negatively where a part is inside out), which the remeshed solid holds once (or not at all).
    """
    lo, hi = mesh.bounds
    h = float(np.max(hi - lo)) / resolution
    if not h > 0:
        raise MeshError("winding-number remesh: mesh has zero extent")
    axes = [np.arange(lo[k] - 2 * h, hi[k] + 2.5 * h, h) for k in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)  # [Q, 3]
    if len(pts) * len(mesh.faces) <= exact_budget:
        # A lattice point on the surface is on the level: the surface then runs through it, where w
        # itself (1/4 on a box's edge, 1/8 at a corner) would cut the edges off a box on the lattice.
        field = winding_number(mesh, pts, surface_value=0.5)
        multiplicity = field
    else:
        crossings = ray_crossings(mesh, pts)  # [Q, D]
        field = (crossings > 0.5).mean(axis=1)
        multiplicity = np.median(crossings, axis=1)
    excess = float((multiplicity - np.clip(multiplicity, 0.0, 1.0)).sum() * h ** 3)
    origin = np.array([a[0] for a in axes])
    return field.reshape(tuple(len(a) for a in axes)), origin, h, excess


def remesh_winding_number(mesh: trimesh.Trimesh, resolution: int = 64, exact_budget: float = 5e7) -> trimesh.Trimesh:
    """Robust fallback repair: the 0.5 level set of an inside-ness field, by marching cubes.

    The field (see _inside_field) is the exact generalized winding number when (lattice points x
    faces) <= ``exact_budget`` (cost O(points x faces)), otherwise the Embree ray vote, its cheap
    approximation for large meshes; ``mesh`` is oriented outward first (_oriented). The result is
    closed, consistently wound and of positive volume for any field with an inside: the lattice is
    padded by a layer held outside (a ray vote can call the lattice's own boundary inside, which
    would leave the surface open there), no value sits on the level, and marching cubes' own shared
    vertices are kept (merging by position would glue the surface where it passes a lattice point).
    ``out.metadata["overlap_volume"]`` is the field's multiplicity excess (_inside_field).
    """
    from skimage.measure import marching_cubes

    field, origin, h, excess = _inside_field(_oriented(mesh), resolution, exact_budget)
    if not (field.max() > 0.5 and field.min() < 0.5):
        raise MeshError("winding-number remesh: the surface encloses no volume (inside-ness never crosses 0.5)")
    field = np.pad(field, 1, constant_values=0.0)
    near = np.abs(field - 0.5) < _LEVEL_GAP
    field[near] = np.where(field[near] >= 0.5, 0.5 + _LEVEL_GAP, 0.5 - _LEVEL_GAP)
    verts, faces, _, _ = marching_cubes(field, level=0.5, spacing=(h, h, h))
    out = trimesh.Trimesh(verts + (origin - h), faces, process=False)
    if out.volume < 0:  # marching cubes winds its triangles by its own axis convention
        out.invert()
    out.metadata["overlap_volume"] = excess
    return out


def _enclosed_volume(mesh: trimesh.Trimesh, signed: bool = False) -> float:
    """Volume enclosed by the mesh with every open boundary loop capped by a fan to its centroid
    (its magnitude; with ``signed``, negative for an inside-out mesh).

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
    return volume if signed else abs(volume)


def _check_input(mesh: trimesh.Trimesh, label: str) -> float:
    """The longest bounding-box extent of a mesh a repair can work on; MeshError naming ``label``
    for an empty, too large (coordinates whose cube overflows) or flat one."""
    if len(mesh.faces) == 0:
        raise MeshError(f"{label}: mesh is empty (no faces)")
    largest = float(np.max(np.abs(mesh.vertices)))
    if not largest <= MAX_COORDINATE:
        raise MeshError(f"{label}: too large, coordinates reach {largest:.3g} (at most {MAX_COORDINATE:.0e}: its "
                        "volume overflows double precision); rescale it")
    extent = float(np.max(mesh.extents))
    if not extent > 0 or np.min(mesh.extents) <= 1e-9 * extent:
        raise MeshError(f"{label}: irreparable, mesh is flat (bounding box extents {mesh.extents.tolist()}), it encloses no volume")
    return extent


def _clean(mesh: trimesh.Trimesh, label: str, extent: float, steps: list[str]) -> tuple[trimesh.Trimesh, float]:
    """The trimesh step (merge, drop degenerate/duplicate faces, fill small holes, fix normals):
    (mesh, raw volume); MeshError when the raw mesh encloses no volume."""
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
        raise MeshError(f"{label}: irreparable, no non-degenerate faces")
    if not m.is_watertight:
        trimesh.repair.fill_holes(m)
        steps.append("fill_holes (trimesh)")
    trimesh.repair.fix_normals(m)
    return m, raw_volume


@contextmanager
def _quiet_stdio():
    """Silence file descriptors 1 and 2: MeshFix prints from C++ ("MeshFix could not fix everything"),
    past Python's sys.stderr, and a refusal is to be the one line on stderr."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (*saved, devnull):
            os.close(fd)


def _meshfix(m: trimesh.Trimesh, steps: list[str]) -> trimesh.Trimesh:
    """MeshFix's repair of ``m`` (``m`` itself when MeshFix fails or leaves nothing)."""
    import pymeshfix

    try:
        # Keep every component: dropping parts is caught as lost volume, never silent.
        with _quiet_stdio():
            v, f = pymeshfix.clean_from_arrays(
                np.ascontiguousarray(m.vertices, np.float64), np.ascontiguousarray(m.faces, np.int32),
                remove_smallest_components=False,
            )
        fixed = trimesh.Trimesh(v, f, process=True)
        steps.append("pymeshfix")
        if len(fixed.faces):
            trimesh.repair.fix_normals(fixed)
            return fixed
    except Exception as exc:  # MeshFix failing is an expected route to the fallback
        steps.append(f"pymeshfix failed ({type(exc).__name__})")
    return m


def repair_mesh(
    mesh: trimesh.Trimesh,
    label: str,
    volume_tolerance: float = DEFAULT_VOLUME_TOLERANCE,
    allow_remesh: bool = True,
) -> tuple[trimesh.Trimesh, list[str], float]:
    """Make ``mesh`` a watertight, consistently outward-oriented solid.

    Returns (repaired mesh, list of the repair steps applied, raw volume: the raw mesh's capped
    volume, less what it counts twice where it overlaps itself when the remesh measured that).
    Raises MeshError naming ``label`` and the check that failed when the mesh is empty, too large,
    encloses no volume, or cannot be repaired without changing its volume by more than
    ``volume_tolerance``.
    """
    extent = _check_input(mesh, label)
    steps: list[str] = []
    if "points" in mesh.metadata:  # a point cloud's surface (load_raw_mesh)
        steps.append(f"surface of {mesh.metadata['points']} points (marching cubes on their signed distance)")
    m, raw_volume = _clean(mesh, label, extent, steps)
    open_edges = boundary_edges(m)
    reference, note = raw_volume, ""
    if solid_problem(m) is not None:
        cleaned = m
        m = _meshfix(cleaned, steps)
        if solid_problem(m) is not None or not _volume_ok(m, raw_volume, volume_tolerance):
            if not allow_remesh:
                raise MeshError(f"{label}: irreparable, {solid_problem(m) or _volume_change(m, raw_volume)} "
                                "after trimesh and MeshFix repair")
            try:
                m = remesh_winding_number(cleaned)
            except MeshError as exc:
                raise MeshError(f"{label}: irreparable, {exc} (after {', '.join(steps)})") from exc
            steps.append("winding-number remesh (marching cubes)")
            overlap = float(m.metadata.get("overlap_volume", 0.0))
            if abs(overlap) > 1e-6 * raw_volume:
                reference = raw_volume - overlap
                note = f" (the raw mesh's {raw_volume:.6g} less {overlap:.6g} it counts twice where it overlaps itself)"

    problem = solid_problem(m)
    if problem is not None:
        raise MeshError(f"{label}: irreparable, {problem} after {', '.join(steps)}")
    if not _volume_ok(m, reference, volume_tolerance):
        if open_edges:  # the volume of an open surface is not its shape's: say so, and what to do
            raise MeshError(
                f"{label}: the mesh is open ({open_edges} edges on a hole's rim), and closing it "
                f"{_volume_change(m, reference).removeprefix('repair ')} (more than {100 * volume_tolerance:.0f} %): "
                "close its holes in a mesh editor (e.g. MeshLab's Close Holes, Blender's 3D-Print Make Manifold) "
                "and give the closed mesh")
        raise MeshError(
            f"{label}: irreparable, {_volume_change(m, reference)}{note} "
            f"(more than {100 * volume_tolerance:.0f} %; steps: {', '.join(steps) or 'none'})"
        )
    return m, steps, reference


def boundary_edges(m: trimesh.Trimesh) -> int:
    """Edges that only one face uses: the rims of the surface's holes (0 for a closed surface)."""
    if not len(m.faces):
        return 0
    _, counts = np.unique(np.sort(m.edges, axis=1), axis=0, return_counts=True)
    return int((counts == 1).sum())


def solid_problem(m: trimesh.Trimesh) -> str | None:
    """The first check ``m`` fails as a solid, in words (None when it is closed, consistently wound
    and of positive volume): what a refusal names."""
    if len(m.faces) == 0:
        return "no faces"
    edges = np.sort(np.asarray(m.edges), axis=1)  # [3F, 2] one row per face's edge
    _, counts = np.unique(edges, axis=0, return_counts=True)
    n_open, n_many = int(np.sum(counts == 1)), int(np.sum(counts > 2))
    if n_open or n_many or not m.is_watertight:
        parts = ([f"{n_open} open edges"] if n_open else []) + (
            [f"{n_many} edges shared by more than two faces"] if n_many else [])
        return "not watertight: " + (" and ".join(parts) or "edges not paired")
    if not m.is_winding_consistent:
        return "inconsistent winding"
    volume = float(m.volume)
    if volume < 0:
        return f"negative volume ({volume:.3g}: inside out)"
    if not volume > 0:
        return "zero volume"
    return None


def _volume_change(m: trimesh.Trimesh, reference: float) -> str:
    return f"repair changed the volume from {reference:.6g} to {float(m.volume):.6g}"


def _volume_ok(m: trimesh.Trimesh, raw_volume: float, tol: float) -> bool:
    return raw_volume > 0 and abs(float(m.volume) - raw_volume) <= tol * raw_volume
