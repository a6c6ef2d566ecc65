"""Stage entry points with plain arguments (config dicts, paths): what the workflow scripts call.

Each function turns the validated config subset into typed dataclasses and calls the library
stage, so every stage can be run and tested from plain Python, without Snakemake.
"""

from __future__ import annotations

from pathlib import Path

from physmorph.config import SamplingConfig, TargetConfig


def fetch_mesh_stage(output: str, source: dict, mesh_dir: str | None = None) -> Path:
    from physmorph.meshes import fetch_mesh

    out = Path(output)
    return fetch_mesh(out.name, source["url"], source["sha256"], out.parent, mesh_dir=mesh_dir)


def shape_spec(name: str, entry: dict):
    from physmorph.meshes import ShapeSpec

    return ShapeSpec(name=name, **entry)


def prepare_mesh_stage(shape: str, entry: dict, raw: str | None, output: str, raw_sha256: str | None = None) -> dict:
    """``raw_sha256``: the raw mesh's checksum from the config (verified again before preparation)."""
    from physmorph.meshes import prepare_mesh

    return prepare_mesh(shape_spec(shape, entry), Path(raw) if raw else None, Path(output), raw_sha256=raw_sha256)


def sample_particles_stage(mesh_h5: str, output: str, preview: str, sampling: SamplingConfig, seed: int) -> dict:
    from physmorph.particles import sample_particles

    return sample_particles(Path(mesh_h5), Path(output), sampling.grid_res, sampling.ppc_surface,
                            sampling.ppc_interior, sampling.density, sampling.sigma_scale, seed,
                            preview_png=Path(preview))


def rasterize_target_stage(mesh_h5: str, output: str, preview: str, sampling: SamplingConfig,
                           target: dict, seed: int, render: dict | None = None) -> dict:
    """``render``: the config's ``render:`` section (physmorph.render.RenderConfig fields), used for
    the ceiling (the target's own particles rendered at rest); always rendered on the CPU."""
    from physmorph.render import RenderConfig
    from physmorph.targets import rasterize_target

    render = dict(render or {})
    rcfg = RenderConfig(**{**render, "device": "cpu"})
    return rasterize_target(mesh_h5, output, sampling, TargetConfig(**target), seed, preview_png=preview,
                            config={"sampling": sampling.__dict__, "target": target, "render": render},
                            render=rcfg)


def morph_stage(config: dict, name: str, particles_h5: str, target_h5: str, output: str) -> dict:
    from physmorph.config import experiment, validate_config
    from physmorph.morph import morph_config, run_morph

    cfg = validate_config(config)
    mcfg = morph_config(cfg, name)
    record = {"experiment": experiment(cfg, name), "morph": mcfg.to_dict()}
    return run_morph(particles_h5, target_h5, output, mcfg, name=name, config_record=record)


def tables_stage(names: list[str], runs: list[str], out_dir: str) -> dict:
    from physmorph.tables import build_tables

    return build_tables(dict(zip(names, runs)), out_dir)


def figures_stage(names: list[str], runs: list[str], shapes: list[str], targets: list[str], target_cfg: dict,
                  out_dir: str) -> list:
    from physmorph.figures import build_figures

    return build_figures({n: Path(p) for n, p in zip(names, runs)}, {s: Path(p) for s, p in zip(shapes, targets)},
                         target_cfg, Path(out_dir))


def tradeoff_point_stage(config: dict, point: str, particles_h5: str, target_h5: str, output: str) -> dict:
    from physmorph.config import validate_config
    from physmorph.morph import morph_config, run_morph
    from physmorph.tradeoff import point_config, tradeoff_points

    cfg = validate_config(config)
    pcfg = point_config(cfg, tradeoff_points(cfg)[point])
    mcfg = morph_config(pcfg, cfg["tradeoff"]["experiment"])
    record = {"tradeoff_point": point, "morph": mcfg.to_dict()}
    return run_morph(particles_h5, target_h5, output, mcfg, name=f"tradeoff {point}", config_record=record)


def tradeoff_stage(config: dict, names: list[str], runs: list[str], out_dir: str):
    from physmorph.config import validate_config
    from physmorph.tradeoff import build_tradeoff, tradeoff_points

    points = tradeoff_points(validate_config(config))
    return build_tradeoff(points, {n: Path(p) for n, p in zip(names, runs)}, Path(out_dir))
