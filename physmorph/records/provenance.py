"""What made a file or a page: the commit, whether the tree had local changes, and the method.

The method settings of a morph are its MorphConfig less what a profile or an experiment sets for
size and length (the grid, the images, the frames, the device, the threads) and an experiment's own
choices (its method and drag): two runs with the same method settings ran the same algorithm, so
the mid and paper profiles' pages compare with the default's. ``method_sha`` names them in 12 hex
digits; the pages also keep the settings themselves, so ``python -m physmorph.reports.userdocs check`` can
name the keys in which a page differs from the shipped method without any run file.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
from pathlib import Path
from typing import Any

from physmorph.settings.retired import ADDED_METHOD_SETTINGS, RETIRED_METHOD_SETTINGS

# leaf names that set size, length or hardware, never the algorithm (at any depth of the config)
RESOLUTION_LEAVES = frozenset({
    "grid_res", "ppc_surface", "ppc_interior", "width", "height", "supersample", "surface_points", "voxels",
    "cameras", "frames", "save_every", "release_frames", "progress", "threads", "device", "domain_lo",
    "domain_hi", "density",
})
# an experiment's own keys (config experiments.*: method, drag): what it is, not how it is solved
EXPERIMENT_LEAVES = frozenset({"method", "drag"})

CODE_PATHS = ("physmorph", "workflow", "config", "Snakefile")  # what decides a result's numbers


def _flat(d: dict, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in d.items():
        if isinstance(value, dict):
            out.update(_flat(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def method_settings(config: dict) -> dict[str, Any]:
    """The method's settings in a config record (a MorphConfig as a dict, or any stage's
    config): dotted keys, sorted, size/length/hardware keys and the experiment's own left out. A
    run file's record holds the MorphConfig as its "resolved" part, which is taken alone."""
    config = config or {}
    if isinstance(config.get("resolved"), dict):
        config = config["resolved"]
    flat = _flat(config)
    keep = {k: v for k, v in flat.items() if k.rsplit(".", 1)[-1] not in RESOLUTION_LEAVES | EXPERIMENT_LEAVES}
    return dict(sorted(keep.items()))


ABSENT = "(absent)"  # merge_settings' value of a key some runs' records lack


def method_sha(settings: dict[str, Any]) -> str:
    """12 hex digits of the SHA-256 of ``settings`` (:func:`method_settings`) as canonical JSON."""
    text = json.dumps(settings, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def differing_keys(settings: dict[str, Any], reference: dict[str, Any]) -> list[str]:
    """Keys whose value in ``settings`` is not the reference's (a key either lacks counts; a
    list of values, as a page keeps for keys its runs disagree on, differs unless all equal it).
    A key the code no longer has (physmorph.settings.retired) counts as the reference's where
    ``settings`` holds the value the shipped method always ran with; a key added since
    (physmorph.settings.retired.ADDED_METHOD_SETTINGS) that ``settings`` lacks holds the value at
    which the method runs as before it."""
    settings = {**{k: v for k, v in ADDED_METHOD_SETTINGS.items() if k in reference}, **settings}
    out = []
    for key in sorted(set(settings) | set(reference)):
        if key not in reference and key in RETIRED_METHOD_SETTINGS:
            expected = RETIRED_METHOD_SETTINGS[key]
        elif key not in settings or key not in reference:
            out.append(key)
            continue
        else:
            expected = reference[key]
        value = settings[key]
        values = value["values"] if isinstance(value, dict) and "values" in value else [value]
        # a page of runs from either side of a setting's removal or addition merges the records
        # that lack it as ABSENT: those ran as the retired / added setting's value does
        if key in RETIRED_METHOD_SETTINGS or key in ADDED_METHOD_SETTINGS:
            values = [expected if v == ABSENT else v for v in values]
        if any(json.dumps(v, default=str) != json.dumps(expected, default=str) for v in values):
            out.append(key)
    return out


def merge_settings(many: list[dict[str, Any]]) -> dict[str, Any]:
    """One settings dict for several runs: a key all agree on keeps its value; one they disagree on
    (or some lack) becomes {"values": [...]}, its distinct values."""
    keys = sorted(set().union(*many)) if many else []
    out: dict[str, Any] = {}
    for key in keys:
        seen: list = []
        for s in many:
            v = s.get(key, ABSENT)
            if all(json.dumps(v, default=str) != json.dumps(w, default=str) for w in seen):
                seen.append(v)
        out[key] = seen[0] if len(seen) == 1 else {"values": seen}
    return out


def git_state(where: str | None = None) -> tuple[str, str]:
    """(commit, dirty) of the checkout holding ``where`` (default: this package): dirty is "yes"
    when a tracked file under physmorph/, workflow/, config/ or the Snakefile differs from the
    commit, "no" when none does, and ("unknown", "unknown") outside a git work tree."""
    cwd = Path(where) if where else Path(__file__).resolve().parent
    try:
        top = subprocess.run(["git", "rev-parse", "--show-toplevel"], cwd=cwd, capture_output=True, text=True,
                             timeout=5, check=True).stdout.strip()
        rev = subprocess.run(["git", "rev-parse", "HEAD"], cwd=top, capture_output=True, text=True, timeout=5,
                             check=True).stdout.strip()
        changed = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", *CODE_PATHS],
                                 cwd=top, capture_output=True, text=True, timeout=10, check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return "unknown", "unknown"
    return rev, "yes" if changed.strip() else "no"
