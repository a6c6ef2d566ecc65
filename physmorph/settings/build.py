"""Building the settings from YAML: files merged left to right, a config class built from a
mapping with every refusal naming its dotted key.

``load_mapping`` merges exactly as Snakemake merges ``--configfile`` onto the Snakefile's
``configfile`` (later keys override, nested mappings merge); ``build`` validates one section by its
declaration (physmorph.settings.base).
"""

from __future__ import annotations

import copy
from dataclasses import fields
from pathlib import Path
from typing import Any

import yaml

from physmorph.settings.base import validate_plain_dataclass, with_prefix
from physmorph.settings.errors import ConfigError
from physmorph.settings.retired import RETIRED_METHOD_SETTINGS


def dotted_overrides(items: list[str]) -> dict:
    """``["morph.gamma=0.3", "mpm.dt=1e-3"]`` (dotted key = YAML value, as a script's ``--set``
    takes them) as the nested mapping load_settings merges on the config files."""
    out: dict = {}
    for item in items:
        key, _, value = item.partition("=")
        node = out
        parts = key.split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = yaml.safe_load(value)
    return out


def deep_merge(base: dict, override: dict) -> dict:
    out = copy.deepcopy(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def fail_at(key: str, msg: str):
    """Refuse the config at the dotted ``key`` (the root where empty)."""
    raise ConfigError.for_key(key or "<root>", msg)


def build(cls, data: Any, where: str = "", derived: dict[str, tuple[str, Any]] | None = None):
    """``cls`` from the mapping ``data`` (validated by its declaration); errors name ``where.key``.
    ``cls`` is a config class (physmorph.settings.base) or a plain dataclass (validated by pydantic too).

    derived: fields not settable here, name -> (where it is set, value)."""
    derived = derived or {}
    if data is None:
        data = {}
    if not isinstance(data, dict):
        fail_at(where, f"expected a mapping, got {data!r}")
    settable = sorted(f.name for f in fields(cls) if f.init and f.name not in derived)
    for k in data:
        if k in derived:
            fail_at(with_prefix(where, str(k)), f"not settable here: it is set by {derived[k][0]}")
        if k not in settable:  # before the values: a misspelt key is the likelier mistake
            fail_at(with_prefix(where, str(k)), _unknown_key_reason(with_prefix(where, str(k)), settable))
    kwargs = {**data, **{k: v for k, (_, v) in derived.items()}}
    if hasattr(cls, "__pydantic_validator__"):
        try:
            return cls(**{str(k): v for k, v in kwargs.items()})
        except ValueError as exc:
            if not hasattr(exc, "reason"):
                raise
            key = exc.key if exc.key != "<root>" else ""
            raise ConfigError.for_key(with_prefix(where, key or ""), exc.reason) from None
    try:
        return validate_plain_dataclass(cls, kwargs)
    except ConfigError as exc:
        raise ConfigError.for_key(with_prefix(where, exc.key if exc.key != "<root>" else ""), exc.reason) from None


def _unknown_key_reason(key: str, settable: list[str]) -> str:
    """Why ``key`` is refused: a setting the code no longer has (physmorph.settings.retired) is
    named as such, with the value the method always ran with; any other, with the keys allowed."""
    method_key = key.removeprefix("morph.")
    if method_key in RETIRED_METHOD_SETTINGS:
        return (f"no longer a setting: the method runs as it did with {RETIRED_METHOD_SETTINGS[method_key]!r} "
                "(docs/study/log.md holds what the other values did)")
    return f"unknown key (allowed: {', '.join(settable)})"


def load_mapping(*paths: str | Path, overrides: dict | None = None) -> dict:
    cfg: dict = {}
    for p in paths:
        p = Path(p)
        if not p.exists():
            raise ConfigError(f"{p}: config file not found")
        try:
            data = yaml.safe_load(p.read_text()) or {}
        except yaml.YAMLError as exc:
            raise ConfigError(f"{p}: not valid YAML ({exc})") from exc
        if not isinstance(data, dict):
            raise ConfigError(f"{p}: top level must be a mapping")
        cfg = deep_merge(cfg, data)
    if overrides:
        cfg = deep_merge(cfg, overrides)
    return cfg
