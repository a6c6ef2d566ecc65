"""The stability map of the extremes (physmorph.studies.extremes, physmorph.studies.stability_map): every cell's
outcome is one of converged, not converged, warned, refused (naming the key) or stopped (naming
frame and quantity, earlier frames kept), never a crash, a hang or a silent NaN. The classifier on
hand-made runs and on the exceptions themselves (their key, frame and quantity are data: a
reworded message changes no outcome), the refusals of the most extreme configs, the process guard,
and the most extreme cells that run, on the tiny test profile with fewer frames (the outcome's
class is what is tested)."""

import dataclasses
import math
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

from physmorph.settings.errors import ConfigError
from physmorph.settings.build import deep_merge
from physmorph.settings.workflow import load_settings
from physmorph.settings.build import load_mapping
from physmorph.studies.extremes import cell_mapping, check_cell, map_cells, read_cell_run, run_cell
from physmorph.base.isolated_call import error_report, run_isolated
from physmorph.meshes.errors import MeshError
from physmorph.settings.mpm import MPMDivergenceError
from physmorph.morph.stability import MorphDivergenceError
from physmorph.studies.stability_map import (ERROR_FIELDS, FAILURES, KNOBS, MAP_EXPERIMENT, OUTCOMES, CellRun, build_map,
                                     classify)
from snakemake_runs import plan_here

REPO = Path(__file__).resolve().parents[2]
ALLOWED = tuple(o for o in OUTCOMES if o not in FAILURES)


@pytest.fixture(scope="module")
def base():
    return load_mapping(REPO / "config" / "config.yaml", REPO / "config" / "test.yaml")


@pytest.fixture(scope="module")
def cells(base):
    return map_cells(base)


# ------------------------------------------------------------------------------ classify

MESH_MISFIT = ("bunny: mesh bounds [[-8.5, -6.2, -8.4], [9.5, 11.6, 5.5]] do not fit the grid's particle region "
               "[-10.0, 10.0]^3 (res 16, domain [-16.0, 16.0]; particles keep 3 cells from each face); raise "
               "sampling.grid_res, shrink the shape (shapes.bunny.size) or enlarge the domain")
MEMORY = ("config: morph iso_bunny_full needs an estimated 29,098 MB (...) above the limit of 24,105 MB "
          "(max_memory_mb (null: this machine's memory)); lower sampling.grid_res")
KEPT = " (completed frames are kept in r.h5.partial)"  # what the morph loop adds when it re-raises a stop
DONE = dict(status="complete", frames_planned=12, frames_completed=12, gap_closed_last=0.5, gap_closed_best=0.6)


def _refused(exc: ConfigError) -> CellRun:
    """The CellRun of a config the check refused with ``exc`` (as physmorph.studies.extremes.check_cell reads it)."""
    return CellRun(refusal=exc.reason, refused_key=exc.key)


def _raised(exc: BaseException, cause: BaseException | None = None, **run) -> CellRun:
    """The CellRun of a cell whose process raised ``exc`` (``from cause``), reported as a cell's
    process reports it (physmorph.base.isolated_call.error_report)."""
    exc.__cause__ = cause
    report = error_report(exc, ERROR_FIELDS)
    return CellRun(returncode=1, error_type=report["error_type"], error_message=report["error_message"],
                   error_data=report["error_data"], **run)


def _stop_f(message: str = "frame 7: |F| = 61.2 exceeds 50 (particle 3)", **run) -> CellRun:
    """A stop as the morph loop raises it: the state check's error re-raised with where the kept frames are."""
    state_check = MorphDivergenceError(message, frame=7, quantity="F", particle=3)
    return _raised(MorphDivergenceError(message + KEPT), state_check, **run)


def _solver_stop(frame: int, message: str, quantity: str, **run) -> CellRun:
    """A stop the solver raised, re-raised by the morph loop at its frame."""
    return _raised(MorphDivergenceError(f"frame {frame}: {message}{KEPT}", frame=frame),
                   MPMDivergenceError(message, quantity=quantity), **run)


@pytest.mark.parametrize("run, outcome, named", [
    (_refused(ConfigError.for_key("mpm.dt", "dt=0.0132 exceeds the stable step 0.011")), "refused", "mpm.dt"),
    (_refused(ConfigError(MEMORY, key="max_memory_mb")), "refused", "max_memory_mb"),
    (_refused(ConfigError("something is wrong")), "crash", "names no config key"),
    # the key is the error's data: a message that reads like a refusal of a key is not one without it
    (_refused(ConfigError("config key 'mpm.dt': dt=0.0132 exceeds")), "crash", "names no config key"),
    (CellRun(timed_out=True, returncode=-9, frames_completed=4), "hang", "after frame 4"),
    (_stop_f(frames_completed=6), "stopped", "F"),
    (_solver_stop(3, "x became non-finite (NaN/Inf or |x| > 1e+08) at substep 4 (particle 12)", "x",
                  frames_completed=2), "stopped", "x"),
    (_solver_stop(2, "the dFc gradient became non-finite (NaN/Inf) in the backward pass", "dFc gradient",
                  frames_completed=1), "stopped", "dFc gradient"),
    # a stop that lost frames, or names no frame, is a bug
    (_stop_f(frames_completed=3), "crash", "frames 0..3 are kept"),
    (_raised(MorphDivergenceError("frame 7: it diverged")), "crash", "names no frame"),
    (_raised(ValueError("x of particle 3 is outside")), "crash", "ValueError"),
    (_raised(MeshError(MESH_MISFIT, key="sampling.grid_res")), "refused", "sampling.grid_res"),
    (_raised(MeshError("bunny: mesh is empty, nothing to sample")), "crash", "MeshError"),
    (CellRun(returncode=-9), "crash", "SIGKILL"),
    (CellRun(**DONE), "converged", "50 %"),
    (CellRun(**{**DONE, "gap_closed_last": 0.1}), "not converged", "closed 10 %"),
    (CellRun(**DONE, config_warnings=("CFLWarning: dt=0.0099 is 90% of the stable step",)), "warned", "90% of the stable"),
    (CellRun(**DONE, run_warnings=("frame 9: alpha MSE rose for 8 frames in a row",)), "warned", "rose for 8 frames"),
    # success with garbage
    (CellRun(**{**DONE, "metrics_finite": False}), "crash", "silent NaN"),
    (CellRun(**{**DONE, "gap_closed_last": math.nan}), "crash", "silent NaN"),
    (CellRun(**{**DONE, "frames_completed": 5}), "crash", "after 5 of 12 frames"),
])
def test_classify_names_what_happened(run, outcome, named):
    got = classify(run)
    assert got.outcome == outcome, got
    assert named in " ".join(str(v) for v in (got.detail, got.key, got.quantity)), got
    if outcome == "stopped":
        assert got.frame == run.error_data["frame"] == run.frames_completed + 1


@pytest.mark.parametrize("said, reworded", [
    (_refused(ConfigError.for_key("mpm.dt", "dt=0.0132 exceeds the stable step 0.011")),
     _refused(ConfigError("the frame step is longer than the material allows", key="mpm.dt"))),
    (_refused(ConfigError(MEMORY, key="max_memory_mb")),
     _refused(ConfigError("too big for this machine", key="max_memory_mb"))),
    (_raised(MeshError(MESH_MISFIT, key="sampling.grid_res")),
     _raised(MeshError("the bunny does not fit", key="sampling.grid_res"))),
    (_stop_f(frames_completed=6), _stop_f("the deformation gradient blew up", frames_completed=6)),
    (_solver_stop(3, "x became non-finite at substep 4", "x", frames_completed=2),
     _solver_stop(3, "positions went bad", "x", frames_completed=2)),
])
def test_a_reworded_message_changes_no_outcome(said, reworded):
    """What a cell ends in is read from the errors' attributes (key, frame, quantity), never from
    their text: the same error in other words is classified the same."""
    a, b = classify(said), classify(reworded)
    assert a.outcome in ("refused", "stopped"), a
    assert (a.outcome, a.key, a.frame, a.quantity) == (b.outcome, b.key, b.frame, b.quantity), (a, b)


def test_a_stops_frame_and_quantity_cross_the_cells_process_as_data(tmp_path, monkeypatch):
    """A cell's process sends its exception's key, frame and quantity as JSON: a solver divergence
    re-raised at its frame, under a message that names neither, is a stop at that frame and quantity."""
    (tmp_path / "diverging_cell.py").write_text(
        "from physmorph.settings.mpm import MPMDivergenceError\n"
        "from physmorph.morph.stability import MorphDivergenceError\n\n\n"
        "def run(frame, message):\n"
        "    try:\n"
        "        raise MPMDivergenceError('v blew up', quantity='v', substep=4, particle=12)\n"
        "    except MPMDivergenceError as exc:\n"
        "        raise MorphDivergenceError(message, frame=frame) from exc\n")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(p for p in (str(tmp_path), os.environ.get("PYTHONPATH")) if p))
    child = run_isolated("diverging_cell:run", {"frame": 3, "message": "it went wrong"}, timeout_s=120,
                         error_fields=ERROR_FIELDS)
    assert child.error_type == "MorphDivergenceError" and child.error_data == {"frame": 3, "quantity": "v"}, child
    out = classify(CellRun(returncode=child.returncode, error_type=child.error_type, error_message=child.error_message,
                           error_data=child.error_data, frames_completed=2))
    assert (out.outcome, out.frame, out.quantity) == ("stopped", 3, "v"), out


# ------------------------------------------------------------------------------ the sweep

def test_the_map_covers_every_knob_with_at_least_four_values_around_its_default(base, cells):
    for knob in KNOBS:
        mine = [c for c in cells.values() if c.knob == knob.name]
        assert len(mine) >= 4, knob.name
        assert sum(c.is_default for c in mine) == 1, knob.name
        assert all(c.key == knob.key.format(experiment=MAP_EXPERIMENT) for c in mine)
    assert all(c.overrides for c in cells.values())
    assert any(c.knob == "dt" and check_cell(cell_mapping(base, c)).settings is None for c in cells.values())  # past CFL


def test_a_default_cell_is_the_base_run(base, cells):
    want = load_settings(REPO / "config" / "config.yaml", REPO / "config" / "test.yaml").experiment_config(MAP_EXPERIMENT)
    for c in cells.values():
        if c.is_default:
            assert check_cell(cell_mapping(base, c)).settings.experiment_config(MAP_EXPERIMENT) == want, c.name


@pytest.mark.parametrize("cell, key", [
    ("dt-0.0132", "mpm.dt"),                       # 1.2 x the stable step
    ("youngs_modulus-1e+07", "mpm.dt"),            # the stiffest: its stable step is 0.3 x the default dt
    ("poisson_ratio-0.499", "mpm.dt"),             # nearly incompressible: the P-wave outruns dt
    ("grid_res-128", "mpm.dt"),                    # a finer cell shortens the stable step
    ("drag-480", f"experiments.{MAP_EXPERIMENT}.drag"),  # drag x dt = 2
    ("particles-ppc14x14", "max_memory_mb"),       # ~2M particles: more than the machine (or the limit) holds
])
def test_the_most_extreme_configs_are_refused_naming_the_key(base, cells, cell, key):
    # the memory refusal with a limit below this machine's, so it holds on any machine
    mapping = deep_merge(cell_mapping(base, cells[cell]), {"max_memory_mb": 16000})
    check = check_cell(mapping)
    assert check.settings is None and check.refused_key == key
    out = classify(CellRun(refusal=check.refusal, refused_key=check.refused_key))
    assert (out.outcome, out.key) == ("refused", key), out


def test_near_the_stable_step_the_config_warns(base, cells):
    check = check_cell(cell_mapping(base, cells["dt-0.00988"]))
    assert check.settings is not None
    assert len(check.warnings) == 1 and "CFLWarning: dt=0.00988" in check.warnings[0] and "of the stable step" in check.warnings[0]


# ------------------------------------------------------------------------------ the process guard

def test_a_hang_is_cut_at_its_limit_with_what_it_started():
    r = run_isolated("subprocess:run", {"args": ["sleep", "47.125"]}, timeout_s=2.0)
    assert r.timed_out and r.wall_s < 20
    assert classify(CellRun(timed_out=r.timed_out, returncode=r.returncode)).outcome == "hang"
    # the grandchild (the sleep the child started) went with the child's process group
    assert subprocess.run(["pgrep", "-f", "^sleep 47.125$"], capture_output=True).stdout == b""


def test_a_dead_interpreter_and_an_exception_are_crashes_that_say_why():
    dead = run_isolated("os:abort", {}, timeout_s=60)
    assert classify(CellRun(returncode=dead.returncode)).detail.endswith("(SIGABRT) without a result")
    raised = run_isolated("json:loads", {"s": "{"}, timeout_s=60)
    assert raised.error_type == "JSONDecodeError" and "json/decoder.py" in raised.traceback
    out = classify(CellRun(returncode=raised.returncode, error_type=raised.error_type,
                           error_message=raised.error_message))
    assert out.outcome == "crash" and out.detail.startswith("JSONDecodeError: Expecting")


# ------------------------------------------------------------------------------ the table and figure

def test_the_map_writes_a_table_and_a_figure_with_failures_first(tmp_path):
    common = dict(key="k", order=0.0, is_default=False, note="", n_particles=1178, frames_planned=12, wall_s=1.0,
                  refused_key=None, stop_frame=None, stop_quantity=None, warnings=[], frames_completed=12,
                  gap_closed_last=0.5, gap_closed_best=0.6)
    records = [
        {**common, "cell": "dt-a", "knob": "dt", "value": "0.38 (default)", "is_default": True,
         "outcome": "converged", "detail": "closed 50 % of the gap"},
        {**common, "cell": "dt-b", "knob": "dt", "value": "1.2", "order": 1.2, "outcome": "refused",
         "detail": "dt=0.0132 exceeds", "refused_key": "mpm.dt", "n_particles": None,
         "frames_planned": None, "frames_completed": None, "gap_closed_last": math.nan, "gap_closed_best": math.nan},
        {**common, "cell": "eta-a", "knob": "eta", "value": "1", "outcome": "stopped",
         "detail": "frame 7: |F| = 61.2 exceeds 50 (particle 3)" + KEPT,
         "stop_frame": 7, "stop_quantity": "F", "frames_completed": 6},
        {**common, "cell": "eta-b", "knob": "eta", "value": "0.5", "order": 0.5, "outcome": "crash",
         "detail": "ValueError: boom"},
    ]
    df = build_map(records, tmp_path)
    assert df["knob"].tolist() == ["dt", "dt", "eta", "eta"]
    md = (tmp_path / "stability_map.md").read_text()
    assert md.startswith("4 cells: converged 1, refused 1, stopped 1, crash 1.")
    assert "**Cells that crashed or hung**" in md and "ValueError: boom" in md
    assert "`mpm.dt`: dt=0.0132 exceeds" in md and "frame 7, F: frame 7: \\|F\\| = 61.2 exceeds 50" in md
    assert (tmp_path / "stability_map.png").stat().st_size > 10_000
    # the docs page (python -m physmorph.reports.userdocs stability PROFILE) reads the same files
    from physmorph.reports.userdocs import write_stability_doc

    tree = tmp_path / "results" / "test" / "stability_map"
    tree.mkdir(parents=True)
    for f in ("stability_map.csv", "stability_map.png"):
        (tmp_path / f).rename(tree / f)
    page = write_stability_doc("test", tmp_path / "results", tmp_path / "docs" / "stability.md",
                               tmp_path / "docs" / "images" / "stability_map.png").read_text()
    assert "4 cells over 2 settings (dt 2, eta 2): converged 1, refused 1, stopped 1, crash 1. Cells that crashed " \
           "or hung: 1." in page
    assert "](images/stability_map.png)" in page and (tmp_path / "docs" / "images" / "stability_map.png").exists()
    assert "| eta | 0.5 | 1,178 | 12/12 | crash | 50 | ValueError: boom |" in page


def test_the_workflow_plans_one_job_per_cell_and_none_for_a_refused_cells_inputs(tmp_path, cells):
    for name in ("Snakefile", "config", "workflow"):
        (tmp_path / name).symlink_to(REPO / name)
    out = plan_here(tmp_path, ["-n", "--cores", "2", "stability_map", "--configfile", "config/test.yaml"])
    text = out.stdout + out.stderr
    assert out.returncode == 0, text[-3000:]
    assert f"stability_cell           {len(cells)}" in text, text[-2000:]
    assert "results/test/stability_map/stability_map.png" in text
    assert "particles/iso_32x14x14.h5" not in text and "targets/bunny_128x1x1.h5" not in text  # refused: never made


# ------------------------------------------------------------------------------ the extreme cells that run

@pytest.fixture(scope="module")
def meshes(tmp_path_factory, tiny):
    """The prepared iso and bunny meshes (a cell samples and rasterizes them at its resolution):
    the session's tiny ones (conftest), linked into a folder of this module's."""
    _, made = tiny
    d = tmp_path_factory.mktemp("extremes")
    for name in ("iso.h5", "bunny.h5"):
        (d / name).symlink_to(made / name)
    return d


@pytest.mark.parametrize("name", ["step_size-x10", "gamma-10", "eta-1"])
def test_the_most_extreme_running_cells_end_in_an_allowed_outcome(base, cells, meshes, name):
    """The largest step, gain and plasticity rate, 5 frames (two with plasticity), in this process:
    they share one compiled solver (none of the three is a kernel setting). Slow (~11 s for the
    first cell): it builds that solver."""
    short = {"experiments": {MAP_EXPERIMENT: {"frames": 5, "release_frames": 0}}}
    cell = dataclasses.replace(cells[name], overrides=deep_merge(cells[name].overrides, short))
    work = meshes / name
    rec = run_cell(cell, cell_mapping(base, cell), meshes / "iso.h5", meshes / "bunny.h5", work, isolate=False)
    assert rec["outcome"] in ALLOWED, rec
    assert rec["n_particles"] > 1000 and rec["frames_planned"] == 5
    found = read_cell_run(work / "run.h5")
    if rec["outcome"] == "stopped":
        assert found["frames_completed"] == rec["stop_frame"] - 1 and found["metrics_finite"]
    else:
        assert found["frames_completed"] == 5 and np.isfinite(rec["gap_closed_last"])


def test_a_grid_too_coarse_to_hold_the_target_is_refused_naming_the_grid(base, cells, meshes):
    """At 16 cells the particle region ([-10, 10]^3: 3 cells kept from each face) cannot hold the
    bunny around its centroid: its sampling refuses it naming sampling.grid_res, before any morph."""
    rec = run_cell(cells["grid_res-16"], cell_mapping(base, cells["grid_res-16"]), meshes / "iso.h5",
                   meshes / "bunny.h5", meshes / "grid16", isolate=False)
    assert (rec["outcome"], rec["refused_key"]) == ("refused", "sampling.grid_res"), rec
    assert "bunny: mesh bounds" in rec["detail"] and not (meshes / "grid16" / "run.h5.partial").exists()
