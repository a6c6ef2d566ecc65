"""The config's JSON schema and the record of first defaults, both generated from the settings'
declarations, and the maintenance command that writes them: ``python -m physmorph.settings
--schema`` / ``--defaults``."""

from __future__ import annotations

import json
from dataclasses import MISSING, fields, is_dataclass
from pathlib import Path
from typing import Any, get_args, get_type_hints

import yaml

from physmorph.settings.base import field_default, json_schema_of
from physmorph.settings.morph import MorphConfig
from physmorph.settings.params import to_plain
from physmorph.settings.sections import SamplingConfig
from physmorph.settings.study_points import TradeoffPoint
from physmorph.settings.workflow import Settings, section_derived


def settings_classes() -> list[type]:
    """Every config dataclass reachable from Settings and MorphConfig (and the tradeoff point)."""
    seen: list[type] = []

    def walk(tp: Any) -> None:
        if is_dataclass(tp) and isinstance(tp, type):
            if tp in seen:
                return
            seen.append(tp)
            for hint in get_type_hints(tp).values():
                walk(hint)
        for arg in get_args(tp):
            walk(arg)

    for root in (Settings, MorphConfig, TradeoffPoint):
        walk(root)
    return seen


def current_defaults() -> dict[str, Any]:
    """``{"Class.field": default}`` of every config class (fields without a default left out)."""
    out = {}
    for cls in settings_classes():
        for f in fields(cls):
            default = field_default(f)
            if default is not MISSING and not is_dataclass(default):
                out[f"{cls.__name__}.{f.name}"] = to_plain(default)
    return out


def record_first_defaults(path: str | Path) -> list[str]:
    """Add the fields not yet recorded to ``path`` (never rewrites a recorded default); returns them."""
    path = Path(path)
    recorded = json.loads(path.read_text()) if path.exists() else {}
    new = {k: v for k, v in current_defaults().items() if k not in recorded}
    if new:
        path.write_text(json.dumps({**recorded, **new}, indent=1, sort_keys=True) + "\n")
    return sorted(new)


def defaults_changed(path: str | Path) -> list[str]:
    """Problems with the first-defaults record: fields not yet recorded, and fields whose default
    changed but which are not in their class's ALWAYS_IN_PARAMS (their old runs would not rerun)."""
    path = Path(path)
    recorded = json.loads(path.read_text()) if path.exists() else {}
    problems = []
    classes = {c.__name__: c for c in settings_classes()}
    for key, default in current_defaults().items():
        if key not in recorded:
            problems.append(f"{key}: not recorded in {path.name}; run `python -m physmorph.settings --defaults`")
            continue
        cls_name, name = key.split(".", 1)
        if recorded[key] != default and name not in getattr(classes[cls_name], "ALWAYS_IN_PARAMS", ()):
            problems.append(f"{key}: default changed {recorded[key]!r} -> {default!r}, so runs made with the old "
                            f"default (which left it out of their params) would not rerun; add '{name}' to "
                            f"{cls_name}.ALWAYS_IN_PARAMS")
    return problems


def json_schema() -> dict:
    """The config's JSON schema, generated from the declarations of :class:`Settings` and its
    sections; the Snakefile validates the merged config with it before Settings builds it. It accepts
    what the settings accept (numbers and booleans as strings too) and leaves out the fields other
    keys set (mpm.grid_res: sampling.grid_res, ...)."""
    out = json_schema_of(Settings)
    props = out["properties"]
    props["morph"] = json_schema_of(MorphConfig)
    derived = {"mpm": section_derived("mpm", SamplingConfig(), "auto", (0, 1)), "render": {"device": None},
               "morph": dict.fromkeys(("method", "mpm", "render", "plasticity", "surface"))}
    for name, names in derived.items():
        for k in names:
            props[name]["properties"].pop(k)
        props[name]["required"] = [k for k in props[name].get("required", []) if k not in names]
        if not props[name]["required"]:
            del props[name]["required"]
    return {"$schema": "https://json-schema.org/draft/2020-12/schema",
            "title": "physmorph config (generated from physmorph.settings.workflow.Settings; do not edit)", **out}


SCHEMA_HEADER = ("# GENERATED from physmorph.settings.workflow.Settings by `python -m physmorph.settings --schema`; do not edit.\n"
                 "# The Snakefile validates the merged config with it; physmorph.settings.workflow.Settings then builds the settings.\n")


def schema_text() -> str:
    return SCHEMA_HEADER + yaml.safe_dump(json_schema(), sort_keys=False, width=110)


def main(argv: list[str] | None = None) -> None:
    """The maintenance command: ``--schema [PATH]`` writes the config's JSON schema, ``--defaults
    [PATH]`` records new fields' first defaults. Without PATH they write this checkout's workflow
    files (workflow/schemas/config.schema.yaml, workflow/schemas/first_defaults.json)."""
    import argparse

    schemas = Path(__file__).resolve().parents[2] / "workflow" / "schemas"
    parser = argparse.ArgumentParser(prog="python -m physmorph.settings")
    what = parser.add_mutually_exclusive_group(required=True)
    what.add_argument("--schema", nargs="?", const=schemas / "config.schema.yaml", type=Path, metavar="PATH",
                      help="regenerate the schema (default: workflow/schemas/config.schema.yaml)")
    what.add_argument("--defaults", nargs="?", const=schemas / "first_defaults.json", type=Path, metavar="PATH",
                      help="record new fields' first defaults (default: workflow/schemas/first_defaults.json)")
    args = parser.parse_args(argv)
    if args.schema is not None:
        args.schema.write_text(schema_text())
        print(f"wrote {args.schema}")
        return
    added = record_first_defaults(args.defaults)
    print(f"{args.defaults}: recorded {len(added)} new field(s)" + (": " + ", ".join(added) if added else ""))
    for problem in defaults_changed(args.defaults):
        print("  " + problem)


if __name__ == "__main__":  # pragma: no cover - a maintenance command
    main()
