"""HDF5 helpers: atomic writes, provenance attributes and reads that fail with clear errors.

Every stage output is written to ``<path>.partial`` and renamed into place only when complete,
so a killed or failing stage never leaves a file that looks finished.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import time
from contextlib import contextmanager
from importlib import metadata
from pathlib import Path

import h5py
import numpy as np

PROVENANCE_PACKAGES = ("numpy", "scipy", "torch", "taichi", "trimesh", "h5py", "scikit-image", "pymeshfix")


def package_versions() -> dict[str, str]:
    out = {}
    for name in PROVENANCE_PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "absent"
    return out


def git_commit() -> str:
    """The commit of the physmorph checkout, or 'unknown' outside a git work tree."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=Path(__file__).resolve().parent,
            capture_output=True, text=True, timeout=5, check=True,
        )
        return out.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def peak_rss_mb() -> float:
    """Peak resident memory of this process in MiB (Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def write_provenance(f: h5py.File, config: dict | None, started: float) -> None:
    f.attrs["config"] = json.dumps(config or {}, sort_keys=True, default=str)
    f.attrs["package_versions"] = json.dumps(package_versions(), sort_keys=True)
    f.attrs["git_commit"] = git_commit()
    f.attrs["wall_time_s"] = float(time.time() - started)
    f.attrs["peak_rss_mb"] = peak_rss_mb()
    f.attrs["physmorph_version"] = __import__("physmorph").__version__


@contextmanager
def atomic_h5(path: str | os.PathLike, config: dict | None = None):
    """Open ``path.partial`` for writing; on success add provenance and rename to ``path``.

    On any exception the partial file is removed and the exception propagates.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".partial")
    started = time.time()
    try:
        with h5py.File(tmp, "w") as f:
            yield f
            write_provenance(f, config, started)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


class StageInputError(ValueError):
    """An input file is missing, corrupt or lacks a field; the message names file and field."""


def open_h5(path: str | os.PathLike) -> h5py.File:
    path = Path(path)
    if not path.exists():
        raise StageInputError(f"{path}: file not found")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise StageInputError(f"{path}: not a readable HDF5 file ({exc})") from exc


def read_field(f: h5py.File, name: str, shape_tail: tuple | None = None) -> np.ndarray:
    """Dataset ``name`` as an array; a missing field or wrong trailing shape names file and field."""
    if name not in f:
        raise StageInputError(f"{f.filename}: missing field '{name}'")
    try:
        data = f[name][()]
    except OSError as exc:
        raise StageInputError(f"{f.filename}: field '{name}' is unreadable ({exc})") from exc
    if shape_tail is not None and tuple(data.shape[-len(shape_tail):]) != tuple(shape_tail):
        raise StageInputError(f"{f.filename}: field '{name}' has shape {data.shape}, expected [..., {shape_tail}]")
    return data


def read_attr(f: h5py.File, name: str):
    if name not in f.attrs:
        raise StageInputError(f"{f.filename}: missing attribute '{name}'")
    return f.attrs[name]
