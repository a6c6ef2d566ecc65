"""HDF5 helpers: atomic writes, provenance attributes, content checksums and reads that fail
with clear errors.

Every stage output is written to ``<path>.partial``, stamped with a content checksum (the last
thing written), flushed to disk (fsync) and renamed into place only when complete, so a killed or
failing stage never leaves a file that looks finished. Readers verify the checksum, so a file whose
bytes changed afterwards (zero-filled blocks, a torn copy, an edit) is refused with its name.

The checksum (``content_sha256``) is the SHA-256 of every attribute and dataset in a fixed order
(names, dtypes, shapes and bytes), computed from the file as stored; it leaves out only itself.
Beside it, ``data_sha256`` is the same digest without the root attributes that say how the file
was made (wall time, peak memory, commit, package versions): the identity of what the file holds,
so a stage rerun that writes the same data keeps it, and a run made from the first file resumes
from, and exports against, the second. Readers verify both.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import resource
import time
from collections.abc import Mapping
from contextlib import contextmanager
from importlib import metadata
from pathlib import Path

import h5py
import numpy as np

from physmorph.records.provenance import git_state, method_settings, method_sha

CHECKSUM_ATTR = "content_sha256"
DATA_ATTR = "data_sha256"
# Attributes a checksum never covers (the checksums themselves).
_CHECKSUM_ATTRS = frozenset({CHECKSUM_ATTR, DATA_ATTR, "metrics_sha256"})
# Root attributes that record how a file was made, not what it holds: the data digest leaves them out.
EXECUTION_ATTRS = frozenset({"wall_time_s", "peak_rss_mb", "git_commit", "git_dirty", "package_versions",
                             "physmorph_version"})
_HASH_BLOCK_BYTES = 1 << 26  # datasets are hashed in row blocks of about this size

PROVENANCE_PACKAGES = ("numpy", "scipy", "torch", "taichi", "trimesh", "h5py", "scikit-image", "pymeshfix")


def package_versions() -> dict[str, str]:
    out = {}
    for name in PROVENANCE_PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "absent"
    return out


_CODE_STATE: tuple[str, str] | None = None


def code_state() -> tuple[str, str]:
    """(commit, dirty) of the physmorph checkout as this process first saw it: a long run that
    finishes after the tree moved on still names the code it started with (RunWriter asks at its
    start)."""
    global _CODE_STATE
    if _CODE_STATE is None:
        _CODE_STATE = git_state()
    return _CODE_STATE


def git_commit() -> str:
    """The commit of the physmorph checkout, or 'unknown' outside a git work tree."""
    return code_state()[0]


def peak_rss_mb() -> float:
    """Peak resident memory of this process in MiB (Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def write_provenance(f: h5py.File, config: dict | None, started: float) -> None:
    f.attrs["config"] = json.dumps(config or {}, sort_keys=True, default=str)
    f.attrs["package_versions"] = json.dumps(package_versions(), sort_keys=True)
    commit, dirty = code_state()
    f.attrs["git_commit"] = commit
    f.attrs["git_dirty"] = dirty  # "yes": made by a tree with local changes to the code
    f.attrs["method_sha"] = method_sha(method_settings(config or {}))
    f.attrs["wall_time_s"] = float(time.time() - started)
    f.attrs["peak_rss_mb"] = peak_rss_mb()
    f.attrs["physmorph_version"] = __import__("physmorph").__version__


class StageInputError(ValueError):
    """An input file is missing, corrupt or lacks a field; the message names file and field."""


def _hash_value(h: "hashlib._Hash", value) -> None:
    """Feed one attribute value (str, bytes, number, array) into ``h`` unambiguously."""
    if isinstance(value, str):
        data = b"s" + value.encode("utf-8")
    elif isinstance(value, bytes):
        data = b"b" + value
    else:
        a = np.asarray(value)
        if a.dtype.kind in "OSUV":  # strings and objects: their printed form
            data = b"o" + repr(a.tolist()).encode("utf-8")
        else:
            data = f"{a.dtype.str}{a.shape}".encode() + np.ascontiguousarray(a).tobytes()
    h.update(len(data).to_bytes(8, "little"))
    h.update(data)


class _Both:
    """Feeds the content and (``data``) the data digest at once (one pass over the datasets' bytes)."""

    def __init__(self, data: bool = True) -> None:
        self.content, self.data = hashlib.sha256(), (hashlib.sha256() if data else None)

    def update(self, data) -> None:
        self.content.update(data)
        if self.data is not None:
            self.data.update(data)


def _hash_attrs(h: _Both, name: str, attrs: h5py.AttributeManager) -> None:
    for key in sorted(k for k in attrs.keys() if k not in _CHECKSUM_ATTRS):
        execution = name == "/" and key in EXECUTION_ATTRS
        for sink in ((h.content,) if execution else (h,)):
            _hash_value(sink, f"attr {name}@{key}")
            _hash_value(sink, attrs[key])


def _hash_dataset(h: _Both, ds: h5py.Dataset, written: np.ndarray | None = None) -> None:
    """Feed ``ds`` into ``h``: its dtype, shape and C-order bytes. ``written``: the array ``ds`` was
    just written from, hashed in its place (no read back) where its dtype and shape are the
    dataset's, so its bytes are the stored ones."""
    _hash_value(h, f"{ds.dtype.str}{ds.shape}")
    if ds.dtype.kind in "OSUV" or ds.ndim == 0 or ds.size == 0:
        _hash_value(h, ds[()])
        return
    if written is not None and written.dtype == ds.dtype and written.shape == ds.shape:
        h.update(np.ascontiguousarray(written).reshape(-1).view(np.uint8))
        return
    row_bytes = max(1, ds.size // ds.shape[0] * ds.dtype.itemsize)
    step = max(1, _HASH_BLOCK_BYTES // row_bytes)
    for i in range(0, ds.shape[0], step):  # C order: the blocks' bytes concatenate to the whole
        h.update(np.ascontiguousarray(ds[i:i + step]).reshape(-1).view(np.uint8))


def _digests(f: h5py.File | h5py.Group, only: str | None = None,
             written: Mapping[str, np.ndarray] | None = None, data: bool = True) -> tuple[str, str | None]:
    """(content, data) SHA-256 of the attributes and datasets under ``f`` (the module docstring);
    the data digest None unless ``data``."""
    h = _Both(data)
    _hash_attrs(h, "/", f.attrs)
    names: list[str] = []
    f.visit(names.append)
    for name in sorted(names):
        if only is not None and name != only and not name.startswith(only + "/"):
            continue
        obj = f[name]
        _hash_value(h, f"{'dataset' if isinstance(obj, h5py.Dataset) else 'group'} {name}")
        _hash_attrs(h, name, obj.attrs)
        if isinstance(obj, h5py.Dataset):
            _hash_dataset(h, obj, None if written is None else written.get(name))
    return h.content.hexdigest(), (None if h.data is None else h.data.hexdigest())


def content_checksum(f: h5py.File | h5py.Group, only: str | None = None,
                     written: Mapping[str, np.ndarray] | None = None) -> str:
    """SHA-256 of the attributes and datasets under ``f`` (see the module docstring).

    ``only``: hash the root attributes and just the objects under this member (e.g. "metrics"),
    for a cheap check of the part a reader uses. ``written``: dataset name -> the array it was
    written from in this process (hashed from memory, see _hash_dataset; the same checksum).
    """
    return _digests(f, only, written, data=False)[0]


def stamp_checksum(f: h5py.File, written: Mapping[str, np.ndarray] | None = None, data: bool = True) -> str:
    """Write ``content_sha256`` and (``data``) ``data_sha256`` of everything already in ``f``; call
    it last. ``written``: as in content_checksum (the arrays the datasets were just written from:
    nothing is read back). A file no run names as its input (a run's frame, checkpoint or finished
    file) needs no data digest. Returns the content checksum."""
    f.flush()
    content, digest = _digests(f, written=written, data=data)
    f.attrs[CHECKSUM_ATTR] = content
    if digest is not None:
        f.attrs[DATA_ATTR] = digest
    return content


def verify_checksum(f: h5py.File, required: bool = True, remedy: str = "delete it and rerun the stage that writes it",
                    written: Mapping[str, np.ndarray] | None = None) -> str | None:
    """Check ``content_sha256`` against the file's content; StageInputError naming the file when it
    differs, is unreadable or (``required``) is missing. Returns the checksum (None if absent).
    ``written``: dataset name -> the array just read from it, hashed in its place (as in
    content_checksum)."""
    path = f.filename
    try:
        stored = f.attrs.get(CHECKSUM_ATTR)
    except (OSError, RuntimeError, KeyError) as exc:
        raise StageInputError(f"{path}: its content checksum is unreadable ({exc}); the file is damaged: {remedy}") from exc
    if stored is None:
        if required:
            raise StageInputError(f"{path}: no content checksum ('{CHECKSUM_ATTR}'): it was written by an older physmorph "
                                  f"or damaged; {remedy}")
        return None
    try:
        stored_data = f.attrs.get(DATA_ATTR)  # absent in run files and in files written before it existed
        actual, data = _digests(f, written=written, data=stored_data is not None)
    except (OSError, RuntimeError, KeyError, ValueError) as exc:
        raise StageInputError(f"{path}: unreadable content ({exc}); the file is damaged (torn or overwritten): {remedy}") from exc
    for what, kept, computed in (("checksum", stored, actual), ("data digest", stored_data, data)):
        if kept is not None and computed != str(kept):
            raise StageInputError(f"{path}: content does not match its {what} (stored {str(kept)[:12]}..., computed "
                                  f"{computed[:12]}...): the file changed after it was written (zero-filled, torn or "
                                  f"edited); {remedy}")
    return actual


def stored_checksum(path: str | os.PathLike) -> str:
    """The verified content checksum of a stage output."""
    with open_h5(path) as f:
        return str(f.attrs[CHECKSUM_ATTR])


def data_identity(f: h5py.File) -> str:
    """What a file holds, for run keys: its data digest, or, in a file written before the digest
    existed, its content checksum (so a run keyed on that file still resumes)."""
    return str(f.attrs.get(DATA_ATTR, f.attrs[CHECKSUM_ATTR]))


def stored_identity(path: str | os.PathLike) -> str:
    """The verified data identity of a stage output (data_identity)."""
    with open_h5(path) as f:
        return data_identity(f)


def fsync_path(path: str | os.PathLike) -> None:
    """Flush a closed file's data (or a directory entry's rename) to the disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def disk_full_message(path: str | os.PathLike, exc: OSError) -> str | None:
    if exc.errno == errno.ENOSPC:
        return f"{path}: disk full ({exc.strerror or exc}); free space on {Path(path).parent} and rerun"
    return None


@contextmanager
def atomic_h5(path: str | os.PathLike, config: dict | None = None):
    """Open ``path.partial`` for writing; on success add provenance, stamp the content checksum
    (last), fsync and rename to ``path``.

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
            stamp_checksum(f)
        fsync_path(tmp)
        os.replace(tmp, path)
        fsync_path(path.parent)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        full = disk_full_message(path, exc) if isinstance(exc, OSError) else None
        if full:
            raise OSError(exc.errno, full) from exc
        raise


def open_h5(path: str | os.PathLike, verify: bool = True) -> h5py.File:
    """Open a stage output read-only; with ``verify`` its content checksum must be present and match."""
    path = Path(path)
    if not path.exists():
        raise StageInputError(f"{path}: file not found")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise StageInputError(f"{path}: not a readable HDF5 file ({exc}); delete it and rerun the stage that writes it") from exc
    if verify:
        try:
            verify_checksum(f)
        except BaseException:
            f.close()
            raise
    return f


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
