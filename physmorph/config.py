"""The workflow's settings: one typed, frozen object built from the merged YAML profiles.

``load_settings(paths)`` merges the YAML files left to right (later keys override, nested mappings
merge), exactly as Snakemake merges ``--configfile`` onto the Snakefile's ``configfile``, then
``Settings.from_mapping`` turns the dict into frozen dataclasses. That conversion is the one
validator: unknown keys, wrong types and values outside a field's allowed set are refused with
the dotted key and the allowed values; numbers are accepted as int, float or numeric strings
(``--config 'mpm={smoothing: 0.5}'`` hands Snakemake a string); every experiment is resolved to
its full :class:`~physmorph.morph_config.MorphConfig` and a memory estimate per stage is checked against
the machine's memory, so a bad config fails before any job runs.

Every default lives in a dataclass: the sections ``mpm``, ``render``, ``plasticity``, ``surface``
and ``morph`` are the library's own config classes, the rest is defined here. ``config/config.yaml``
restates the defaults it documents (a test checks they agree). The workflow's JSON schema
(``workflow/schemas/config.schema.yaml``) is generated from these classes (``json_schema``).
"""

from __future__ import annotations

import copy
import json
import math
import os
import re
import types
from dataclasses import MISSING as dataclasses_MISSING
from dataclasses import asdict, dataclass, field, fields, is_dataclass, replace
from pathlib import Path
from typing import Any, Literal, Union, get_args, get_origin, get_type_hints

import yaml

from physmorph.config_error import ConfigError
from physmorph.grid import DOMAIN_HI, DOMAIN_LO
from physmorph.morph_config import MorphConfig
from physmorph.mpm.config import MPMConfig
from physmorph.mpm.memory import bytes_per_particle_substep
from physmorph.plasticity import PlasticityConfig
from physmorph.render.config import RenderConfig
from physmorph.export.settings import ExportConfig
from physmorph.surface import SurfaceMaskConfig
from physmorph.tradeoff_points import TradeoffPoint, tradeoff_points

RES_PATTERN = r"(\d+)x(\d+)x(\d+)"


def deep_merge(base: dict, override: dict) -> dict:
    out = copy.deepcopy(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


# --------------------------------------------------------------------------------------------
# Typed conversion (the one validator) and its JSON-schema twin
# --------------------------------------------------------------------------------------------

def _join(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


def _fail(key: str, msg: str):
    raise ConfigError.for_key(key or "<root>", msg)


def _number(value, key: str, what: str = "a number") -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        _fail(key, f"expected {what}, got {value!r}")
    try:
        out = float(value.strip()) if isinstance(value, str) else float(value)
    except ValueError:
        _fail(key, f"expected {what}, got {value!r}")
    if not math.isfinite(out):
        _fail(key, f"expected a finite number, got {value!r}")
    return out


def coerce(value: Any, tp: Any, key: str) -> Any:
    """``value`` as type ``tp`` (int, float, bool, str, Literal, Optional, tuple, dict, dataclass)."""
    origin = get_origin(tp)
    if tp is Any:
        return value
    if origin is Literal:
        choices = get_args(tp)
        if isinstance(value, str) and value in choices:
            return value
        _fail(key, f"{value!r} is not allowed (allowed: {', '.join(map(str, choices))})")
    if origin in (Union, types.UnionType):
        args = [a for a in get_args(tp) if a is not type(None)]
        if value is None:
            if len(args) < len(get_args(tp)):
                return None
            _fail(key, "must be set (got null)")
        first = None
        for a in args:
            try:
                return coerce(value, a, key)
            except ConfigError as exc:
                first = first or exc
        raise first
    if value is None:
        _fail(key, "must be set (got null)")
    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.strip().lower() in ("true", "false"):
            return value.strip().lower() == "true"
        _fail(key, f"expected true or false, got {value!r}")
    if tp is int:
        num = _number(value, key, "an integer")
        if not num.is_integer():
            _fail(key, f"expected an integer, got {value!r}")
        return int(num)
    if tp is float:
        return _number(value, key)
    if tp is str:
        if not isinstance(value, str):
            _fail(key, f"expected a string, got {value!r}")
        return value
    if origin is tuple:
        args = get_args(tp)
        if not isinstance(value, (list, tuple)):
            _fail(key, f"expected a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(coerce(v, args[0], f"{key}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            _fail(key, f"expected {len(args)} values, got {len(value)}")
        return tuple(coerce(v, a, f"{key}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
    if origin is dict:
        _, vt = get_args(tp)
        if not isinstance(value, dict):
            _fail(key, f"expected a mapping, got {value!r}")
        return {str(k): coerce(v, vt, _join(key, str(k))) for k, v in value.items()}
    if is_dataclass(tp):
        return build(tp, value, key)
    raise TypeError(f"{key}: unsupported field type {tp!r}")


def _failing_key(cls, exc: Exception, where: str) -> str:
    """The field a dataclass's own check complains about: its messages start with the field name."""
    m = re.match(r"\s*(?:[A-Za-z_]+\.)?([A-Za-z_]+)", str(exc))
    names = {f.name for f in fields(cls)}
    return _join(where, m[1]) if m and m[1] in names else where


def build(cls, data: Any, where: str = "", derived: dict[str, tuple[str, Any]] | None = None):
    """``cls(**data)`` with every value coerced to its field's type; errors name ``where.key``.

    derived: fields not settable here, name -> (where it is set, value)."""
    derived = derived or {}
    if data is None:
        data = {}
    if not isinstance(data, dict):
        _fail(where, f"expected a mapping, got {data!r}")
    hints = get_type_hints(cls)
    names = [f.name for f in fields(cls) if f.init and f.name not in derived]
    for k in data:
        if k in derived:
            _fail(_join(where, k), f"not settable here: it is set by {derived[k][0]}")
        if k not in names:
            _fail(_join(where, str(k)), f"unknown key (allowed: {', '.join(sorted(names))})")
    kwargs = {k: coerce(v, hints[k], _join(where, k)) for k, v in data.items()}
    kwargs.update({k: v for k, (_, v) in derived.items()})
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (ValueError, TypeError) as exc:
        raise ConfigError.for_key(_failing_key(cls, exc, where) or "<root>", exc) from exc


def to_plain(obj: Any) -> Any:
    """Dataclasses, tuples and mappings as JSON-ready dicts and lists."""
    if is_dataclass(obj):
        obj = asdict(obj)
    if isinstance(obj, dict):
        return {str(k): to_plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_plain(v) for v in obj]
    return obj


def canonical_json(obj: Any) -> str:
    """One string per value (sorted keys, no spaces): the full record a stage writes into its file."""
    return json.dumps(to_plain(obj), sort_keys=True, separators=(",", ":"))


# --------------------------------------------------------------------------------------------
# What rule params carry: every setting that differs from its default
# --------------------------------------------------------------------------------------------
# Snakemake reruns a job when its params string changes. If params held every field, adding a
# field to a config class (a new option whose default changes nothing) would change the params
# of every job that holds that class and rerun whole result trees for identical numbers. So a
# field at its default is left out, and the job rebuilds its config from what is left (a left-out
# field takes its default). The one case this would get wrong is a *changed* default: runs made
# with the old one would keep their params and not rerun. A record of first defaults (the
# workflow's workflow/schemas/first_defaults.json, which ``python -m physmorph.config --defaults``
# extends) holds each field's first default (append-only); a field whose default has changed since
# must be named in its class's ALWAYS_IN_PARAMS (a ClassVar), which puts it in every params string,
# so the runs that omitted it rerun once (tests/test_config.py checks both).


def _field_default(f) -> Any:
    if f.default is not dataclasses_MISSING:
        return f.default
    if f.default_factory is not dataclasses_MISSING:
        return f.default_factory()
    return dataclasses_MISSING


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
                default = _field_default(f)
                if is_dataclass(value) and not isinstance(value, type):
                    # Left out only when empty against its own class's defaults and the field's
                    # default is that class's default instance (so rebuilding gives it back).
                    if plain == {} and to_plain(default) == to_plain(type(value)()):
                        continue
                elif default is not dataclasses_MISSING and to_plain(value) == to_plain(default):
                    continue
            out[f.name] = plain
        return out
    if isinstance(obj, dict):
        return {str(k): without_defaults(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [without_defaults(v) for v in obj]
    return obj


def params_json(obj: Any) -> str:
    """What a rule's params hold: canonical JSON of ``obj`` without its fields at their defaults."""
    return json.dumps(without_defaults(obj), sort_keys=True, separators=(",", ":"))


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
            default = _field_default(f)
            if default is not dataclasses_MISSING and not is_dataclass(default):
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
            problems.append(f"{key}: not recorded in {path.name}; run `python -m physmorph.config --defaults`")
            continue
        cls_name, name = key.split(".", 1)
        if recorded[key] != default and name not in getattr(classes[cls_name], "ALWAYS_IN_PARAMS", ()):
            problems.append(f"{key}: default changed {recorded[key]!r} -> {default!r}, so runs made with the old "
                            f"default (which left it out of their params) would not rerun; add '{name}' to "
                            f"{cls_name}.ALWAYS_IN_PARAMS")
    return problems


def schema_of(tp: Any, derived: dict | None = None) -> dict:
    origin = get_origin(tp)
    if tp is Any:
        return {}
    if origin is Literal:
        return {"enum": list(get_args(tp))}
    if origin in (Union, types.UnionType):
        opts = [schema_of(a) for a in get_args(tp) if a is not type(None)]
        opts += [{"type": "null"}] if type(None) in get_args(tp) else []
        return opts[0] if len(opts) == 1 else {"anyOf": opts}
    simple = {bool: "boolean", int: "integer", float: "number", str: "string"}
    if tp in simple:
        # numbers may come as strings from --config; the settings accept both
        return {"type": [simple[tp], "string"]} if tp in (int, float) else {"type": simple[tp]}
    if origin is tuple:
        args = get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return {"type": "array", "items": schema_of(args[0])}
        return {"type": "array", "prefixItems": [schema_of(a) for a in args], "minItems": len(args),
                "maxItems": len(args)}
    if origin is dict:
        return {"type": "object", "additionalProperties": schema_of(get_args(tp)[1])}
    if is_dataclass(tp):
        hints = get_type_hints(tp)
        derived = derived or {}
        props, required = {}, []
        for f in fields(tp):
            if not f.init or f.name in derived:
                continue
            sub = schema_of(hints[f.name])
            if f.default is not dataclasses_MISSING and not is_dataclass(f.default):
                sub["default"] = to_plain(f.default)
            elif f.default is dataclasses_MISSING and f.default_factory is dataclasses_MISSING:
                required.append(f.name)
            props[f.name] = sub
        out = {"type": "object", "additionalProperties": False, "properties": props}
        if tp.__doc__ and not tp.__doc__.startswith(tp.__name__ + "("):
            out["description"] = tp.__doc__.strip().splitlines()[0]
        if required:
            out["required"] = required
        return out
    raise TypeError(f"unsupported field type {tp!r}")


# --------------------------------------------------------------------------------------------
# The sections defined here (the solver, renderer, plasticity, mask and morph sections are the
# library's own dataclasses)
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class RawMesh:
    """A raw mesh downloaded from a pinned URL and checked against its SHA-256."""

    url: str
    sha256: str

    def __post_init__(self) -> None:
        if not re.fullmatch(r"[0-9a-f]{64}", self.sha256):
            raise ValueError(f"sha256 must be 64 lowercase hex digits, got {self.sha256!r}")


@dataclass(frozen=True)
class ShapeSettings:
    """One shape: a raw mesh (``file``: a raw_meshes entry; ``path``: a mesh on disk), an
    isosphere or an extruded letter, normalised to ``size`` domain units."""

    kind: Literal["file", "isosphere", "letter"]
    file: str | None = None
    path: str | None = None
    glyph: str | None = None
    size: float = 16.0
    depth: float | None = None

    def __post_init__(self) -> None:
        if self.kind == "file" and (self.file is None) == (self.path is None):
            raise ValueError("file or path: kind 'file' takes exactly one of 'file' (a raw_meshes entry) or "
                             "'path' (a mesh file on disk)")
        if self.kind != "file" and (self.file or self.path):
            raise ValueError(f"file or path: only kind 'file' takes them (kind is {self.kind!r})")
        if self.kind == "letter" and (not self.glyph or len(self.glyph) != 1):
            raise ValueError(f"glyph: kind 'letter' needs a single character, got {self.glyph!r}")
        if not self.size > 0:
            raise ValueError(f"size must be > 0, got {self.size}")
        if self.depth is not None and not self.depth > 0:
            raise ValueError(f"depth must be > 0, got {self.depth}")


@dataclass(frozen=True)
class SamplingConfig:
    """Particle sampling on the simulation grid (file tag {grid_res}x{ppc_surface}x{ppc_interior})."""

    grid_res: int = 32
    ppc_surface: int = 2
    ppc_interior: int = 1
    density: float = 75.0
    sigma_scale: float = 0.7

    def __post_init__(self) -> None:
        if self.grid_res < 8:
            raise ValueError(f"grid_res must be >= 8, got {self.grid_res}")
        for k in ("ppc_surface", "ppc_interior"):
            if getattr(self, k) < 1:
                raise ValueError(f"{k} must be >= 1, got {getattr(self, k)}")
        for k in ("density", "sigma_scale"):
            if not getattr(self, k) > 0:
                raise ValueError(f"{k} must be > 0, got {getattr(self, k)}")

    @property
    def tag(self) -> str:
        """The resolution tag used in file names: {grid_res}x{ppc_surface}x{ppc_interior}."""
        return f"{self.grid_res}x{self.ppc_surface}x{self.ppc_interior}"

    def with_tag(self, tag: str) -> "SamplingConfig":
        m = re.fullmatch(RES_PATTERN, tag)
        if not m:
            raise ConfigError(f"resolution tag '{tag}' must look like 32x2x1 (grid x ppc_surface x ppc_interior)")
        return replace(self, grid_res=int(m[1]), ppc_surface=int(m[2]), ppc_interior=int(m[3]))


@dataclass(frozen=True)
class TargetConfig:
    """Target rasterization: ring cameras, the target's grid mass and surface points."""

    cameras: int = 8
    elevation_deg: float = 21.0
    fov_y_deg: float = 40.0
    distance: float = 36.0
    width: int = 160
    height: int = 90
    supersample: int = 3  # rays per pixel per axis for the exact coverage alpha
    surface_points: int = 20000  # target surface samples for Chamfer

    def __post_init__(self) -> None:
        checks = [("cameras", self.cameras >= 1, ">= 1"), ("elevation_deg", -89 <= self.elevation_deg <= 89, "in [-89, 89]"),
                  ("fov_y_deg", 0 < self.fov_y_deg < 180, "in (0, 180)"), ("distance", self.distance > 0, "> 0"),
                  ("width", self.width >= 4, ">= 4"), ("height", self.height >= 4, ">= 4"),
                  ("supersample", 1 <= self.supersample <= 8, "in [1, 8]"),
                  ("surface_points", self.surface_points >= 100, ">= 100")]
        for name, ok, rule in checks:
            if not ok:
                raise ValueError(f"{name} must be {rule}, got {getattr(self, name)}")


@dataclass(frozen=True)
class Experiment:
    """One morph run; unset fields take the global sections' values."""

    source: str
    target: str
    method: Literal["physics_only", "f_inject", "full", "position_inject"]
    drag: float | None = None  # mpm.drag
    frames: int | None = None  # morph.frames
    cameras: int | None = None  # morph.cameras (render-loss views)
    gamma: float | None = None  # morph.gamma
    gamma_x: float | None = None  # morph.gamma_x
    grad_iters: int | None = None  # mpm.grad_iters
    plasticity_start: int | None = None  # plasticity.start_frame
    release_frames: int | None = None  # morph.release_frames


# experiment key -> (section, field) it overrides
EXPERIMENT_OVERRIDES = {"drag": ("mpm", "drag"), "grad_iters": ("mpm", "grad_iters"),
                        "plasticity_start": ("plasticity", "start_frame"), "frames": ("morph", "frames"),
                        "cameras": ("morph", "cameras"), "gamma": ("morph", "gamma"), "gamma_x": ("morph", "gamma_x"),
                        "release_frames": ("morph", "release_frames")}


@dataclass(frozen=True)
class Tradeoff:
    """The speed/accuracy study: the base experiment with one knob changed at a time (physmorph.tradeoff)."""

    experiment: str
    frames: int
    knobs: dict[str, tuple[Any, ...]] = field(default_factory=dict)
    # The base point's threads: the study's own, so the workflow's `threads` (which changes no
    # result) neither adds nor removes a point nor changes what the points' times measure.
    threads: int = 2

    def __post_init__(self) -> None:
        if self.frames < 1:
            raise ValueError(f"frames must be >= 1, got {self.frames}")
        if self.threads < 1:
            raise ValueError(f"threads must be >= 1, got {self.threads}")


@dataclass(frozen=True)
class Tables:
    """What ``snakemake tables`` builds: the shapes' data and the experiments' runs."""

    shapes: tuple[str, ...] = ()
    experiments: tuple[str, ...] = ()


@dataclass(frozen=True)
class Settings:
    """Everything the workflow needs, typed and frozen. Build with :meth:`from_mapping`."""

    profile: str = "default"
    device: Literal["auto", "cpu", "cuda"] = "auto"
    threads: int = 2
    mesh_dir: str | None = None
    seed: int = 0
    domain: tuple[float, float] = (DOMAIN_LO, DOMAIN_HI)
    max_memory_mb: int | None = None  # refuse stages estimated above this; null: this machine's memory
    morph_gpus: int = 0  # GPUs a morph job asks a cluster scheduler for (resources.gpu)
    raw_meshes: dict[str, RawMesh] = field(default_factory=dict)
    shapes: dict[str, ShapeSettings] = field(default_factory=dict)
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    target: TargetConfig = field(default_factory=TargetConfig)
    mpm: MPMConfig = field(default_factory=MPMConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    plasticity: PlasticityConfig = field(default_factory=PlasticityConfig)
    surface: SurfaceMaskConfig = field(default_factory=SurfaceMaskConfig)
    morph: Any = None  # physmorph.morph_config.MorphConfig (its mpm/render/plasticity/surface are the sections above)
    experiments: dict[str, Experiment] = field(default_factory=dict)
    tradeoff: Tradeoff | None = None
    tables: Tables = field(default_factory=Tables)
    export: ExportConfig = field(default_factory=ExportConfig)

    # ---- construction -------------------------------------------------------------------
    @classmethod
    def from_mapping(cls, cfg: dict) -> "Settings":
        """Typed settings from the merged config dict; raises ConfigError naming the key."""
        if not isinstance(cfg, dict):
            _fail("", f"the config must be a mapping, got {cfg!r}")
        hints = get_type_hints(cls)
        allowed = {f.name for f in fields(cls)}
        for k in cfg:
            if k not in allowed:
                _fail(str(k), f"unknown key (allowed: {', '.join(sorted(allowed))})")
        plain = {k: coerce(cfg[k], hints[k], k) for k in ("profile", "device", "threads", "mesh_dir", "seed", "domain",
                                                           "max_memory_mb", "morph_gpus") if k in cfg}
        s = cls(**plain)
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]*", s.profile):
            _fail("profile", f"must be a plain name (letters, digits, _ . -): it names results/{{profile}}/, got {s.profile!r}")
        if s.threads < 1:
            _fail("threads", f"must be >= 1, got {s.threads}")
        if s.seed < 0:
            _fail("seed", f"must be >= 0, got {s.seed}")
        if not s.domain[1] > s.domain[0]:
            _fail("domain", f"needs [lo, hi] with hi > lo, got {list(s.domain)}")
        if s.morph_gpus < 0:
            _fail("morph_gpus", f"must be >= 0, got {s.morph_gpus}")
        if s.max_memory_mb is not None and s.max_memory_mb < 1:
            _fail("max_memory_mb", f"must be >= 1 (or null), got {s.max_memory_mb}")
        s = replace(
            s, sampling=build(SamplingConfig, cfg.get("sampling"), "sampling"),
            raw_meshes=coerce(cfg.get("raw_meshes") or {}, hints["raw_meshes"], "raw_meshes"),
            shapes=coerce(cfg.get("shapes") or {}, hints["shapes"], "shapes"),
            target=build(TargetConfig, cfg.get("target"), "target"),
            experiments=coerce(cfg.get("experiments") or {}, hints["experiments"], "experiments"),
            tradeoff=coerce(cfg.get("tradeoff"), hints["tradeoff"], "tradeoff"),
            tables=build(Tables, cfg.get("tables"), "tables"),
            export=build(ExportConfig, cfg.get("export"), "export"))
        s._check_references()
        # Memory first: a grid too big for the machine says so before the solver's own checks.
        raw_mpm = cfg.get("mpm") if isinstance(cfg.get("mpm"), dict) else {}
        mpm_hints = get_type_hints(MPMConfig)
        s.check_memory(types.SimpleNamespace(**{
            k: coerce(raw_mpm[k], mpm_hints[k], f"mpm.{k}") if k in raw_mpm else getattr(MPMConfig, k)
            for k in ("substeps", "precision", "control", "optimizer")}))
        mpm = build(MPMConfig, cfg.get("mpm"), "mpm", derived=_section_derived("mpm", s.sampling, s.device, s.domain))
        render = build(RenderConfig, cfg.get("render"), "render", derived=_section_derived("render", s.sampling, s.device, s.domain))
        plasticity = build(PlasticityConfig, cfg.get("plasticity"), "plasticity")
        surface = build(SurfaceMaskConfig, cfg.get("surface"), "surface")
        morph = build(MorphConfig, cfg.get("morph"), "morph",
                      derived={"method": ("experiments.<name>.method", "full"), "mpm": ("the mpm section", mpm),
                               "render": ("the render section", render),
                               "plasticity": ("the plasticity section", plasticity),
                               "surface": ("the surface section", surface)})
        s = replace(s, mpm=mpm, render=render, plasticity=plasticity, surface=surface, morph=morph)
        for name in s.experiments:
            s.experiment_config(name)  # every experiment's full settings, checked now
        if s.tradeoff is not None:
            try:
                points = tradeoff_points(s)
            except ValueError as exc:
                raise ConfigError(str(exc)) from exc
            for p in points.values():
                s.point_config(p)
        return s

    def _check_references(self) -> None:
        for name, spec in self.shapes.items():
            if not re.fullmatch(r"[A-Za-z][A-Za-z0-9]*", name):
                _fail(f"shapes.{name}", "a shape name is letters and digits, starting with a letter")
            if spec.kind == "file" and spec.file is not None and spec.file not in self.raw_meshes:
                _fail(f"shapes.{name}.file", f"'{spec.file}' is not listed in raw_meshes "
                                             f"(known: {', '.join(sorted(self.raw_meshes)) or 'none'}); "
                                             "for a mesh on disk use 'path' instead")
        for name, exp in self.experiments.items():
            if not re.fullmatch(r"[A-Za-z0-9_]+", name):
                _fail(f"experiments.{name}", "an experiment name is letters, digits and _")
            for role in ("source", "target"):
                if getattr(exp, role) not in self.shapes:
                    _fail(f"experiments.{name}.{role}", f"unknown shape '{getattr(exp, role)}' "
                                                        f"(known: {', '.join(sorted(self.shapes))})")
        for i, shape in enumerate(self.tables.shapes):
            if shape not in self.shapes:
                _fail(f"tables.shapes[{i}]", f"unknown shape '{shape}' (known: {', '.join(sorted(self.shapes))})")
        for i, name in enumerate(self.tables.experiments):
            if name not in self.experiments:
                _fail(f"tables.experiments[{i}]", f"unknown experiment '{name}'")
        if self.tradeoff is not None and self.tradeoff.experiment not in self.experiments:
            _fail("tradeoff.experiment", f"unknown experiment '{self.tradeoff.experiment}'")

    # ---- resolution ---------------------------------------------------------------------
    def experiment(self, name: str) -> Experiment:
        """The experiment ``name``; an unknown name is an error listing the known ones."""
        if name not in self.experiments:
            known = ", ".join(sorted(self.experiments)) or "none"
            raise ConfigError(f"unknown experiment '{name}' (known: {known})")
        return self.experiments[name]

    def shape(self, name: str) -> ShapeSettings:
        if name not in self.shapes:
            raise ConfigError(f"unknown shape '{name}' (known: {', '.join(sorted(self.shapes))})")
        return self.shapes[name]

    def experiment_config(self, name: str, sampling: SamplingConfig | None = None,
                          target: TargetConfig | None = None, **exp_changes):
        """The full MorphConfig of experiment ``name``: global sections, then the experiment's own
        keys. ``sampling``/``target``/``exp_changes``: another resolution (the tradeoff points)."""
        exp = replace(self.experiment(name), **exp_changes)
        sampling = sampling or self.sampling
        target = target or self.target
        where = f"experiments.{name}"
        changes: dict[str, dict] = {"mpm": {}, "plasticity": {}, "morph": {}}
        keys: dict[tuple[str, str], str] = {}
        for key, (section, fname) in EXPERIMENT_OVERRIDES.items():
            if getattr(exp, key) is not None:
                changes[section][fname] = getattr(exp, key)
                keys[(section, fname)] = f"{where}.{key}"
        mpm = _replace(self.mpm, "mpm", keys, grid_res=sampling.grid_res, density=sampling.density,
                       **changes["mpm"])
        plasticity = _replace(self.plasticity, "plasticity", keys, **changes["plasticity"])
        cfg = _replace(self.morph, "morph", {**keys, ("morph", "method"): f"{where}.method"}, method=exp.method,
                       mpm=mpm, plasticity=plasticity, render=self.render, surface=self.surface, **changes["morph"])
        if cfg.cameras is not None and cfg.cameras > target.cameras:
            _fail(keys.get(("morph", "cameras"), "morph.cameras"),
                  f"{cfg.cameras} render-loss views, but the target has only {target.cameras} (target.cameras)")
        return cfg

    def point_config(self, point):
        """(sampling, target, MorphConfig) of a tradeoff point (physmorph.tradeoff.TradeoffPoint)."""
        sampling = replace(self.sampling, grid_res=point.grid_res, ppc_surface=point.ppc_surface,
                           ppc_interior=point.ppc_interior)
        target = replace(self.target, width=point.width, height=point.height)
        cfg = self.experiment_config(self.tradeoff.experiment, sampling, target, cameras=point.cameras,
                                     grad_iters=point.grad_iters, frames=point.frames)
        try:
            # release_frames 0: a point measures the morph; no study quantity reads the release probe,
            # which cost the test profile's 3-frame points most of their run time
            cfg = replace(cfg, release_frames=0,
                          mpm=replace(cfg.mpm, learning_rate=point.learning_rate, precision=point.precision))
        except ValueError as exc:
            _fail(f"tradeoff.knobs.{point.knob or 'learning_rate'}", str(exc))
        return sampling, target, cfg

    # ---- memory -------------------------------------------------------------------------
    def memory_limit_mb(self) -> float:
        if self.max_memory_mb is not None:
            return float(self.max_memory_mb)
        return physical_memory_mb()

    def memory_estimates(self, mpm=None) -> list["MemoryEstimate"]:
        """One estimate per stage and resolution the config asks for (the largest matters).
        ``mpm``: what has substeps, precision and control (default: the mpm section)."""
        mpm = mpm or self.mpm
        used = set(self.tables.shapes)
        for exp in self.experiments.values():
            used.update((exp.source, exp.target))
        out = []
        for shape in sorted(used):
            out.append(sampling_memory(self.shapes[shape], self.sampling, self.domain, f"sample_particles {shape}"))
            out.append(target_memory(self.sampling, self.target, f"rasterize_target {shape}"))
        for name in sorted(self.experiments):
            out.append(morph_memory(self.shapes[self.experiments[name].source], self.sampling, self.target,
                                    mpm, self.domain, f"morph {name}"))
        if self.tradeoff is not None:
            src = self.shapes[self.experiments[self.tradeoff.experiment].source]
            try:
                points = tradeoff_points(self)
            except ValueError as exc:
                raise ConfigError(str(exc)) from exc
            for pname, p in points.items():
                sampling = replace(self.sampling, grid_res=p.grid_res, ppc_surface=p.ppc_surface,
                                   ppc_interior=p.ppc_interior)
                target = replace(self.target, width=p.width, height=p.height)
                point_mpm = types.SimpleNamespace(substeps=mpm.substeps, precision=p.precision, control=mpm.control,
                                                  optimizer=mpm.optimizer)
                out.append(morph_memory(src, sampling, target, point_mpm, self.domain, f"tradeoff point {pname}"))
        return out

    def check_memory(self, mpm=None) -> None:
        limit = self.memory_limit_mb()
        est = max(self.memory_estimates(mpm), key=lambda e: e.mb, default=None)
        if est is not None and est.mb > limit:
            key = "max_memory_mb" if self.max_memory_mb is not None else "max_memory_mb (null: this machine's memory)"
            raise ConfigError(
                f"config: {est.stage} needs an estimated {est.mb:,.0f} MB ({est.detail}) at sampling.grid_res "
                f"{self.sampling.grid_res}, sampling.ppc_surface {self.sampling.ppc_surface}, "
                f"{self.target.width}x{self.target.height} images: above the limit of {limit:,.0f} MB ({key}); "
                "lower sampling.grid_res, sampling.ppc_surface or the image size, or raise max_memory_mb on a "
                "bigger machine", key="max_memory_mb")


def _section_derived(section: str, sampling: SamplingConfig, device: str, domain) -> dict:
    if section == "mpm":
        return {"grid_res": ("sampling.grid_res", sampling.grid_res), "density": ("sampling.density", sampling.density),
                "device": ("device", device), "domain_lo": ("domain", float(domain[0])),
                "domain_hi": ("domain", float(domain[1])), "threads": ("threads (the rule's threads)", None)}
    return {"device": ("device", device)}


def _replace(obj, section: str, keys: dict, **changes):
    """dataclasses.replace with the key of a refused value named (an experiment's, if it set it)."""
    try:
        return replace(obj, **changes)
    except (ValueError, TypeError) as exc:
        bad = _failing_key(type(obj), exc, section)
        fname = bad.split(".")[-1] if "." in bad else ""
        raise ConfigError.for_key(keys.get((section, fname), bad), exc) from exc


def load_settings(*paths: str | Path, overrides: dict | None = None) -> Settings:
    """Merge the YAML files (and ``overrides``) left to right and build the typed settings."""
    return Settings.from_mapping(load_mapping(*paths, overrides=overrides))


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


def json_schema() -> dict:
    """The config's JSON schema, generated from :class:`Settings` (documentation and editors;
    validation itself is :meth:`Settings.from_mapping`)."""
    out = schema_of(Settings)
    sections = {"mpm": (MPMConfig, _section_derived("mpm", SamplingConfig(), "auto", (0, 1))),
                "render": (RenderConfig, {"device": None}), "plasticity": (PlasticityConfig, {}),
                "surface": (SurfaceMaskConfig, {}),
                "morph": (MorphConfig, {k: None for k in ("method", "mpm", "render", "plasticity", "surface")})}
    for name, (cls, derived) in sections.items():
        out["properties"][name] = schema_of(cls, derived)
    out["properties"]["profile"]["pattern"] = "^[A-Za-z0-9][A-Za-z0-9_.-]*$"
    return {"$schema": "https://json-schema.org/draft/2020-12/schema",
            "title": "physmorph config (generated from physmorph.config.Settings; do not edit)", **out}


# --------------------------------------------------------------------------------------------
# Memory estimates (checked at DAG time; also the rules' resources.mem_mb)
# --------------------------------------------------------------------------------------------

BASE_PROCESS_MB = 600.0  # python + numpy + torch + taichi runtime, measured ~500 MB
# Per particle in the morph, besides what the solver stores per substep and per control slot
# (morph_memory): the per-frame work arrays (plasticity neighbours, renderer, mask); calibrated on
# the paper profile with its real particle count (iso, 471,282 particles, 8 x 960x540: 7.04 GB
# peak RSS; the estimate with this constant 7.1 GB).
MORPH_BYTES_PER_PARTICLE = 10000.0
# Seconds a morph's particle-frame takes on a 2-core CPU (measured 1.4-2e-4): the morph rule's
# runtime request and the stability map's wall-clock limits
SECONDS_PER_PARTICLE_FRAME = 2e-4


@dataclass(frozen=True)
class MemoryEstimate:
    stage: str
    mb: float
    detail: str


def physical_memory_mb() -> float:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**20
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        return float("inf")


def particle_estimate(shape: ShapeSettings, sampling: SamplingConfig, domain) -> int:
    """Particles of a shape normalised to ``shape.size``: a shell two cells deep at ppc_surface^3
    per cell and the interior at ppc_interior^3, for a solid of volume ~0.15 size^3 (the benchmark
    shapes are ~1170 units^3 at sizes 14-20) and the area of a sphere of that volume x 1.5."""
    dx = (domain[1] - domain[0]) / sampling.grid_res
    volume = 0.15 * shape.size ** 3
    area = 1.5 * (36 * math.pi) ** (1 / 3) * volume ** (2 / 3)
    shell = 2 * area / dx ** 2
    interior = max(volume / dx ** 3 - shell, 0.0)
    return int(shell * sampling.ppc_surface ** 3 + interior * sampling.ppc_interior ** 3)


def sampling_memory(shape, sampling: SamplingConfig, domain, stage: str) -> MemoryEstimate:
    n = particle_estimate(shape, sampling, domain)
    # candidates (3 float64 + flags) and inside tests for every particle, a float64 voxel grid
    mb = BASE_PROCESS_MB + (n * 400 + sampling.grid_res ** 3 * 16) / 2**20
    return MemoryEstimate(stage, mb, f"~{n:,} particles x 400 B + grid {sampling.grid_res}^3 x 16 B")


def target_memory(sampling: SamplingConfig, target: TargetConfig, stage: str) -> MemoryEstimate:
    rays = target.width * target.height * target.supersample ** 2
    pixels = target.cameras * target.width * target.height
    mb = BASE_PROCESS_MB + (rays * 64 + pixels * 48 + sampling.grid_res ** 3 * 16) / 2**20
    return MemoryEstimate(stage, mb, f"{target.cameras} x {target.width}x{target.height} images, "
                                     f"{rays:,} rays per view, grid {sampling.grid_res}^3")


def morph_memory(source: ShapeSettings, sampling: SamplingConfig, target: TargetConfig, mpm, domain,
                 stage: str, n_particles: int | None = None) -> MemoryEstimate:
    """A morph's peak memory; ``n_particles``: the sampled count when the particles exist (a
    scheduler's request then follows the real run), else estimated from the shape's size."""
    n = particle_estimate(source, sampling, domain) if n_particles is None else int(n_particles)
    scale = 2 if mpm.precision == "float64" else 1
    slots = mpm.substeps if mpm.control == "per_substep" else 1
    # stored per substep: what the solver keeps for its backward (physmorph.mpm.memory); per
    # control slot dFc and its gradient (72 B in float32), and Adam's two moments when Adam runs (72 B)
    moments = 72 if mpm.optimizer == "adam" else 0
    per_particle = (mpm.substeps * bytes_per_particle_substep(mpm) + slots * (72 + moments) * scale
                    + MORPH_BYTES_PER_PARTICLE)
    pixels = target.cameras * target.width * target.height
    grid = sampling.grid_res ** 3 * (64 + 16 * mpm.substeps) * scale  # and the P2G grid kept per substep
    mb = BASE_PROCESS_MB + (n * per_particle + grid + pixels * 64) / 2**20
    return MemoryEstimate(stage, mb, f"~{n:,} particles x {per_particle:,.0f} B + grid {sampling.grid_res}^3 x "
                                     f"{64 * scale} B + {target.cameras} x {target.width}x{target.height} images x 64 B")


# --------------------------------------------------------------------------------------------
# What a run's results depend on (the morph rules' params)
# --------------------------------------------------------------------------------------------

def morph_params(cfg) -> str:
    """Canonical JSON of what a morph run's results depend on (cfg: physmorph.morph_config.MorphConfig).

    Settings at their defaults are left out (see ``without_defaults``: a new option reruns
    nothing), and so are settings the run's method never reads, so changing them reruns nothing:
    plasticity and the stray pull outside ``full``, the injection gains and their calibration (and the
    settle phase, unless it judges the physics loss) for ``physics_only``,
    ``gamma`` for ``position_inject`` and ``gamma_x`` elsewhere, the surface mask when nothing uses
    it; so are the thread count and the progress switch. The run rebuilds its MorphConfig from this
    string (what is left out takes its default)."""
    d = without_defaults(cfg)
    d.pop("progress", None)
    d.get("mpm", {}).pop("threads", None)
    if cfg.method != "full":
        d.pop("plasticity", None)
        d.pop("stray_pull", None)
        d.pop("stray_pull_onset", None)
    if cfg.method == "physics_only":
        for k in ("gamma", "gamma_x", "injection_calibration"):
            d.pop(k, None)
        if cfg.settle_objective != "physics":  # the settle phase judges the images, which it never reads
            for k in ("settle", "settle_objective", "settle_backoff"):
                d.pop(k, None)
        if cfg.metric_all_particles:
            d.pop("surface", None)
    else:
        d.pop("gamma_x" if cfg.method != "position_inject" else "gamma", None)
    return json.dumps(d, sort_keys=True, separators=(",", ":"))


SCHEMA_HEADER = ("# GENERATED from physmorph.config.Settings by `python -m physmorph.config --schema`; do not edit.\n"
                 "# Documentation and editor support: the workflow validates with physmorph.config.Settings itself.\n")


def schema_text() -> str:
    return SCHEMA_HEADER + yaml.safe_dump(json_schema(), sort_keys=False, width=110)


def main(argv: list[str] | None = None) -> None:
    """The maintenance command: ``--schema [PATH]`` writes the config's JSON schema, ``--defaults
    [PATH]`` records new fields' first defaults. Without PATH they write this checkout's workflow
    files (workflow/schemas/config.schema.yaml, workflow/schemas/first_defaults.json)."""
    import argparse

    schemas = Path(__file__).resolve().parent.parent / "workflow" / "schemas"
    parser = argparse.ArgumentParser(prog="python -m physmorph.config")
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
