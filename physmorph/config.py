"""Configuration: load the YAML profiles, validate against the schema, typed views.

``load_config(paths)`` merges the files left to right (later keys override, nested mappings
merge), exactly as Snakemake merges ``--configfile`` onto the Snakefile's ``configfile``.
``validate_config`` checks the merged dict against ``workflow/schemas/config.schema.yaml``
and the cross-references (experiment shapes, table lists); every error names the key.
"""

from __future__ import annotations

import copy
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jsonschema
import yaml

REPO_ROOT = Path(__file__).resolve().parent.parent
SCHEMA_PATH = REPO_ROOT / "workflow" / "schemas" / "config.schema.yaml"
RES_PATTERN = r"(\d+)x(\d+)x(\d+)"


class ConfigError(ValueError):
    """Invalid configuration; the message names the offending key."""


def deep_merge(base: dict, override: dict) -> dict:
    out = copy.deepcopy(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def load_config(*paths: str | Path, overrides: dict | None = None) -> dict:
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
    return validate_config(cfg)


def _key_path(path) -> str:
    return ".".join(str(p) for p in path) or "<root>"


def validate_config(cfg: dict) -> dict:
    """Return ``cfg`` if valid, else raise ConfigError naming the first offending key."""
    schema = yaml.safe_load(SCHEMA_PATH.read_text())
    validator = jsonschema.Draft202012Validator(schema)
    errors = sorted(validator.iter_errors(cfg), key=lambda e: (len(e.absolute_path), list(map(str, e.absolute_path))))
    if errors:
        err = errors[0]
        path = list(err.absolute_path)
        if err.validator == "additionalProperties":
            unknown = sorted(set(err.instance) - set(err.schema.get("properties", {})))
            raise ConfigError(f"config key '{_key_path(path + unknown[:1])}': unknown key "
                              f"(allowed: {', '.join(sorted(err.schema.get('properties', {})))})")
        if err.validator == "required":
            missing = re.findall(r"'([^']+)' is a required property", err.message)
            raise ConfigError(f"config key '{_key_path(path + missing[:1])}': required key is missing")
        raise ConfigError(f"config key '{_key_path(path)}': {err.message}")
    shapes = cfg["shapes"]
    for name, spec in shapes.items():
        if spec["kind"] == "file":
            if "file" not in spec:
                raise ConfigError(f"config key 'shapes.{name}.file': required for kind 'file'")
            if spec["file"] not in cfg.get("raw_meshes", {}):
                raise ConfigError(f"config key 'shapes.{name}.file': '{spec['file']}' is not listed in raw_meshes")
        if spec["kind"] == "letter" and "glyph" not in spec:
            raise ConfigError(f"config key 'shapes.{name}.glyph': required for kind 'letter'")
    for name, exp in cfg["experiments"].items():
        for role in ("source", "target"):
            if exp[role] not in shapes:
                raise ConfigError(f"config key 'experiments.{name}.{role}': unknown shape '{exp[role]}' "
                                  f"(known: {', '.join(sorted(shapes))})")
    for i, shape in enumerate(cfg["tables"].get("shapes", [])):
        if shape not in shapes:
            raise ConfigError(f"config key 'tables.shapes[{i}]': unknown shape '{shape}'")
    if "tradeoff" in cfg and cfg["tradeoff"]["experiment"] not in cfg["experiments"]:
        raise ConfigError(f"config key 'tradeoff.experiment': unknown experiment '{cfg['tradeoff']['experiment']}'")
    for i, name in enumerate(cfg["tables"].get("experiments", [])):
        if name not in cfg["experiments"]:
            raise ConfigError(f"config key 'tables.experiments[{i}]': unknown experiment '{name}'")
    return cfg


def experiment(cfg: dict, name: str) -> dict:
    """The experiment ``name``; an unknown name is an error listing the known ones."""
    if name not in cfg["experiments"]:
        known = ", ".join(sorted(cfg["experiments"])) or "none"
        raise ConfigError(f"unknown experiment '{name}' (known: {known})")
    return cfg["experiments"][name]


@dataclass(frozen=True)
class SamplingConfig:
    grid_res: int
    ppc_surface: int
    ppc_interior: int
    density: float
    sigma_scale: float

    @property
    def tag(self) -> str:
        """The resolution tag used in file names: {grid_res}x{ppc_surface}x{ppc_interior}."""
        return f"{self.grid_res}x{self.ppc_surface}x{self.ppc_interior}"

    @classmethod
    def from_tag(cls, tag: str, cfg: dict) -> "SamplingConfig":
        m = re.fullmatch(RES_PATTERN, tag)
        if not m:
            raise ConfigError(f"resolution tag '{tag}' must look like 32x2x1 (grid x ppc_surface x ppc_interior)")
        s = cfg["sampling"]
        return cls(int(m[1]), int(m[2]), int(m[3]), float(s["density"]), float(s["sigma_scale"]))

    @classmethod
    def from_config(cls, cfg: dict) -> "SamplingConfig":
        s = cfg["sampling"]
        return cls(int(s["grid_res"]), int(s["ppc_surface"]), int(s["ppc_interior"]),
                   float(s["density"]), float(s["sigma_scale"]))


@dataclass(frozen=True)
class TargetConfig:
    cameras: int = 8
    elevation_deg: float = 21.0
    fov_y_deg: float = 40.0
    distance: float = 48.0
    width: int = 160
    height: int = 90
    supersample: int = 3
    surface_points: int = 20000

    @classmethod
    def from_config(cls, cfg: dict) -> "TargetConfig":
        return cls(**cfg["target"])


def shape_entry(cfg: dict, name: str) -> dict[str, Any]:
    if name not in cfg["shapes"]:
        raise ConfigError(f"unknown shape '{name}' (known: {', '.join(sorted(cfg['shapes']))})")
    return cfg["shapes"][name]
