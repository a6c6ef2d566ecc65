"""Loading raw meshes and repairing them into watertight solids (the order is in
physmorph.meshes' docstring); a repair that changes the volume by more than its tolerance fails."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import trimesh

from .errors import MeshError

# A repair may change the enclosed volume by at most this fraction (MeshFix on the Bunny: < 1 %).
DEFAULT_VOLUME_TOLERANCE = 0.03


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
