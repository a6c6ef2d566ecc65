"""The workflow's settings: one typed, frozen object built from the merged YAML profiles.

``load_settings(paths)`` merges the YAML files left to right (later keys override, nested mappings
merge), exactly as Snakemake merges ``--configfile`` onto the Snakefile's ``configfile``, then
``Settings.from_mapping`` turns the dict into frozen pydantic dataclasses. Every config class is
declared once (physmorph.settings.base): each field with its default, its range and its meaning,
and from those declarations come the validation (unknown keys, wrong types and values out of range
refused with the dotted key and the allowed values; numbers accepted as int, float or numeric
string, since ``--config 'mpm={smoothing: 0.5}'`` hands Snakemake a string), the JSON schema the
Snakefile validates with (``json_schema``), config/README.md (physmorph.reports.userdocs) and the check
that config/config.yaml restates the defaults. Every experiment is resolved to its full
:class:`~physmorph.settings.morph.MorphConfig` and a memory estimate per stage is checked against the
machine's memory, so a bad config fails before any job runs.

The sections ``mpm``, ``render``, ``plasticity``, ``surface``, ``morph`` and ``export`` are the
library's own config classes; the workflow's own are in physmorph.settings.sections. What rule
params carry is physmorph.settings.params; the YAML merging and the building of one section,
physmorph.settings.build; the memory model, physmorph.settings.memory_model; the schema and the
first-defaults record, physmorph.settings.schema.
"""

from __future__ import annotations

import re
import types
from dataclasses import field, replace
from pathlib import Path
from typing import Annotated, Any, Literal

import pydantic

from physmorph.base.grid import DOMAIN_HI, DOMAIN_LO
from physmorph.settings.base import Float, Int, Refused, setting, settings_dataclass, with_prefix
from physmorph.settings.build import build, fail_at, load_mapping
from physmorph.settings.errors import ConfigError
from physmorph.settings.export import ExportConfig
from physmorph.settings.memory_model import (MemoryEstimate, morph_memory, physical_memory_mb, sampling_memory,
                                             target_memory)
from physmorph.settings.morph import MorphConfig
from physmorph.settings.mpm import MPMConfig
from physmorph.settings.plasticity import PlasticityConfig
from physmorph.settings.render import RenderConfig
from physmorph.settings.sections import (EXPERIMENT_OVERRIDES, Experiment, RawMesh, SamplingConfig, ShapeSettings,
                                         Tables, TargetConfig, Tradeoff)
from physmorph.settings.surface import SurfaceMaskConfig
from physmorph.settings.study_points import tradeoff_points


# sections built after the memory check, each with the fields other keys set (section_derived)
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
            fail_at("", f"the config must be a mapping, got {cfg!r}")
        s = build(cls, {k: v for k, v in cfg.items() if k not in LIBRARY_SECTIONS})
        s._check_references()
        # Memory first: a grid too big for the machine says so before the solver's own checks.
        s.check_memory(_memory_knobs(cfg.get("mpm")))
        mpm = build(MPMConfig, cfg.get("mpm"), "mpm", derived=section_derived("mpm", s.sampling, s.device, s.domain))
        render = build(RenderConfig, cfg.get("render"), "render", derived=section_derived("render", s.sampling, s.device, s.domain))
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
                fail_at(f"shapes.{name}", "a shape name is letters and digits, starting with a letter")
            if spec.kind == "file" and spec.file is not None and spec.file not in self.raw_meshes:
                fail_at(f"shapes.{name}.file", f"'{spec.file}' is not listed in raw_meshes "
                                             f"(known: {', '.join(sorted(self.raw_meshes)) or 'none'}); "
                                             "for a mesh on disk use 'path' instead")
        for name, exp in self.experiments.items():
            if not re.fullmatch(r"[A-Za-z0-9_]+", name) or name == "index":
                fail_at(f"experiments.{name}", "an experiment name is letters, digits and _, and not 'index' (the "
                                               "viewer's own page)")
            for role in ("source", "target"):
                if getattr(exp, role) not in self.shapes:
                    fail_at(f"experiments.{name}.{role}", f"unknown shape '{getattr(exp, role)}' "
                                                        f"(known: {', '.join(sorted(self.shapes))})")
        for i, shape in enumerate(self.tables.shapes):
            if shape not in self.shapes:
                fail_at(f"tables.shapes[{i}]", f"unknown shape '{shape}' (known: {', '.join(sorted(self.shapes))})")
        for i, name in enumerate(self.tables.experiments):
            if name not in self.experiments:
                fail_at(f"tables.experiments[{i}]", f"unknown experiment '{name}'")
        if len(self.tables.noise) not in (0, 2):
            fail_at("tables.noise", f"two experiments (one morph from two particle samples) or none, got "
                                  f"{list(self.tables.noise)}")
        for i, name in enumerate(self.tables.noise):
            if name not in self.tables.experiments:
                fail_at(f"tables.noise[{i}]", f"'{name}' is not one of tables.experiments")
        for i, name in enumerate(self.export.experiments):
            if name not in self.experiments or self.experiments[name].method != "full":
                fail_at(f"export.experiments[{i}]", f"'{name}' is not an experiment of method full (those: "
                                                   f"{', '.join(n for n, e in self.experiments.items() if e.method == 'full') or 'none'})")
        if self.tradeoff is not None and self.tradeoff.experiment not in self.experiments:
            fail_at("tradeoff.experiment", f"unknown experiment '{self.tradeoff.experiment}'")

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
            fail_at(keys.get(("morph", "cameras"), "morph.cameras"),
                  f"{cfg.cameras} render-loss views, but the target has only {target.cameras} (target.cameras)")
        return cfg

    def point_config(self, point):
        """(sampling, target, MorphConfig) of a tradeoff point (physmorph.studies.tradeoff.TradeoffPoint)."""
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
            fail_at(f"tradeoff.knobs.{point.knob or 'learning_rate'}", str(exc))
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
                                    mpm, self.domain, f"morph {name}", threads=self.threads))
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
                out.append(morph_memory(src, sampling, target, point_mpm, self.domain, f"tradeoff point {pname}",
                                        threads=p.threads))
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


def section_derived(section: str, sampling: SamplingConfig, device: str, domain) -> dict:
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
