"""A call in its own process under a wall-clock limit, its exception sent back as data.

``run_isolated("module:function", kwargs, timeout_s)`` runs ``function(**kwargs)`` in a fresh
Python (``python -m physmorph.base.isolated_call CALL.json RESULT.json``) that leads its own process
group, killed with everything it started at the limit: a hang is cut, and a crash of the
interpreter is seen rather than suffered. The child reports the exception it raised, if any, as
JSON: its class name, message and traceback, and the attributes the caller names in
``error_fields`` (a refused config key, a divergence's frame and quantity), so the caller reads
what happened from data, never from the wording of a message. The stability map
(physmorph.studies.extremes) runs its cells this way.
"""

from __future__ import annotations

import importlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path


@dataclass(frozen=True)
class ChildResult:
    returncode: int | None
    timed_out: bool
    error_type: str | None  # the class of the exception the call raised, None when it returned
    error_message: str | None
    traceback: str | None
    wall_s: float
    error_data: dict = field(default_factory=dict)  # the exception's attributes named in error_fields


def _json_ready(value):
    """A scalar attribute as JSON holds it (a NumPy number as its Python twin; anything else as text)."""
    if isinstance(value, (str, int, float, bool)):
        return value
    item = getattr(value, "item", None)
    if callable(item):
        value = item()
        if isinstance(value, (str, int, float, bool)):
            return value
    return str(value)


def error_report(exc: BaseException, error_fields: tuple[str, ...] = ()) -> dict:
    """What is reported of ``exc``: error_type, error_message, traceback and error_data, each of
    ``error_fields`` that ``exc`` carries as an attribute (left out when absent or None)."""
    data = {}
    for name in error_fields:
        value = getattr(exc, name, None)
        if value is not None:
            data[name] = _json_ready(value)
    return {"error_type": type(exc).__name__, "error_message": str(exc),
            "traceback": "".join(traceback.format_exception(exc)), "error_data": data}


def run_isolated(target: str, kwargs: dict, timeout_s: float, log: str | Path | None = None,
                 error_fields: tuple[str, ...] = ()) -> ChildResult:
    """Call ``module:function(**kwargs)`` (kwargs JSON-ready) in a fresh Python process with its
    output appended to ``log``; kill it (its whole process group) after ``timeout_s`` seconds.
    An exception it raised comes back as :func:`error_report` with ``error_fields``."""
    repo = str(Path(__file__).resolve().parents[2])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (repo, os.environ.get("PYTHONPATH", "")) if p)}
    with tempfile.TemporaryDirectory(prefix="physmorph-call-") as tmp:
        call, result = Path(tmp) / "call.json", Path(tmp) / "result.json"
        call.write_text(json.dumps({"target": target, "kwargs": kwargs, "error_fields": list(error_fields)}))
        out = open(log, "a") if log is not None else subprocess.DEVNULL
        started = time.time()
        try:
            proc = subprocess.Popen([sys.executable, "-m", "physmorph.base.isolated_call", str(call), str(result)],
                                    stdout=out, stderr=subprocess.STDOUT, env=env, start_new_session=True)
            try:
                returncode, timed_out = proc.wait(timeout=timeout_s), False
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)  # the child leads its own group: it and what it started
                returncode, timed_out = proc.wait(), True
        finally:
            if log is not None:
                out.close()
        wall = time.time() - started
        payload = json.loads(result.read_text()) if result.exists() else {}
    return ChildResult(returncode, timed_out, payload.get("error_type"), payload.get("error_message"),
                       payload.get("traceback"), wall, payload.get("error_data") or {})


def call_here(target: str, kwargs: dict, error_fields: tuple[str, ...] = ()) -> ChildResult:
    """:func:`run_isolated` in this process (no wall-clock limit; an Exception is caught and
    reported as the child would report it): for tests that share this process's compiled kernels."""
    module, func = target.split(":")
    started = time.time()
    try:
        getattr(importlib.import_module(module), func)(**kwargs)
    except Exception as exc:  # noqa: BLE001 - reported as the child would
        report = error_report(exc, error_fields)
        return ChildResult(1, False, report["error_type"], report["error_message"], report["traceback"],
                           time.time() - started, report["error_data"])
    return ChildResult(0, False, None, None, None, time.time() - started)


def _child_main(call_path: str, result_path: str) -> int:
    """The child of run_isolated: make the call, write what it raised (if anything) to result_path."""
    spec = json.loads(Path(call_path).read_text())
    module, func = spec["target"].split(":")
    out: dict = {"error_type": None, "error_message": None, "traceback": None, "error_data": {}}
    code = 0
    try:
        getattr(importlib.import_module(module), func)(**spec["kwargs"])
    except BaseException as exc:  # noqa: BLE001 - every exception is reported; the parent judges it
        out = error_report(exc, tuple(spec.get("error_fields", ())))
        print(out["traceback"], file=sys.stderr, flush=True)
        code = 1
    Path(result_path).write_text(json.dumps(out))
    return code


if __name__ == "__main__":  # the child of run_isolated: python -m physmorph.base.isolated_call CALL.json RESULT.json
    sys.exit(_child_main(sys.argv[1], sys.argv[2]))
