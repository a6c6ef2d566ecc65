"""The run files' command line, ``python -m physmorph.records.runfile RUN [RUN ...]``, and what a
path given as a run is.

Each path gets one line: a finished run file's or a partial run's summary
(physmorph.records.runfile.describe_run), or why it is neither. A path is a run when it is
  * a finished run file: an HDF5 file holding the group ``metrics`` or one of a run file's
    attributes (RUN_FILE_ATTRS), or an HDF5 file that cannot be opened but whose first
    TRACE_BYTES bytes hold one of those attributes' names (a run file truncated or overwritten in part);
  * a partial run: a directory ``<out>.partial/`` holding its LOCK, its checkpoint or a frame file.
Only a run is ever told to be deleted (physmorph.records.runfile's remedies, when it is damaged);
anything else (a mesh, a text file, another HDF5 file, a directory, a missing path) is named as not a
physmorph run file, with no advice.

physmorph.records.runfile imports this module (the names a run leaves on disk, declared here; its
readers ask ``not_a_run`` first) and its ``__main__`` runs ``main`` with its describe_run, so this
module imports no other of physmorph.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Callable

import h5py

# The names a run leaves on disk, declared here for physmorph.records.runfile, which writes them.
LOCK_NAME = "LOCK"  # in a partial run's directory: the writer's lock
CHECKPOINT_NAME = "checkpoint.h5"  # in a partial run's directory, beside its frame_XXXX.h5
METRICS_CHECKSUM_ATTR = "metrics_sha256"
# Attributes a finished run file has and no other file physmorph writes: its run key and the
# checksums of its inputs (physmorph.records.runkey.RunKey.attrs) and of its metrics.
RUN_FILE_ATTRS = ("run_key", "input_checksums", METRICS_CHECKSUM_ATTR)
PARTIAL_ENTRIES = (LOCK_NAME, CHECKPOINT_NAME)  # beside frame_XXXX.h5, what a partial run's directory holds
TRACE_BYTES = 1 << 20  # where a run file's attribute names are (its first kilobytes: attributes come first)
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"  # at offset 0, 512, 1024, 2048, ... (after a user block)
PROG = "python -m physmorph.records.runfile"


def is_partial_run(path: Path) -> bool:
    """Whether ``path`` is a partial run's directory: ``<out>.partial/`` with its lock, checkpoint or a frame."""
    return (path.is_dir() and path.name.endswith(".partial")
            and (any((path / name).exists() for name in PARTIAL_ENTRIES) or any(path.glob("frame_*.h5"))))


def has_hdf5_signature(path: Path) -> bool:
    """Whether the file starts with the HDF5 signature (or holds it after a user block)."""
    with open(path, "rb") as fh:
        offset = 0
        while True:
            fh.seek(offset)
            head = fh.read(len(HDF5_SIGNATURE))
            if head == HDF5_SIGNATURE:
                return True
            if len(head) < len(HDF5_SIGNATURE):
                return False
            offset = 512 if offset == 0 else 2 * offset


def _holds_run_attr_names(path: Path) -> bool:
    with open(path, "rb") as fh:
        head = fh.read(TRACE_BYTES)
    return any(name.encode("ascii") in head for name in RUN_FILE_ATTRS)


def not_a_run(path: str | os.PathLike) -> str | None:
    """One line naming ``path`` and saying why it is no physmorph run file nor partial run, or None
    when it is one (which may still be damaged: its reader says how)."""
    path = Path(path)
    if not path.exists():
        return f"{path}: not found"
    if path.is_dir():
        if is_partial_run(path):
            return None
        return (f"{path}: a directory, not a physmorph run file nor a partial run (a partial run is a directory "
                f"<out>.partial holding {', '.join(PARTIAL_ENTRIES)} or frame_XXXX.h5)")
    if not path.is_file():
        return f"{path}: not a regular file, so not a physmorph run file"
    if not has_hdf5_signature(path):
        return f"{path}: not a physmorph run file (not an HDF5 file)"
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        if _holds_run_attr_names(path):
            return None  # a run file torn or overwritten: its reader names the damage and the remedy
        return (f"{path}: an HDF5 file that cannot be opened ({exc}) and holds none of a physmorph run file's "
                f"attribute names ({', '.join(RUN_FILE_ATTRS)}): not recognisable as a physmorph run file")
    with f:
        if "metrics" in f or any(name in f.attrs for name in RUN_FILE_ATTRS):
            fmt = f.attrs.get("format")
            if fmt is not None:  # a frame or checkpoint file (a finished run file has no 'format')
                return (f"{path}: a file of a partial run (format {str(fmt)!r}), not a finished run file: "
                        f"give its directory {path.parent}")
            return None
    return (f"{path}: not a physmorph run file (an HDF5 file with neither the group 'metrics' nor a run "
            f"file's attributes {', '.join(RUN_FILE_ATTRS)})")


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG, description="Print one line about each run given: a finished run file's status, frames, alpha "
        "MSE (first -> last, best and its frame), wall time and peak memory; a partial run's committed frames and "
        "its last writer. A path that is not a physmorph run file is named as such on stderr (nothing is changed).",
        epilog="exit status: 0 when every path is a run, 1 when one is not (or is damaged), 2 on a usage error")
    p.add_argument("runs", nargs="+", metavar="RUN",
                   help="a finished run file <out>.h5, or a partial run's directory <out>.partial")
    return p


def main(describe: Callable[[str], str], argv: list[str] | None = None) -> int:
    """``describe`` (physmorph.records.runfile.describe_run) each run of the command line; its
    RunFileError (a RuntimeError) or OSError is printed as one line and makes the status 1."""
    code = 0
    for run in parser().parse_args(argv).runs:
        try:
            print(describe(run))
        except (RuntimeError, OSError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            code = 1
    return code
