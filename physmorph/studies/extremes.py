"""The stability map of the extremes: what one morph does when one setting at a time goes to its limit.

Around a base experiment (physmorph.studies.stability_map.MAP_EXPERIMENT, iso -> bunny with the full
method, on the profile the workflow runs; docs/stability.md shows the test profile's map) each cell
changes one setting a user touches, from its default to and past its limit: the frame step
``mpm.dt`` (as a fraction of the stable step cfl dx / c, past it), Young's modulus, Poisson's
ratio, the optimiser's step (``mpm.learning_rate``), the injection gain ``morph.gamma``, the
plasticity rate ``plasticity.eta``, the experiment's ``drag``, the grid and the particles per cell.
Every cell ends in exactly one outcome (physmorph.studies.stability_map: converged, not converged, warned,
refused, stopped; never crash or hang).

An accepted cell does what the workflow's jobs do for a run (sample the particles, rasterize the
target, morph: :func:`cell_pipeline`) in its own process under a wall-clock limit
(physmorph.base.isolated_call), so a hang is detected and a crash of the interpreter is seen rather
than suffered; what the process raised comes back with its key, frame and quantity as data. Cells
with many particles run ``SHORT_CELL_FRAMES`` frames so the map stays affordable on two cores
(their table row says so).
"""

from __future__ import annotations

import copy
import json
import math
import os
import re
import shutil
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from physmorph.settings.memory_model import SECONDS_PER_PARTICLE_FRAME, particle_estimate
from physmorph.settings.workflow import Settings
from physmorph.settings.build import deep_merge
from physmorph.settings.errors import ConfigError
from physmorph.base.isolated_call import call_here, run_isolated
from physmorph.studies.stability_map import ERROR_FIELDS, KNOB_BY_NAME, MAP_EXPERIMENT, CellRun, build_map, classify

# Cells estimated above this many particles run SHORT_CELL_FRAMES frames (the first plastic frame
# of the test profile included) without the release probe.
SHORT_CELL_PARTICLES = 100_000
SHORT_CELL_FRAMES = 4
# The wall-clock limit's margin over a cell's expected time (physmorph.settings.workflow.SECONDS_PER_PARTICLE_FRAME).
TIMEOUT_MARGIN = 10.0
TIMEOUT_FLOOR_S = 300.0

# The values each knob visits besides the base profile's own (which is always a cell).
DT_CFL_FRACTIONS = (0.01, 0.1, 0.7, 0.9, 1.2)  # 0.9: above cfl_warn_fraction; 1.2: past the bound
YOUNGS_MODULI = (1e3, 1e4, 5e5, 7e5, 1e6, 1e7)
POISSON_RATIOS = (0.0, 0.3, 0.45, 0.47, 0.49, 0.499)
STEP_FACTORS = (0.1, 0.3, 3.0, 10.0)
GAMMAS = (0.0, 1.0, 3.0, 10.0)
ETAS = (0.0, 0.2, 0.5, 1.0)
DRAGS = (0.0, 0.5, 1.0)
DRAG_DT_PRODUCTS = (0.5, 2.0)  # drag x dt: 1 removes all momentum every substep, past 1 is refused
GRIDS = (16, 24, 64, 80, 128)  # at the default dt, 80 is near the stable step and 128 past it
PARTICLES_PER_CELL = (1, 2, 4, 6, 10, 14)  # per axis, surface and interior alike


@dataclass(frozen=True)
class Cell:
    """One cell of the map: the base config with ``overrides`` merged on (physmorph.settings.workflow.deep_merge)."""

    name: str  # "{knob}-{value}", a file name
    knob: str
    key: str  # the config key it sets
    label: str  # the value as the figure and the table show it
    order: float  # sorts the knob's cells (the value, or its particle estimate)
    is_default: bool
    overrides: dict = field(default_factory=dict)
    note: str = ""  # what else the cell changes (a short run), said in the table


def restricted_mapping(base: dict, experiment: str = MAP_EXPERIMENT) -> dict:
    """The merged config reduced to what one run of ``experiment`` reads: that experiment alone,
    its two shapes and their raw meshes, no tables and no speed/accuracy study, so the config's
    checks (memory included) judge this run and nothing else."""
    out = copy.deepcopy(base)
    experiments = out.get("experiments") or {}
    if experiment not in experiments:
        raise ConfigError(f"unknown experiment '{experiment}' (known: {', '.join(sorted(experiments)) or 'none'})")
    exp = experiments[experiment]
    out["experiments"] = {experiment: exp}
    shapes = out.get("shapes") or {}
    used = {s: shapes[s] for s in (exp.get("source"), exp.get("target")) if s in shapes}
    out["shapes"] = used
    files = {spec.get("file") for spec in used.values() if isinstance(spec, dict)}
    out["raw_meshes"] = {k: v for k, v in (out.get("raw_meshes") or {}).items() if k in files}
    out["tables"] = {"shapes": [], "experiments": []}
    out.pop("tradeoff", None)
    return out


def _num(v: float) -> str:
    return f"{v:.3g}"


def map_cells(base: dict, experiment: str = MAP_EXPERIMENT) -> dict[str, Cell]:
    """Every cell of the map, by name (knob by knob, each in value order), around the merged
    config ``base`` (a mapping as Snakemake's ``config``; it must itself be valid)."""
    settings = Settings.from_mapping(restricted_mapping(base, experiment))
    cfg = settings.experiment_config(experiment)
    mpm, sampling = cfg.mpm, settings.sampling
    source = settings.shape(settings.experiment(experiment).source)
    cells: list[Cell] = []

    def add(knob: str, value_text: str, label: str, order: float, is_default: bool, overrides: dict,
            note: str = "") -> None:
        key = KNOB_BY_NAME[knob].key.format(experiment=experiment)
        cells.append(Cell(f"{knob}-{value_text}", knob, key, label + (" (default)" if is_default else ""), order,
                          is_default, overrides, note))

    def sweep(knob: str, default: float, values, overrides_of, label_of=_num) -> None:
        for v in sorted({float(default), *map(float, values)}):
            add(knob, _num(v), label_of(v), v, math.isclose(v, default, rel_tol=1e-9), overrides_of(v))

    cfl = mpm.stable_dt
    default_fraction = mpm.dt / cfl
    for frac in sorted({default_fraction, *DT_CFL_FRACTIONS}):
        dt = mpm.dt if frac == default_fraction else frac * cfl
        add("dt", _num(dt), f"{frac:.2g} ({dt:.2g} s)", frac, frac == default_fraction, {"mpm": {"dt": dt}})
    sweep("youngs_modulus", mpm.youngs_modulus, YOUNGS_MODULI, lambda v: {"mpm": {"youngs_modulus": v}},
          lambda v: f"{v:.2g}")
    sweep("poisson_ratio", mpm.poisson_ratio, POISSON_RATIOS, lambda v: {"mpm": {"poisson_ratio": v}})
    for factor in sorted({1.0, *STEP_FACTORS}):
        lr = factor * mpm.learning_rate
        add("step_size", f"x{_num(factor)}", f"x{factor:g} ({lr:.2g})", factor, factor == 1.0,
            {"mpm": {"learning_rate": lr}})
    sweep("gamma", cfg.gamma, GAMMAS, lambda v: {"morph": {"gamma": v}})
    sweep("eta", cfg.plasticity.eta, ETAS, lambda v: {"plasticity": {"eta": v}})
    drags = {float(cfg.mpm.drag), *DRAGS, *(p / mpm.dt for p in DRAG_DT_PRODUCTS)}
    for d in sorted(drags):
        label = f"{d:.3g}" if d * mpm.dt < 0.1 else f"{d:.3g} (x dt = {d * mpm.dt:.2g})"
        add("drag", _num(d), label, d, math.isclose(d, cfg.mpm.drag), {"experiments": {experiment: {"drag": d}}})
    sweep("grid_res", sampling.grid_res, GRIDS, lambda v: {"sampling": {"grid_res": int(v)}}, lambda v: f"{v:.0f}")
    pairs = {(sampling.ppc_surface, sampling.ppc_interior), *((k, k) for k in PARTICLES_PER_CELL)}
    frames = cfg.frames
    for s_ppc, i_ppc in sorted(pairs, key=lambda p: (p[0] ** 3 + p[1] ** 3, p)):
        sp = replace(sampling, ppc_surface=s_ppc, ppc_interior=i_ppc)
        n = particle_estimate(source, sp, settings.domain)
        overrides = {"sampling": {"ppc_surface": s_ppc, "ppc_interior": i_ppc}}
        note = ""
        if n > SHORT_CELL_PARTICLES and frames > SHORT_CELL_FRAMES:
            overrides["experiments"] = {experiment: {"frames": SHORT_CELL_FRAMES, "release_frames": 0}}
            note = f"{SHORT_CELL_FRAMES} of {frames} frames (its particle count)"
        ppc = f"{s_ppc}" if s_ppc == i_ppc else f"{s_ppc}/{i_ppc}"
        add("particles", f"ppc{s_ppc}x{i_ppc}", f"{ppc} (~{_count(n)})", n,
            (s_ppc, i_ppc) == (sampling.ppc_surface, sampling.ppc_interior), overrides, note)
    out = {c.name: c for c in cells}
    if len(out) != len(cells):
        raise ValueError("two cells of the stability map share a name")  # pragma: no cover - a sweep typo
    return out


def _count(n: float) -> str:
    return f"{n / 1e6:.2g}M" if n >= 1e6 else f"{n / 1e3:.3g}K" if n >= 1e3 else f"{n:.0f}"


def cell_mapping(base: dict, cell: Cell, experiment: str = MAP_EXPERIMENT) -> dict:
    """The merged config of one cell: ``base`` restricted to the experiment, the cell's overrides on it."""
    return deep_merge(restricted_mapping(base, experiment), cell.overrides)


# --------------------------------------------------------------------------------------------
# Checking a cell's config (what happens before any job runs)
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class CellCheck:
    settings: Settings | None  # None when refused
    refusal: str | None  # why the config refused it (the ConfigError's reason)
    refused_key: str | None  # the key it refused (the ConfigError's key)
    warnings: tuple[str, ...]  # the config's warnings (CFLWarning), each once


def check_cell(mapping: dict) -> CellCheck:
    """Build the cell's settings as the workflow does when it parses its config: a ConfigError is
    a refusal; warnings raised on the way (the same one for every resolved experiment) are kept once."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            settings, refusal, key = Settings.from_mapping(mapping), None, None
        except ConfigError as exc:
            settings, refusal, key = None, exc.reason, exc.key
    texts = tuple(dict.fromkeys(f"{w.category.__name__}: {w.message}" for w in caught))
    return CellCheck(settings, refusal, key, texts)


# --------------------------------------------------------------------------------------------
# Running a cell (in its own process, under a wall-clock limit), and what it left
# --------------------------------------------------------------------------------------------

def cell_timeout_s(n_particles: int, frames: int) -> float:
    """A cell's wall-clock limit: TIMEOUT_MARGIN times its expected morph time, at least TIMEOUT_FLOOR_S
    (start-up and the solver's compilation take up to ~30 s on a loaded machine)."""
    return max(TIMEOUT_FLOOR_S, TIMEOUT_MARGIN * SECONDS_PER_PARTICLE_FRAME * n_particles * frames)


# Metrics that every committed frame must hold finite (frame 0 has no physics step: its losses are NaN).
FINITE_METRICS = ("alpha_mse", "iou", "gap_closed", "chamfer", "fp_det_min", "fp_det_max", "total_volume")
FINITE_AFTER_FRAME_0 = ("physics_loss", "physics_loss_initial")


def read_cell_run(run_h5: Path) -> dict:
    """status, frames_completed, run_warnings, metrics_finite and the gap closed of a finished run
    file or, when there is none, of its partial run (its committed frames)."""
    from physmorph.records.runfile import partial_dir, read_metrics

    path = run_h5 if run_h5.exists() else partial_dir(run_h5)
    if not path.exists():
        return {"status": None, "frames_completed": -1}
    m = read_metrics(path)
    n = len(m["alpha_mse"])
    finite = all(np.isfinite(np.asarray(m[k], float)).all() for k in FINITE_METRICS) and \
        all(np.isfinite(np.asarray(m[k], float)[1:]).all() for k in FINITE_AFTER_FRAME_0)
    gap = np.asarray(m["gap_closed"], float)
    return {"status": str(m["attrs"].get("status", "")), "frames_completed": int(m["attrs"].get("frames_completed", n - 1)),
            "run_warnings": tuple(json.loads(str(m["attrs"].get("warnings", "[]")))), "metrics_finite": bool(finite),
            "gap_closed_last": float(gap[-1]) if n else math.nan,
            "gap_closed_best": float(np.nanmax(gap)) if n and np.isfinite(gap).any() else math.nan,
            "n_particles": int(m["attrs"]["n_particles"]) if "n_particles" in m["attrs"] else None,
            "peak_rss_mb": float(m["attrs"].get("peak_rss_mb", math.nan))}


def cell_pipeline(source_mesh: str, target_mesh: str, sampling: str, target: str, render: str, seed: int,
                  settings: str, name: str, experiment: str, work_dir: str, threads: int = 1) -> None:
    """What the workflow does for a run once its config is accepted, at the cell's resolution:
    sample the source's particles, rasterize the target, morph (the stages of physmorph.stages, as
    the jobs call them). Its files go to ``work_dir``: particles.h5, target.h5, run.h5."""
    from physmorph.stages import morph_stage, rasterize_target_stage, sample_particles_stage

    d = Path(work_dir)
    sample_particles_stage(source_mesh, str(d / "particles.h5"), str(d / "particles.png"), sampling, seed)
    rasterize_target_stage(target_mesh, str(d / "target.h5"), str(d / "target.png"), sampling, target, seed,
                           render=render, threads=threads)
    morph_stage(settings, name, str(d / "particles.h5"), str(d / "target.h5"), str(d / "run.h5"), threads=threads,
                experiment=experiment)


def run_cell(cell: Cell, mapping: dict, source_mesh: str | Path | None, target_mesh: str | Path | None,
             work_dir: str | Path, experiment: str = MAP_EXPERIMENT, threads: int = 1,
             timeout_s: float | None = None, isolate: bool = True, log: str | Path | None = None) -> dict:
    """Check the cell's config; if accepted, sample, rasterize and morph it (:func:`cell_pipeline`,
    in its own process under ``timeout_s`` with ``isolate``); classify. Returns the cell's record
    (a row of the map). ``mapping``: the cell's merged config (:func:`cell_mapping`);
    ``source_mesh``/``target_mesh``: the prepared meshes (physmorph.meshes); ``work_dir``: the
    cell's files, emptied first so every cell starts from its config."""
    from physmorph.settings.params import canonical_json, morph_params, params_json
    from physmorph.meshes.particles import stored_particle_count

    work = Path(work_dir)
    check = check_cell(mapping)
    record = {"cell": cell.name, "knob": cell.knob, "key": cell.key, "value": cell.label, "order": cell.order,
              "is_default": cell.is_default, "note": cell.note, "n_particles": None, "frames_planned": None,
              "wall_s": 0.0, "peak_rss_mb": math.nan, "traceback": None}
    if check.settings is None:
        run = CellRun(refusal=check.refusal, refused_key=check.refused_key, config_warnings=check.warnings)
    else:
        s = check.settings
        cfg = s.experiment_config(experiment)
        record["frames_planned"] = cfg.frames
        if work.exists():
            shutil.rmtree(work)
        work.mkdir(parents=True)
        kwargs = {"source_mesh": str(source_mesh), "target_mesh": str(target_mesh),
                  "sampling": canonical_json(s.sampling), "target": canonical_json(s.target),
                  "render": canonical_json(s.render), "seed": s.seed, "settings": morph_params(cfg),
                  "name": cell.name, "experiment": params_json(s.experiment(experiment)), "work_dir": str(work),
                  "threads": int(threads)}
        estimate = particle_estimate(s.shape(s.experiment(experiment).source), s.sampling, s.domain)
        # two frames' worth for sampling and rasterizing
        limit = timeout_s if timeout_s is not None else cell_timeout_s(estimate, cfg.frames + cfg.release_frames + 2)
        if isolate:
            child = run_isolated("physmorph.studies.extremes:cell_pipeline", kwargs, limit, log, error_fields=ERROR_FIELDS)
        else:  # in this process (fast tests): no wall-clock limit, an exception is caught here
            child = call_here("physmorph.studies.extremes:cell_pipeline", kwargs, error_fields=ERROR_FIELDS)
        found = read_cell_run(work / "run.h5")
        record.update(wall_s=child.wall_s, peak_rss_mb=found.pop("peak_rss_mb", math.nan), traceback=child.traceback)
        record["n_particles"] = found.pop("n_particles", None) or stored_particle_count(work / "particles.h5")
        if cell.knob == "particles" and record["n_particles"]:  # the sampled count, not the estimate
            record["value"] = re.sub(r"\(~[^)]*\)", f"({_count(record['n_particles'])})", cell.label)
        run = CellRun(config_warnings=check.warnings, timed_out=child.timed_out, returncode=child.returncode,
                      error_type=child.error_type, error_message=child.error_message, error_data=child.error_data,
                      frames_planned=cfg.frames, **found)
    outcome = classify(run)
    record.update(outcome=outcome.outcome, detail=outcome.detail, refused_key=outcome.key,
                  stop_frame=outcome.frame, stop_quantity=outcome.quantity,
                  warnings=list(run.config_warnings + run.run_warnings),
                  frames_completed=run.frames_completed if run.refusal is None else None,
                  gap_closed_last=run.gap_closed_last, gap_closed_best=run.gap_closed_best)
    return record


# --------------------------------------------------------------------------------------------
# Workflow entry points (workflow/scripts/stability_cell.py, make_stability_map.py)
# --------------------------------------------------------------------------------------------

def cell_stage(cell, mapping, source_mesh: str | None, target_mesh: str | None, output: str, work_dir: str,
               threads: int = 1, log: str | None = None) -> dict:
    """One cell of the map (a rule's job): ``cell`` a Cell or its JSON, ``mapping`` the cell's
    merged config or its JSON; writes the cell's record to ``output`` (JSON)."""
    from physmorph.stages import stage_log

    cell = Cell(**json.loads(cell)) if isinstance(cell, str) else cell
    mapping = json.loads(mapping) if isinstance(mapping, str) else mapping
    with stage_log(log):
        record = run_cell(cell, mapping, source_mesh or None, target_mesh or None, work_dir, threads=threads, log=log)
        print(f"[{cell.name}] {record['outcome']}: {record['detail']}", flush=True)
    out = Path(output)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(json.dumps(record, indent=1, sort_keys=True, default=str))
    os.replace(tmp, out)
    return record


def map_stage(cells: list[str], out_dir: str, title: str = "", log: str | None = None):
    """The map's table and figure from the cells' records (JSON files)."""
    from physmorph.stages import stage_log

    with stage_log(log):
        return build_map([json.loads(Path(p).read_text()) for p in cells], out_dir, title)

