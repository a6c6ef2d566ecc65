"""What a raw mesh is once repaired as prepare_mesh repairs it, known before any job: its volume,
bounds and convex hull at size 1, its separate bodies, or the one line it is refused with.

Every workflow invocation asks (the volume warnings, the dry run's checks of a user's meshes), and
the repair of a large mesh takes seconds, so the answer is kept in a cache
(XDG_CACHE_HOME/physmorph/mesh_records/), one small file a record named by the file's path, size
and modification time: a planning run reads only the records of the meshes it names, and two
processes that measure two meshes at once never overwrite each other's.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from .errors import MeshError, refusal_line

# a new field or another meaning of one: records of older code are not read
RECORD_VERSION = 2


@dataclass(frozen=True)
class MeshRecord:
    """The repaired mesh at size 1 (longest extent 1, its volume centroid at the origin, as
    prepare_mesh places it), or ``refusal``: why the mesh cannot be used."""

    refusal: str | None = None
    unit_volume: float | None = None
    bodies: int = 0  # separate closed bodies after the repair
    unit_lo: tuple[float, float, float] = (0.0, 0.0, 0.0)
    unit_hi: tuple[float, float, float] = (0.0, 0.0, 0.0)
    hull: tuple[tuple[float, float, float], ...] = ()  # [H, 3] the convex hull's vertices

    @property
    def vertices(self) -> np.ndarray:  # [H, 3]: what a view must hold whole (the hull's: views are convex)
        return np.asarray(self.hull, np.float64).reshape(-1, 3)


# the records this process has read or measured, by cache key (a workflow's planning asks once per run)
_KNOWN: dict[str, MeshRecord] = {}


def _cache_file(key: str) -> Path:
    name = hashlib.sha256(key.encode()).hexdigest()[:32]
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "physmorph" / "mesh_records" / f"{name}.json"


def _stored(cache_file: Path, key: str) -> dict | None:
    """What ``cache_file`` keeps for ``key``; None where it is missing, damaged or another key's."""
    try:
        stored = json.loads(cache_file.read_text())
    except (OSError, ValueError):
        return None
    return stored if isinstance(stored, dict) and stored.get("key") == key else None


def _read(cache_file: Path, key: str) -> MeshRecord | None:
    stored = _stored(cache_file, key)
    if stored is None:
        return None
    fields = stored["record"]
    return MeshRecord(**{**fields, "hull": tuple(map(tuple, fields["hull"])),
                         "unit_lo": tuple(fields["unit_lo"]), "unit_hi": tuple(fields["unit_hi"])})


def _measure(raw_path: Path) -> MeshRecord:
    from .prepare import normalize_mesh  # (trimesh and the repair load only when a mesh is measured)
    from .repair import load_raw_mesh, repair_mesh

    try:
        repaired, _, _ = repair_mesh(load_raw_mesh(raw_path), str(raw_path))
    except MeshError as exc:
        return MeshRecord(refusal=refusal_line(exc, raw_path))
    unit, _, _ = normalize_mesh(repaired, 1.0)
    lo, hi = unit.bounds
    hull = unit.convex_hull.vertices
    return MeshRecord(unit_volume=abs(float(unit.volume)), bodies=len(unit.split(only_watertight=False)),
                      unit_lo=tuple(map(float, lo)), unit_hi=tuple(map(float, hi)),
                      hull=tuple(tuple(map(float, v)) for v in hull))


def letter_volume(glyph: str, size: float, depth: float | None) -> float:
    """The volume of physmorph.meshes.shapes.letter_mesh(glyph, size, depth), kept in the same cache
    under the text of shapes.py (another letter geometry, another key), so a planning run loads
    neither trimesh nor a font to warn about a letter target's volume."""
    code = hashlib.sha256((Path(__file__).parent / "shapes.py").read_bytes()).hexdigest()[:16]
    key = f"letter:{code}:{glyph}:{float(size)!r}:{depth!r}"
    cache_file = _cache_file(key)
    stored = _stored(cache_file, key)
    if stored is not None and isinstance(stored.get("volume"), float):
        return stored["volume"]
    from .shapes import letter_mesh

    volume = float(letter_mesh(glyph, size, depth).volume)
    _write(cache_file, {"key": key, "volume": volume})
    return volume


def _write(cache_file: Path, stored: dict) -> None:
    try:
        cache_file.parent.mkdir(parents=True, exist_ok=True)
        tmp = cache_file.with_suffix(f".{os.getpid()}.partial")
        tmp.write_text(json.dumps(stored))
        tmp.replace(cache_file)
    except OSError:  # a read-only home: the answer is still right, only not kept
        pass


def mesh_record(raw_path: str | os.PathLike) -> MeshRecord:
    """The record of ``raw_path`` (an existing file), from the cache or measured now."""
    raw_path = Path(raw_path)
    stat = raw_path.stat()
    key = f"{RECORD_VERSION}:{raw_path.resolve()}:{stat.st_size}:{stat.st_mtime_ns}"
    if key in _KNOWN:
        return _KNOWN[key]
    cache_file = _cache_file(key)
    record = _read(cache_file, key)
    if record is None:
        record = _measure(raw_path)
        _write(cache_file, {"key": key, "record": asdict(record)})
    _KNOWN[key] = record
    return record
