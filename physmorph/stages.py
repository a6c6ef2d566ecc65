"""Stage entry points: what the workflow scripts call, one function per rule.

Settings arrive as the typed dataclasses of :mod:`physmorph.settings.workflow` or as their canonical JSON
(the rules' ``params``, which is what makes Snakemake rerun a job when they change); never as
the raw config dict. ``log``: a file that gets the stage's progress and warnings (the morph
also echoes them to the terminal). Every stage can be run and tested from plain Python.
"""

from __future__ import annotations

import json
import os
import sys
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

from physmorph.settings.sections import RawMesh, SamplingConfig, ShapeSettings, TargetConfig
from physmorph.settings.build import build
from physmorph.settings.params import canonical_json, morph_params
from physmorph.base.grid import DOMAIN_HI, DOMAIN_LO


def typed(cls, value, where: str):
    """``value`` (an instance, its JSON string or a mapping) as ``cls``."""
    if isinstance(value, cls):
        return value
    if isinstance(value, str):
        value = json.loads(value)
    return build(cls, value, where)


class _Tee:
    def __init__(self, *streams):
        self.streams = streams

    def write(self, text):
        for s in self.streams:
            s.write(text)
            s.flush()
        return len(text)

    def flush(self):
        for s in self.streams:
            s.flush()


@contextmanager
def stage_log(log: str | Path | None, echo: bool = False):
    """Send stdout/stderr (progress, warnings) to ``log`` (and the terminal when ``echo``)."""
    if log is None:
        yield
        return
    Path(log).parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as f:
        old = sys.stdout, sys.stderr
        sys.stdout = _Tee(f, old[0]) if echo else _Tee(f)
        sys.stderr = _Tee(f, old[1]) if echo else _Tee(f)
        try:
            yield
        finally:
            sys.stdout, sys.stderr = old


def set_threads(threads: int | None) -> None:
    """The job's threads for torch and for Taichi (physmorph.base.taichi_runtime reads
    PHYSMORPH_THREADS when it initialises without an explicit count, e.g. for the renderer)."""
    if threads:
        import torch

        torch.set_num_threads(int(threads))
        os.environ["PHYSMORPH_THREADS"] = str(int(threads))


def fetch_mesh_stage(output: str, source, mesh_dir: str | None = None, log=None) -> Path:
    from physmorph.meshes.fetch import fetch_mesh

    src = typed(RawMesh, source, "raw_meshes")
    out = Path(output)
    with stage_log(log):
        return fetch_mesh(out.name, src.url, src.sha256, out.parent, mesh_dir=mesh_dir)


def shape_spec(name: str, entry):
    """The library's ShapeSpec of a ``shapes:`` entry (ShapeSettings, its JSON or a mapping)."""
    from physmorph.meshes.shapes import ShapeSpec

    e = typed(ShapeSettings, entry, f"shapes.{name}")
    file = e.file if e.file is not None else (Path(e.path).name if e.path else None)
    return ShapeSpec(name=name, kind=e.kind, file=file, glyph=e.glyph, size=e.size, depth=e.depth)


def prepare_mesh_stage(shape: str, entry, raw: str | None, output: str,
                       domain: tuple[float, float] = (DOMAIN_LO, DOMAIN_HI), log=None,
                       raw_sha256: str | None = None) -> dict:
    """``raw_sha256``: the raw mesh's checksum from the config (verified again before preparation)."""
    from physmorph.meshes.prepare import prepare_mesh

    with stage_log(log):
        return prepare_mesh(shape_spec(shape, entry), Path(raw) if raw else None, Path(output),
                            domain=tuple(domain), raw_sha256=raw_sha256)


def sample_particles_stage(mesh_h5: str, output: str, preview: str, sampling, seed: int, log=None) -> dict:
    from physmorph.meshes.particles import sample_particles

    s = typed(SamplingConfig, sampling, "sampling")
    with stage_log(log):
        return sample_particles(Path(mesh_h5), Path(output), s.grid_res, s.ppc_surface, s.ppc_interior, s.density,
                                s.sigma_scale, seed, preview_png=Path(preview))


def rasterize_target_stage(mesh_h5: str, output: str, preview: str, sampling, target, seed: int,
                           render=None, log=None, threads: int | None = None) -> dict:
    """``render``: the renderer of the ceiling (the target's own particles rendered at rest),
    always on the CPU."""
    from physmorph.settings.render import RenderConfig
    from physmorph.morph.targets import rasterize_target

    s = typed(SamplingConfig, sampling, "sampling")
    t = typed(TargetConfig, target, "target")
    rcfg = replace(typed(RenderConfig, render or {}, "render"), device="cpu")
    set_threads(threads)
    with stage_log(log):
        return rasterize_target(mesh_h5, output, s, t, seed, preview_png=preview,
                                config={"sampling": json.loads(canonical_json(s)), "target": json.loads(canonical_json(t)),
                                        "render": json.loads(canonical_json(rcfg))},
                                render=rcfg)


def prepare_experiment_inputs(settings, experiment: str, mesh_dir: str | Path, path_of) -> None:
    """The prepared meshes, the source's particles and the target of ``experiment`` (settings: a
    Settings), each made by its stage with the workflow's settings (domain, seeds, the ceiling's
    render) where the file ``path_of(kind, shape)`` does not exist yet; kind is "mesh", "particles"
    or "target", so a benchmark lays them out as it likes. Raw meshes: a shape's own path, else its
    file in ``mesh_dir``."""
    exp = settings.experiment(experiment)
    render = replace(settings.render, device="cpu")
    for kind, shape in (("particles", exp.source), ("target", exp.target)):
        spec = settings.shape(shape)
        mesh = Path(path_of("mesh", shape))
        if not mesh.exists():
            mesh.parent.mkdir(parents=True, exist_ok=True)
            raw = (Path(spec.path) if spec.path else Path(mesh_dir) / spec.file) if spec.kind == "file" else None
            prepare_mesh_stage(shape, spec, raw, mesh, domain=tuple(settings.domain))
        out = Path(path_of(kind, shape))
        if out.exists():
            continue
        out.parent.mkdir(parents=True, exist_ok=True)
        if kind == "particles":
            sample_particles_stage(mesh, out, out.with_suffix(".png"), settings.sampling, settings.particle_seed(shape))
        else:
            rasterize_target_stage(mesh, out, out.with_suffix(".png"), settings.sampling, settings.target, settings.seed,
                                   render=render)


def morph_stage(settings, name: str, particles_h5: str, target_h5: str, output: str, threads: int | None = None,
                log=None, experiment: dict | None = None, target_size: float | None = None) -> dict:
    """One morph run. ``settings``: its MorphConfig or that config's params JSON
    (physmorph.settings.workflow.morph_params); ``experiment``: what the run file records about it;
    ``target_size``: the target shape's configured size (named by a volume warning)."""
    from physmorph.settings.morph import MorphConfig
    from physmorph.morph.loop import run_morph

    mcfg = typed(MorphConfig, settings, "morph")
    experiment = json.loads(experiment) if isinstance(experiment, str) else experiment
    record = {"experiment": experiment or {}, "morph": json.loads(morph_params(mcfg))}
    if threads:
        mcfg = replace(mcfg, mpm=replace(mcfg.mpm, threads=int(threads)))
    set_threads(threads)
    with stage_log(log, echo=True):
        return run_morph(particles_h5, target_h5, output, mcfg, name=name, config_record=record,
                         target_size=target_size)


def prepare_mesh_job(shape: str, entry, raw: str | None, output: str,
                     domain: tuple[float, float] = (DOMAIN_LO, DOMAIN_HI), log: str | os.PathLike | None = None,
                     raw_sha256: str | None = None) -> dict:
    """The prepare_mesh rule's entry (workflow/scripts/prepare_mesh.py): prepare_mesh_stage, except
    that a refused mesh (a MeshError) ends the job's ``log`` in one line naming the file and the
    reason, and the job with exit status 2, instead of a traceback."""
    from physmorph.meshes.errors import exit_on_refusal

    return exit_on_refusal(lambda: prepare_mesh_stage(shape, entry, raw, output, domain=domain, log=log,
                                                      raw_sha256=raw_sha256), log=log, path=raw)
