"""The mesh stages' errors, and how a command or job ends on one: a single line, not a traceback."""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Callable, TypeVar

T = TypeVar("T")

# The exit status of a refused mesh (argparse's for a refused command line, so a caller need not tell them apart).
REFUSED_STATUS = 2


class MeshError(ValueError):
    """A mesh cannot be used: the message names the file/shape and why. ``key``: the config key
    whose value refuses it (e.g. a grid too coarse to hold the shape: sampling.grid_res), None when
    the mesh itself is at fault; code reads it, not the message."""

    def __init__(self, message: str, key: str | None = None):
        super().__init__(message)
        self.key = key


class FetchError(RuntimeError):
    """A raw mesh could not be fetched: unreachable URL, missing mirror file or checksum mismatch."""


def refusal_line(exc: BaseException, path: str | os.PathLike | None = None) -> str:
    """``exc``'s message as one line (a reader's or MeshFix's text may hold line breaks), starting
    with ``path`` when the message does not already name it."""
    line = " ".join(str(exc).split()) or type(exc).__name__
    if path is not None and str(path) not in line:
        line = f"{path}: {line}"
    return line


def exit_on_refusal(run: Callable[[], T], log: str | os.PathLike | None = None,
                    path: str | os.PathLike | None = None, refusals: tuple[type, ...] = ()) -> T:
    """``run()``'s result; on a MeshError (or one of ``refusals``: the user's input, not a bug)
    its refusal_line goes to stderr (and is appended to ``log``, so a job's log ends in it) and
    the process exits with REFUSED_STATUS. Other errors still raise: they are bugs, and their
    traceback is what finds them."""
    try:
        return run()
    except (MeshError, *refusals) as exc:
        line = refusal_line(exc, path)
        if log is not None:
            Path(log).parent.mkdir(parents=True, exist_ok=True)
            with open(log, "a") as f:
                f.write(line + "\n")
        sys.stderr.write(line + "\n")
        sys.stderr.flush()
        raise SystemExit(REFUSED_STATUS) from None
