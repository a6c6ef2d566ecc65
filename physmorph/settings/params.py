"""What rule params carry: the settings a job depends on as one canonical JSON string.

Snakemake reruns a job when its params string changes, so these strings must stay byte-identical
for identical settings: canonical JSON (sorted keys, no spaces) of the values, every field at its
default left out (``without_defaults``), and for a morph run what its method never reads
(``morph_params``).
"""

from __future__ import annotations

import json
from dataclasses import MISSING, asdict, fields, is_dataclass
from typing import Any

from physmorph.settings.base import field_default


def to_plain(obj: Any) -> Any:
    """Dataclasses, tuples and mappings as JSON-ready dicts and lists."""
    if is_dataclass(obj):
        obj = asdict(obj)
    return _each_item(obj, to_plain)


def _each_item(obj: Any, convert) -> Any:
    """``convert`` applied to each value of a mapping (keys as strings) or item of a list or tuple
    (as a list); anything else as it is."""
    if isinstance(obj, dict):
        return {str(k): convert(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [convert(v) for v in obj]
    return obj


def _compact_json(plain: Any) -> str:
    return json.dumps(plain, sort_keys=True, separators=(",", ":"))


def canonical_json(obj: Any) -> str:
    """One string per value (sorted keys, no spaces): the full record a stage writes into its file."""
    return _compact_json(to_plain(obj))


# Snakemake reruns a job when its params string changes. If params held every field, adding a
# field to a config class (a new option whose default changes nothing) would change the params
# of every job that holds that class and rerun whole result trees for identical numbers. So a
# field at its default is left out, and the job rebuilds its config from what is left (a left-out
# field takes its default). The one case this would get wrong is a *changed* default: runs made
# with the old one would keep their params and not rerun. A record of first defaults (the
# workflow's workflow/schemas/first_defaults.json, which ``python -m physmorph.settings --defaults``
# extends) holds each field's first default (append-only); a field whose default has changed since
# must be named in its class's ALWAYS_IN_PARAMS (a ClassVar), which puts it in every params string,
# so the runs that omitted it rerun once (tests/settings/test_config.py checks both).


def without_defaults(obj: Any) -> Any:
    """``to_plain(obj)`` with every dataclass field at its default left out, recursively (mappings
    and lists of dataclasses too); a nested dataclass left with nothing is left out."""
    if is_dataclass(obj) and not isinstance(obj, type):
        keep = getattr(type(obj), "ALWAYS_IN_PARAMS", frozenset())
        out = {}
        for f in fields(obj):
            value = getattr(obj, f.name)
            plain = without_defaults(value)
            if f.name not in keep:
                default = field_default(f)
                if is_dataclass(value) and not isinstance(value, type):
                    # Left out only when empty against its own class's defaults and the field's
                    # default is that class's default instance (so rebuilding gives it back).
                    if plain == {} and to_plain(default) == to_plain(type(value)()):
                        continue
                elif default is not MISSING and to_plain(value) == to_plain(default):
                    continue
            out[f.name] = plain
        return out
    return _each_item(obj, without_defaults)


def params_json(obj: Any) -> str:
    """What a rule's params hold: canonical JSON of ``obj`` without its fields at their defaults."""
    return _compact_json(without_defaults(obj))


def morph_params(cfg) -> str:
    """Canonical JSON of what a morph run's results depend on (cfg: physmorph.settings.morph.MorphConfig).

    Settings at their defaults are left out (see ``without_defaults``: a new option reruns
    nothing), and so are settings the run's method never reads, so changing them reruns nothing:
    plasticity and the stray and destination pulls outside ``full``, the injection gains and their calibration (and the
    settle phase, unless it judges the physics loss) for ``physics_only``, the settle hand-over where
    the settle phase does not hand over, the spray's links where no spray is put back, the gain's
    interval where the gain is not measured every frame, the held frames' step without a settle
    phase, ``gamma`` for ``position_inject`` and ``gamma_x`` elsewhere, the surface mask when nothing uses
    it; so are the thread count and the progress switch. The run rebuilds its MorphConfig from this
    string (what is left out takes its default)."""
    d = without_defaults(cfg)
    d.pop("progress", None)
    d.get("mpm", {}).pop("threads", None)
    if cfg.settle_objective != "physics_then_alpha":
        d.pop("settle_handover", None)
    if not cfg.reabsorb_strays:
        d.pop("spray_links", None)
    if cfg.settle == "off":
        d.pop("settle_hold_below", None)
    if cfg.injection_calibration != "every_frame":
        d.pop("injection_calibration_every", None)
    if cfg.method != "full":
        d.pop("plasticity", None)
        for k in ("stray_pull", "stray_pull_onset", "stray_pull_density", "destination_pull", "destination_pull_onset",
                  "reabsorb_strays", "spray_links", "waypoint_cells", "plan_push_speed", "plan_push_onset",
                  "plan_push_outside"):
            d.pop(k, None)
    if cfg.method == "physics_only":
        for k in ("gamma", "gamma_x", "injection_calibration", "injection_calibration_every"):
            d.pop(k, None)
        if cfg.settle_objective != "physics":  # the settle phase judges the images, which it never reads
            for k in ("settle", "settle_objective", "settle_backoff", "settle_regrow", "settle_handover",
                      "settle_hold_below"):
                d.pop(k, None)
        if cfg.metric_all_particles:
            d.pop("surface", None)
    else:
        d.pop("gamma_x" if cfg.method != "position_inject" else "gamma", None)
    return json.dumps(d, sort_keys=True, separators=(",", ":"))
