"""The workflow's settings: one typed, frozen object built from the merged YAML profiles.

``load_settings(paths)`` merges the YAML files left to right (later keys override, nested mappings
merge), exactly as Snakemake merges ``--configfile`` onto the Snakefile's ``configfile``, then
``Settings.from_mapping`` turns the dict into frozen pydantic dataclasses. Every config class is
declared once (physmorph.settings_base): each field with its default, its range and its meaning,
and from those declarations come the validation (unknown keys, wrong types and values out of range
refused with the dotted key and the allowed values; numbers accepted as int, float or numeric
string, since ``--config 'mpm={smoothing: 0.5}'`` hands Snakemake a string), the JSON schema the
Snakefile validates with (``json_schema``), config/README.md (physmorph.userdocs) and the check
that config/config.yaml restates the defaults. Every experiment is resolved to its full
:class:`~physmorph.settings.morph.MorphConfig` and a memory estimate per stage is checked against the
machine's memory, so a bad config fails before any job runs.

The sections ``mpm``, ``render``, ``plasticity``, ``surface``, ``morph`` and ``export`` are the
library's own config classes; the workflow's own are in physmorph.config_sections. What rule
params carry is physmorph.config_params.
"""

from __future__ import annotations

import copy
import json
import math
import os
import re
import types
from dataclasses import MISSING, dataclass, field, fields, is_dataclass, replace
from pathlib import Path
from typing import Annotated, Any, Literal, get_args, get_type_hints

import pydantic
import yaml

from physmorph.config_error import ConfigError
# the params and the workflow's sections are imported from here by the rules, stages and tests too
from physmorph.config_params import canonical_json, morph_params, params_json, to_plain, without_defaults  # noqa: F401
from physmorph.config_sections import (EXPERIMENT_OVERRIDES, RES_PATTERN, Experiment, RawMesh,  # noqa: F401
                                       SamplingConfig, ShapeSettings, Tables, TargetConfig, Tradeoff)
from physmorph.settings.export import ExportConfig
from physmorph.grid import DOMAIN_HI, DOMAIN_LO
from physmorph.settings.morph import MorphConfig
from physmorph.settings.mpm import MPMConfig
from physmorph.settings.solver_memory import bytes_per_particle_substep
from physmorph.settings.plasticity import PlasticityConfig
from physmorph.settings.render import RenderConfig
from physmorph.settings.retired import RETIRED_METHOD_SETTINGS
from physmorph.settings_base import (Float, Int, Refused, field_default, json_schema_of, setting,
                                     settings_dataclass, validate_plain_dataclass, with_prefix)
from physmorph.settings.surface import SurfaceMaskConfig
from physmorph.tradeoff_points import TradeoffPoint, tradeoff_points

def deep_merge(base: dict, override: dict) -> dict:
    out = copy.deepcopy(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def _fail(key: str, msg: str):
    raise ConfigError.for_key(key or "<root>", msg)


def build(cls, data: Any, where: str = "", derived: dict[str, tuple[str, Any]] | None = None):
    """``cls`` from the mapping ``data`` (validated by its declaration); errors name ``where.key``.
    ``cls`` is a config class (physmorph.settings_base) or a plain dataclass (validated by pydantic too).

    derived: fields not settable here, name -> (where it is set, value)."""
    derived = derived or {}
    if data is None:
        data = {}
    if not isinstance(data, dict):
        _fail(where, f"expected a mapping, got {data!r}")
    settable = sorted(f.name for f in fields(cls) if f.init and f.name not in derived)
    for k in data:
        if k in derived:
            _fail(with_prefix(where, str(k)), f"not settable here: it is set by {derived[k][0]}")
        if k not in settable:  # before the values: a misspelt key is the likelier mistake
            _fail(with_prefix(where, str(k)), _unknown_key_reason(with_prefix(where, str(k)), settable))
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
            problems.append(f"{key}: not recorded in {path.name}; run `python -m physmorph.config --defaults`")
            continue
        cls_name, name = key.split(".", 1)
        if recorded[key] != default and name not in getattr(classes[cls_name], "ALWAYS_IN_PARAMS", ()):
            problems.append(f"{key}: default changed {recorded[key]!r} -> {default!r}, so runs made with the old "
                            f"default (which left it out of their params) would not rerun; add '{name}' to "
                            f"{cls_name}.ALWAYS_IN_PARAMS")
    return problems


# --------------------------------------------------------------------------------------------
# The settings (the library's sections are their own classes; the workflow's, physmorph.config_sections)
# --------------------------------------------------------------------------------------------

# sections built after the memory check, each with the fields other keys set (_section_derived)
LIBRARY_SECTIONS = ("mpm", "render", "plasticity", "surface", "morph")
PROFILE_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]*$"


@settings_dataclass
class Settings:
    """Everything the workflow needs, typed and frozen. Build with :meth:`from_mapping`."""

    profile: Annotated[str, setting("name of the results tree: outputs go to results/{profile}/", "",
                                    "a plain name (letters, digits, _ . -): it names results/{profile}/",
                                    pattern=PROFILE_PATTERN)] = "default"
    device: Annotated[Literal["auto", "cpu", "cuda"], setting(
        "where Taichi and torch run; auto picks CUDA when present")] = "auto"
    threads: Annotated[Int, setting("threads per job (Taichi and torch); changing it reruns nothing", ge=1)] = 2
    mesh_dir: Annotated[str | None, setting(
        "a local folder holding the raw meshes (read instead of downloading); null downloads into "
        "resources/meshes/", "path")] = None
    seed: Annotated[Int, setting("random seed of the particle sampling and the target surface points", ge=0)] = 0
    domain: Annotated[tuple[Float, Float], setting("the simulation cube [lo, hi]^3", "domain units",
                                                   "lo < hi")] = (DOMAIN_LO, DOMAIN_HI)
    max_memory_mb: Annotated[Int | None, setting(
        "refuse a config whose estimated stage memory exceeds this; null: this machine's memory", "MB",
        ge=1)] = None
    morph_gpus: Annotated[Int, setting("GPUs a morph job asks a cluster scheduler for (resources.gpu)", ge=0)] = 0
    raw_meshes: Annotated[dict[str, RawMesh], setting("raw mesh files by file name")] = field(default_factory=dict)
    shapes: Annotated[dict[str, ShapeSettings], setting("the shapes, by name")] = field(default_factory=dict)
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    target: TargetConfig = field(default_factory=TargetConfig)
    mpm: MPMConfig = field(default_factory=MPMConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    plasticity: PlasticityConfig = field(default_factory=PlasticityConfig)
    surface: SurfaceMaskConfig = field(default_factory=SurfaceMaskConfig)
    # its mpm, render, plasticity and surface are the sections above; None until from_mapping builds it
    morph: MorphConfig | None = None
    experiments: Annotated[dict[str, Experiment], setting(
        "the experiments, by name (run one: results/{profile}/runs/{name}.h5)")] = field(default_factory=dict)
    tradeoff: Tradeoff | None = None
    tables: Tables = field(default_factory=Tables)
    export: ExportConfig = field(default_factory=ExportConfig)

    def __post_init__(self) -> None:
        """The domain's two ends in order."""
        if not self.domain[1] > self.domain[0]:
            raise Refused("domain", f"needs [lo, hi] with hi > lo, got {list(self.domain)}")

    # ---- construction -------------------------------------------------------------------
    @classmethod
    def from_mapping(cls, cfg: dict) -> "Settings":
        """Typed settings from the merged config dict; raises ConfigError naming the key."""
        if not isinstance(cfg, dict):
            _fail("", f"the config must be a mapping, got {cfg!r}")
        s = build(cls, {k: v for k, v in cfg.items() if k not in LIBRARY_SECTIONS})
        s._check_references()
        # Memory first: a grid too big for the machine says so before the solver's own checks.
        s.check_memory(_memory_knobs(cfg.get("mpm")))
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
        if len(self.tables.noise) not in (0, 2):
            _fail("tables.noise", f"two experiments (one morph from two particle samples) or none, got "
                                  f"{list(self.tables.noise)}")
        for i, name in enumerate(self.tables.noise):
            if name not in self.tables.experiments:
                _fail(f"tables.noise[{i}]", f"'{name}' is not one of tables.experiments")
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

    def particle_seed(self, name: str) -> int:
        """The seed shape ``name``'s particles are sampled with: its own, else the top-level seed."""
        own = self.shape(name).seed
        return self.seed if own is None else own

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
                point_mpm = types.SimpleNamespace(substeps=mpm.substeps, precision=p.precision, optimizer=mpm.optimizer)
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


def _unknown_key_reason(key: str, settable: list[str]) -> str:
    """Why ``key`` is refused: a setting the code no longer has (physmorph.settings.retired) is
    named as such, with the value the method always ran with; any other, with the keys allowed."""
    method_key = key.removeprefix("morph.")
    if method_key in RETIRED_METHOD_SETTINGS:
        return (f"no longer a setting: the method runs as it did with {RETIRED_METHOD_SETTINGS[method_key]!r} "
                "(docs/study/log.md holds what the other values did)")
    return f"unknown key (allowed: {', '.join(settable)})"


def _memory_knobs(raw_mpm: Any) -> types.SimpleNamespace:
    """The mpm keys the memory estimate reads (substeps, precision, optimizer), validated
    on their own: the estimate runs before the whole mpm section is built."""
    raw_mpm = raw_mpm if isinstance(raw_mpm, dict) else {}
    knobs = {}
    for name in ("substeps", "precision", "optimizer"):
        if name not in raw_mpm:
            knobs[name] = getattr(MPMConfig, name)
            continue
        info = MPMConfig.__pydantic_fields__[name]
        declared = Annotated[(info.annotation, *info.metadata)] if info.metadata else info.annotation
        try:
            knobs[name] = pydantic.TypeAdapter(declared).validate_python(raw_mpm[name])
        except pydantic.ValidationError:
            build(MPMConfig, {name: raw_mpm[name]}, "mpm")  # refuses it as the whole section would, naming the key
            raise
    return types.SimpleNamespace(**knobs)


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
    except ValueError as exc:
        if not hasattr(exc, "reason"):
            raise
        raise ConfigError.for_key(keys.get((section, exc.key), with_prefix(section, exc.key or "")), exc.reason) from None


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
    """The config's JSON schema, generated from the declarations of :class:`Settings` and its
    sections; the Snakefile validates the merged config with it before Settings builds it. It accepts
    what the settings accept (numbers and booleans as strings too) and leaves out the fields other
    keys set (mpm.grid_res: sampling.grid_res, ...)."""
    out = json_schema_of(Settings)
    props = out["properties"]
    props["morph"] = json_schema_of(MorphConfig)
    derived = {"mpm": _section_derived("mpm", SamplingConfig(), "auto", (0, 1)), "render": {"device": None},
               "morph": dict.fromkeys(("method", "mpm", "render", "plasticity", "surface"))}
    for name, names in derived.items():
        for k in names:
            props[name]["properties"].pop(k)
        props[name]["required"] = [k for k in props[name].get("required", []) if k not in names]
        if not props[name]["required"]:
            del props[name]["required"]
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
    slots = mpm.substeps  # one control slot per substep
    # stored per substep: what the solver keeps for its backward (physmorph.settings.solver_memory); per
    # control slot dFc and its gradient (72 B in float32), and Adam's two moments when Adam runs (72 B)
    moments = 72 if mpm.optimizer == "adam" else 0
    per_particle = (mpm.substeps * bytes_per_particle_substep(mpm) + slots * (72 + moments) * scale
                    + MORPH_BYTES_PER_PARTICLE)
    pixels = target.cameras * target.width * target.height
    grid = sampling.grid_res ** 3 * (64 + 16 * mpm.substeps) * scale  # and the P2G grid kept per substep
    mb = BASE_PROCESS_MB + (n * per_particle + grid + pixels * 64) / 2**20
    return MemoryEstimate(stage, mb, f"~{n:,} particles x {per_particle:,.0f} B + grid {sampling.grid_res}^3 x "
                                     f"{64 * scale} B + {target.cameras} x {target.width}x{target.height} images x 64 B")


SCHEMA_HEADER = ("# GENERATED from physmorph.config.Settings by `python -m physmorph.config --schema`; do not edit.\n"
                 "# The Snakefile validates the merged config with it; physmorph.config.Settings then builds the settings.\n")


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
