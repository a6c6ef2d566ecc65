"""The stability map of the extremes: what one morph does when one setting at a time goes to its limit.

Around a base experiment (``MAP_EXPERIMENT``, iso -> bunny with the full method, on the profile the
workflow runs; docs/stability.md shows the test profile's map) each cell changes one setting a user
touches, from its default to and past its limit: the frame step ``mpm.dt`` (as a fraction of the
stable step cfl dx / c, past it), Young's modulus, Poisson's ratio, the optimiser's step
(``mpm.learning_rate``), the injection gain ``morph.gamma``, the plasticity rate
``plasticity.eta``, the experiment's ``drag``, the grid and the particles per cell. Every cell ends
in exactly one outcome:

converged      every frame ran, every metric is finite, and the last frame closed at least
               ``CONVERGED_GAP`` of the reachable gap (physmorph.quality)
not converged  every frame ran and every metric is finite, but the last frame closed less: a run
               that does not get there, said so (not a failure of the code)
warned         every frame ran and every metric is finite, with a warning: the config's CFLWarning
               or the run's stability monitor (physmorph.stability); its text is kept
refused        the config check refused it before any job ran (physmorph.config.ConfigError),
               naming the key; or, for what the config cannot know, the sampling refused it naming
               the key (a grid whose particle region cannot hold a prepared mesh: STAGE_REFUSALS)
stopped        the run stopped at a frame, naming the quantity (MorphDivergenceError), and its
               partial run keeps every earlier frame
crash          anything else: an exception of another type, a killed process, a refusal or a stop
               that names no key or frame, lost frames, or a run that reports success with a
               non-finite metric (a silent NaN)
hang           the cell ran past its wall-clock limit

The last two must never appear (tests/test_extremes.py, docs/stability.md). An accepted cell does
what the workflow's jobs do for a run (sample the particles, rasterize the target, morph:
:func:`cell_pipeline`) in its own process (:func:`run_isolated`) under a wall-clock limit, so a
hang is detected and a crash of the interpreter is seen rather than suffered. Cells with many particles run
``SHORT_CELL_FRAMES`` frames so the map stays affordable on two cores (their table row says so).
"""

from __future__ import annotations

import copy
import importlib
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import traceback
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from physmorph.config import SECONDS_PER_PARTICLE_FRAME, ConfigError, Settings, deep_merge, particle_estimate

MAP_EXPERIMENT = "iso_bunny_full"
# A run that ends with at least this share of its reachable gap closed converged (the base cell
# closes 50-59 % at the test profile's 12 frames).
CONVERGED_GAP = 0.25
# Cells estimated above this many particles run SHORT_CELL_FRAMES frames (the first plastic frame
# of the test profile included) without the release probe.
SHORT_CELL_PARTICLES = 100_000
SHORT_CELL_FRAMES = 4
# The wall-clock limit's margin over a cell's expected time (physmorph.config.SECONDS_PER_PARTICLE_FRAME).
TIMEOUT_MARGIN = 10.0
TIMEOUT_FLOOR_S = 300.0

OUTCOMES = ("converged", "not converged", "warned", "refused", "stopped", "crash", "hang")
FAILURES = ("crash", "hang")  # outcomes the map must never hold


@dataclass(frozen=True)
class Knob:
    name: str
    key: str  # the config key it sets ({experiment}: the base experiment's name)
    title: str  # a row label of the figure


KNOBS = (
    Knob("dt", "mpm.dt", "dt (x stable step)"),
    Knob("youngs_modulus", "mpm.youngs_modulus", "Young's modulus E (Pa)"),
    Knob("poisson_ratio", "mpm.poisson_ratio", "Poisson ratio nu"),
    Knob("step_size", "mpm.learning_rate", "step size (x default)"),
    Knob("gamma", "morph.gamma", "injection gain gamma"),
    Knob("eta", "plasticity.eta", "plasticity rate eta"),
    Knob("drag", "experiments.{experiment}.drag", "drag (1/s)"),
    Knob("grid_res", "sampling.grid_res", "grid (cells per axis)"),
    Knob("particles", "sampling.ppc_surface, sampling.ppc_interior", "particles per cell per axis"),
)
KNOB_BY_NAME = {k.name: k for k in KNOBS}

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
    """One cell of the map: the base config with ``overrides`` merged on (physmorph.config.deep_merge)."""

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
    exp_key = f"experiments.{experiment}"
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
    refusal: str | None  # the ConfigError's text
    warnings: tuple[str, ...]  # the config's warnings (CFLWarning), each once


def check_cell(mapping: dict) -> CellCheck:
    """Build the cell's settings as the workflow does when it parses its config: a ConfigError is
    a refusal; warnings raised on the way (the same one for every resolved experiment) are kept once."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            settings, refusal = Settings.from_mapping(mapping), None
        except ConfigError as exc:
            settings, refusal = None, str(exc)
    texts = tuple(dict.fromkeys(f"{w.category.__name__}: {w.message}" for w in caught))
    return CellCheck(settings, refusal, texts)


def refused_key(message: str) -> str | None:
    """The config key a ConfigError names (its ``config key '...'``, or max_memory_mb for the
    memory check), None when it names none."""
    m = re.search(r"config key '([^']+)'", message)
    if m:
        return m[1]
    m = re.search(r"\((max_memory_mb)\b", message)
    return m[1] if m else None


# --------------------------------------------------------------------------------------------
# Running a cell in its own process, under a wall-clock limit
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ChildResult:
    returncode: int | None
    timed_out: bool
    error_type: str | None  # the class of the exception the call raised, None when it returned
    error_message: str | None
    traceback: str | None
    wall_s: float


def run_isolated(target: str, kwargs: dict, timeout_s: float, log: str | Path | None = None) -> ChildResult:
    """Call ``module:function(**kwargs)`` (kwargs JSON-ready) in a fresh Python process with its
    output appended to ``log``; kill it (its whole process group) after ``timeout_s`` seconds.
    The child reports the exception it raised, if any, by class name and message."""
    repo = str(Path(__file__).resolve().parent.parent)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (repo, os.environ.get("PYTHONPATH", "")) if p)}
    with tempfile.TemporaryDirectory(prefix="physmorph-cell-") as tmp:
        call, result = Path(tmp) / "call.json", Path(tmp) / "result.json"
        call.write_text(json.dumps({"target": target, "kwargs": kwargs}))
        out = open(log, "a") if log is not None else subprocess.DEVNULL
        started = time.time()
        try:
            proc = subprocess.Popen([sys.executable, "-m", "physmorph.extremes", str(call), str(result)],
                                    stdout=out, stderr=subprocess.STDOUT, env=env, start_new_session=True)
            try:
                returncode, timed_out = proc.wait(timeout=timeout_s), False
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)  # the child leads its own group: it and what it started
                returncode, timed_out = proc.wait(), True
        finally:
            if log is not None:
                out.close()
        wall = time.time() - started
        payload = json.loads(result.read_text()) if result.exists() else {}
    return ChildResult(returncode, timed_out, payload.get("error_type"), payload.get("error_message"),
                       payload.get("traceback"), wall)


def _child_main(call_path: str, result_path: str) -> int:
    """The child of run_isolated: make the call, write what it raised (if anything) to result_path."""
    spec = json.loads(Path(call_path).read_text())
    module, func = spec["target"].split(":")
    out: dict = {"error_type": None, "error_message": None, "traceback": None}
    code = 0
    try:
        getattr(importlib.import_module(module), func)(**spec["kwargs"])
    except BaseException as exc:  # noqa: BLE001 - every exception is reported; the parent judges it
        out = {"error_type": type(exc).__name__, "error_message": str(exc), "traceback": traceback.format_exc()}
        print(out["traceback"], file=sys.stderr, flush=True)
        code = 1
    Path(result_path).write_text(json.dumps(out))
    return code


def cell_timeout_s(n_particles: int, frames: int) -> float:
    """A cell's wall-clock limit: TIMEOUT_MARGIN times its expected morph time, at least TIMEOUT_FLOOR_S
    (start-up and the solver's compilation take up to ~30 s on a loaded machine)."""
    return max(TIMEOUT_FLOOR_S, TIMEOUT_MARGIN * SECONDS_PER_PARTICLE_FRAME * n_particles * frames)


# --------------------------------------------------------------------------------------------
# What happened, and its outcome
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class CellRun:
    """What one cell did, read from its config check, its process and its run file."""

    refusal: str | None = None
    config_warnings: tuple[str, ...] = ()
    timed_out: bool = False
    returncode: int | None = 0
    error_type: str | None = None
    error_message: str | None = None
    status: str | None = None  # the run file's status ("complete"; "running" for a partial run)
    frames_planned: int = 0
    frames_completed: int = -1  # the last committed frame (-1: none)
    run_warnings: tuple[str, ...] = ()
    metrics_finite: bool = True  # every committed frame's metrics are finite
    gap_closed_last: float = math.nan
    gap_closed_best: float = math.nan


@dataclass(frozen=True)
class Outcome:
    outcome: str  # one of OUTCOMES
    detail: str  # the warning, the refusal, the stop or the crash, in words
    key: str | None = None  # refused: the key named
    frame: int | None = None  # stopped: the frame
    quantity: str | None = None  # stopped: the quantity


_STOP = re.compile(r"^frame (\d+): (?:\|(?P<bound>[^|]+)\| = \S+ exceeds|(?:the )?(?P<nonfinite>.+?) became non-finite)")


def parse_stop(message: str) -> tuple[int, str] | None:
    """(frame, quantity) of a MorphDivergenceError's message ("frame 7: |F| = 61 exceeds 50 ...",
    "frame 3: x became non-finite ...", "frame 2: the dFc gradient became non-finite ..."), else None."""
    m = _STOP.match(message or "")
    if not m:
        return None
    return int(m[1]), (m["bound"] or m["nonfinite"]).strip()


# Refusals a stage makes once it has what the config cannot know (exception class -> the pattern of
# its message that names the key): a shape's bounds around its centroid are known once its mesh is
# prepared, so a grid whose particle region cannot hold it is refused by the sampling.
STAGE_REFUSALS = {"MeshError": re.compile(r"do not fit the grid's particle region .*?raise (sampling\.grid_res)")}


def stage_refusal_key(error_type: str | None, message: str | None) -> str | None:
    """The config key a stage's refusal names (STAGE_REFUSALS), None for anything else."""
    pattern = STAGE_REFUSALS.get(error_type or "")
    m = pattern.search(message or "") if pattern else None
    return m[1] if m else None


def _signal_name(returncode: int) -> str:
    try:
        return signal.Signals(-returncode).name
    except ValueError:
        return f"signal {-returncode}"


def classify(run: CellRun, converged_gap: float = CONVERGED_GAP) -> Outcome:
    """The one outcome of a cell (see the module docstring); crash and hang say what went wrong."""
    warned = run.config_warnings + run.run_warnings
    if run.refusal is not None:
        key = refused_key(run.refusal)
        if key is None:
            return Outcome("crash", f"a refusal that names no config key: {run.refusal}")
        return Outcome("refused", run.refusal, key=key)
    if run.timed_out:
        return Outcome("hang", f"no result within its wall-clock limit (after frame {run.frames_completed})")
    if run.error_type is not None or run.returncode not in (0, None):
        stage_key = stage_refusal_key(run.error_type, run.error_message)
        if stage_key is not None:
            return Outcome("refused", f"refused by the sampling stage: {run.error_message}", key=stage_key)
        if run.error_type == "MorphDivergenceError":
            stop = parse_stop(run.error_message or "")
            if stop is None:
                return Outcome("crash", f"a divergence that names no frame and quantity: {run.error_message}")
            frame, quantity = stop
            if run.frames_completed != frame - 1:
                return Outcome("crash", f"stopped at frame {frame} but frames 0..{run.frames_completed} are kept: "
                                        f"{run.error_message}")
            if not run.metrics_finite:
                return Outcome("crash", f"stopped at frame {frame} with non-finite metrics in the kept frames")
            return Outcome("stopped", run.error_message or "", frame=frame, quantity=quantity)
        if run.error_type is not None:
            return Outcome("crash", f"{run.error_type}: {run.error_message}")
        how = _signal_name(run.returncode) if run.returncode < 0 else f"exit code {run.returncode}"
        return Outcome("crash", f"the process ended ({how}) without a result")
    if run.status != "complete" or run.frames_completed != run.frames_planned:
        return Outcome("crash", f"the run reports {run.status!r} after {run.frames_completed} of "
                                f"{run.frames_planned} frames")
    if not (run.metrics_finite and math.isfinite(run.gap_closed_last)):
        return Outcome("crash", "the run reports success with a non-finite metric (a silent NaN)")
    if warned:
        return Outcome("warned", "; ".join(warned))
    if run.gap_closed_last >= converged_gap:
        return Outcome("converged", f"closed {100 * run.gap_closed_last:.0f} % of the gap")
    return Outcome("not converged", f"ran every frame but closed {100 * run.gap_closed_last:.0f} % of the gap "
                                    f"(converged: at least {100 * converged_gap:.0f} %)")


# Metrics that every committed frame must hold finite (frame 0 has no physics step: its losses are NaN).
FINITE_METRICS = ("alpha_mse", "iou", "gap_closed", "chamfer", "fp_det_min", "fp_det_max", "total_volume")
FINITE_AFTER_FRAME_0 = ("physics_loss", "physics_loss_initial")


def read_cell_run(run_h5: Path) -> dict:
    """status, frames_completed, run_warnings, metrics_finite and the gap closed of a finished run
    file or, when there is none, of its partial run (its committed frames)."""
    from physmorph.runfile import partial_dir, read_metrics

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
    from physmorph.config import canonical_json, morph_params, params_json
    from physmorph.particles import stored_particle_count

    work = Path(work_dir)
    check = check_cell(mapping)
    record = {"cell": cell.name, "knob": cell.knob, "key": cell.key, "value": cell.label, "order": cell.order,
              "is_default": cell.is_default, "note": cell.note, "n_particles": None, "frames_planned": None,
              "wall_s": 0.0, "peak_rss_mb": math.nan, "traceback": None}
    if check.settings is None:
        run = CellRun(refusal=check.refusal, config_warnings=check.warnings)
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
            child = run_isolated("physmorph.extremes:cell_pipeline", kwargs, limit, log)
        else:  # in this process (fast tests): no wall-clock limit, an exception is caught here
            child = _call_here("physmorph.extremes:cell_pipeline", kwargs)
        found = read_cell_run(work / "run.h5")
        record.update(wall_s=child.wall_s, peak_rss_mb=found.pop("peak_rss_mb", math.nan), traceback=child.traceback)
        record["n_particles"] = found.pop("n_particles", None) or stored_particle_count(work / "particles.h5")
        if cell.knob == "particles" and record["n_particles"]:  # the sampled count, not the estimate
            record["value"] = re.sub(r"\(~[^)]*\)", f"({_count(record['n_particles'])})", cell.label)
        run = CellRun(config_warnings=check.warnings, timed_out=child.timed_out, returncode=child.returncode,
                      error_type=child.error_type, error_message=child.error_message, frames_planned=cfg.frames,
                      **found)
    outcome = classify(run)
    record.update(outcome=outcome.outcome, detail=outcome.detail, refused_key=outcome.key,
                  stop_frame=outcome.frame, stop_quantity=outcome.quantity,
                  warnings=list(run.config_warnings + run.run_warnings),
                  frames_completed=run.frames_completed if run.refusal is None else None,
                  gap_closed_last=run.gap_closed_last, gap_closed_best=run.gap_closed_best)
    return record


def _call_here(target: str, kwargs: dict) -> ChildResult:
    module, func = target.split(":")
    started = time.time()
    try:
        getattr(importlib.import_module(module), func)(**kwargs)
    except Exception as exc:  # noqa: BLE001 - reported as the child would
        return ChildResult(1, False, type(exc).__name__, str(exc), traceback.format_exc(), time.time() - started)
    return ChildResult(0, False, None, None, None, time.time() - started)


# --------------------------------------------------------------------------------------------
# The map: table and figure
# --------------------------------------------------------------------------------------------

OUTCOME_COLORS = {"converged": "#4daf4a", "not converged": "#c7e9c0", "warned": "#ff9f1c", "refused": "#9ecae1",
                  "stopped": "#b07cc6", "crash": "#e41a1c", "hang": "#000000"}
TABLE_COLUMNS = ("knob", "key", "value", "particles", "frames", "outcome", "gap_closed_last_%", "gap_closed_best_%",
                 "detail", "wall_s")


def map_table(records: list[dict]):
    """The map as a DataFrame, one row per cell in knob order, then value order."""
    import pandas as pd

    rank = {k.name: i for i, k in enumerate(KNOBS)}
    rows = []
    for r in sorted(records, key=lambda r: (rank.get(r["knob"], len(rank)), r["order"])):
        frames = "" if r["frames_planned"] is None else (
            f"{r['frames_completed']}/{r['frames_planned']}" + (f" ({r['note']})" if r["note"] else ""))
        rows.append({"knob": r["knob"], "key": r["key"], "value": r["value"],
                     "particles": "" if r["n_particles"] is None else f"{r['n_particles']:,}",
                     "frames": frames, "outcome": r["outcome"],
                     "gap_closed_last_%": 100 * r["gap_closed_last"], "gap_closed_best_%": 100 * r["gap_closed_best"],
                     "detail": _short_detail(r), "wall_s": round(r["wall_s"], 1)})
    return pd.DataFrame(rows, columns=list(TABLE_COLUMNS))


def _short_detail(r: dict) -> str:
    """The table's detail: the key of a refusal with its reason, a stop's frame and quantity, the warning."""
    text = str(r["detail"]).replace("|", "\\|").replace("\n", " ")
    if r["outcome"] == "refused":
        reason = re.sub(r"^config key '[^']+': ", "", text)
        return f"`{r['refused_key']}`: {reason}"
    if r["outcome"] == "stopped":
        return f"frame {r['stop_frame']}, {r['stop_quantity']}: {text.split(' (completed frames')[0]}"
    return text


def _annotation(r: dict) -> str:
    o = r["outcome"]
    if o == "refused":
        return f"refused\n{r['refused_key']}"
    if o == "stopped":
        return f"stopped\n{r['stop_quantity']} @ frame {r['stop_frame']}"
    if o in FAILURES:
        return o.upper()
    gap = f"{100 * r['gap_closed_last']:.0f} %"
    return f"warned\n{gap}" if o == "warned" else gap


def plot_map(records: list[dict], png: str | Path, title: str = "") -> None:
    """Knobs as rows, their values as columns, each cell coloured by its outcome and annotated
    with the gap closed at the last frame, the key of a refusal or the frame of a stop."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch, Rectangle

    rows = [k for k in KNOBS if any(r["knob"] == k.name for r in records)]
    by_knob = {k.name: sorted((r for r in records if r["knob"] == k.name), key=lambda r: r["order"]) for k in rows}
    ncols = max(len(v) for v in by_knob.values())
    fig, ax = plt.subplots(figsize=(1.55 * ncols + 2.6, 0.78 * len(rows) + 1.5))
    for i, knob in enumerate(rows):
        y = len(rows) - 1 - i
        for j, r in enumerate(by_knob[knob.name]):
            ax.add_patch(Rectangle((j, y), 0.96, 0.92, facecolor=OUTCOME_COLORS[r["outcome"]],
                                   edgecolor="k", lw=2.0 if r["is_default"] else 0.3))
            dark = r["outcome"] in ("hang", "crash", "stopped")
            ax.text(j + 0.48, y + 0.68, r["value"].replace(" (default)", "*"), ha="center", va="center",
                    fontsize=6.5, color="w" if dark else "k")
            ax.text(j + 0.48, y + 0.3, _annotation(r), ha="center", va="center", fontsize=6.5,
                    color="w" if dark else "k", fontweight="bold")
    ax.set_xlim(-0.05, ncols)
    ax.set_ylim(-0.05, len(rows))
    ax.set_yticks([len(rows) - 1 - i + 0.46 for i in range(len(rows))])
    ax.set_yticklabels([k.title for k in rows], fontsize=8)
    ax.set_xticks([])
    for s in ax.spines.values():
        s.set_visible(False)
    present = [o for o in OUTCOMES if any(r["outcome"] == o for r in records)]
    ax.legend(handles=[Patch(facecolor=OUTCOME_COLORS[o], edgecolor="k", lw=0.3, label=o) for o in present],
              loc="upper center", bbox_to_anchor=(0.5, -0.01), ncol=len(present), fontsize=7, frameon=False)
    ax.set_title(title or "stability map: one knob at a time from the default (* bold border)", fontsize=9)
    fig.tight_layout()
    fig.savefig(png, dpi=130)
    plt.close(fig)


def build_map(records: list[dict], out_dir: str | Path, title: str = ""):
    """Write stability_map.csv, stability_map.md and stability_map.png; return the table. The
    markdown says how many cells ended in each outcome; a crash or a hang is named first."""
    from physmorph.tables import markdown_table

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    df = map_table(records)
    df.to_csv(out / "stability_map.csv", index=False)
    counts = df["outcome"].value_counts()
    summary = ", ".join(f"{o} {int(counts[o])}" for o in OUTCOMES if o in counts)
    failures = df[df["outcome"].isin(FAILURES)]
    head = f"{len(df)} cells: {summary}.\n\n"
    if len(failures):
        head += ("**Cells that crashed or hung** (a bug: each must become a refusal, a warning or a named stop):\n\n"
                 + markdown_table(failures) + "\n")
    (out / "stability_map.md").write_text(head + markdown_table(df))
    plot_map(records, out / "stability_map.png", title)
    return df


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


if __name__ == "__main__":  # the child of run_isolated: python -m physmorph.extremes CALL.json RESULT.json
    sys.exit(_child_main(sys.argv[1], sys.argv[2]))
