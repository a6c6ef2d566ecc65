"""Stage 2: a raw mesh or procedural shape -> watertight, normalised mesh HDF5 (and its reader)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import trimesh

from physmorph.base.grid import DOMAIN_HI, DOMAIN_LO
from physmorph.records.h5io import StageInputError, atomic_h5, open_h5, read_attr, read_field

from .errors import MeshError
from .fetch import sha256_of
from .repair import DEFAULT_VOLUME_TOLERANCE, load_raw_mesh, repair_mesh
from .shapes import ShapeSpec, isosphere, letter_mesh


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
