"""End-to-end: the Snakemake workflow on config/test.yaml, in a scratch working directory.

One real run of the test profile (module fixture) serves every test that needs finished outputs:
the tables, the params that trigger reruns, the report and a user mesh given by path."""

import hashlib
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pytest

from snakemake_runs import REPO, TEST, planned_jobs, planned_outputs
from snakemake_runs import scratch_workdir as _workdir, snakemake_run as _run


# ------------------------------------------------------------------------- one real run

@pytest.fixture(scope="module")
def test_run(tmp_path_factory, mesh_dir):
    """The test profile's tables, figures and tradeoff, made once in a scratch working directory:
    (that directory, mesh_dir). Slow: the test profile's whole workflow, each job its own process:
    two 12-frame morphs (each then released for 40 frames), three 3-frame tradeoff points and the
    meshes, particles, targets, tables and figures they need."""
    wd = _workdir(tmp_path_factory.mktemp("wf"))
    out = _run(wd, "tables", "figures", "tradeoff", *TEST, "--config", f"mesh_dir={mesh_dir}", check=False)
    assert out.returncode == 0, out.stderr[-4000:]
    return wd, mesh_dir


def test_tables_on_test_profile(test_run):
    """The test profile's run leaves every stage's outputs, logs and benchmarks, its tables in three
    formats with the paper's numbers beside ours, the speed/accuracy study and the figures.
    Slow: its fixture test_run runs the test profile's whole workflow, each job its own process."""
    wd, _ = test_run
    r = wd / "results/test"
    for shape in ("iso", "bunny"):
        assert (r / f"particles/{shape}_32x1x1.h5").exists()
        assert (r / f"targets/{shape}_32x1x1.h5").exists()
        assert (r / f"previews/targets/{shape}_32x1x1.png").stat().st_size > 1000
    with h5py.File(r / "runs/iso_bunny_full.h5") as f:
        assert f.attrs["status"] == "complete"
        assert len(f["metrics/alpha_mse"]) == 13  # frame 0 + 12 frames
        assert "git_commit" in f.attrs and "peak_rss_mb" in f.attrs
    assert not list(wd.glob("results/**/*.partial"))
    # every job wrote its log and benchmark; the morph's log has its progress
    for rule in ("prepare_mesh", "sample_particles", "rasterize_target", "morph"):
        assert list((r / "logs" / rule).glob("*.log")), rule
        assert list((r / "benchmarks" / rule).glob("*.tsv")), rule
    assert "iso_bunny_full" in (r / "logs/morph/iso_bunny_full.log").read_text()
    # Tables: every table in three formats, well formed, with our numbers beside the paper's.
    main = pd.read_csv(r / "tables/main.csv")
    assert list(main["target"]) == ["bunny", "cow", "duck"]
    bunny = main.set_index("target").loc["bunny"]
    assert bunny["paper_physics_only"] == 0.0799 and np.isfinite(bunny["physics_only"]) and np.isfinite(bunny["ours"])
    assert 0 <= bunny["frame"] <= 12
    timing = pd.read_csv(r / "tables/timing.csv")
    assert set(timing["experiment"]) == {"iso_bunny_physics_only", "iso_bunny_full"}
    assert (timing["frame_s"] > 0).all() and (timing["peak_rss_mb"] > 0).all()
    conv = pd.read_csv(r / "tables/convergence.csv").set_index("experiment")
    assert set(conv.index) == {"iso_bunny_physics_only", "iso_bunny_full"}
    assert (conv["ceiling"] > 0).all() and np.isfinite(conv[["closed_best_%", "closed_final_%"]].to_numpy()).all()
    directions = pd.read_csv(r / "tables/directions.csv", keep_default_na=False).set_index("case")
    # both runs made here: the direction holds when full is below physics-only at the frame where
    # physics-only first made 90 % of its improvement, recomputed from the two run files
    curves = {}
    for method in ("physics_only", "full"):
        with h5py.File(r / f"runs/iso_bunny_{method}.h5") as f:
            curves[method] = f["metrics/alpha_mse"][()]
    po, full = curves["physics_only"], curves["full"]
    k = next(i for i, v in enumerate(po) if po[0] - v >= 0.9 * (po[0] - po.min()))
    row = directions.loc["bunny"]
    assert f"(frame {k})" in row["measure"] and bunny["frame"] == k
    assert float(row["ours"]) == pytest.approx(full[k], rel=1e-6)
    assert float(row["baseline"]) == pytest.approx(po[k], rel=1e-6)
    assert row["holds"] == ("yes" if full[k] < po[k] else "no")
    assert directions.loc["iso_bunny_f_inject vs iso_bunny_position_inject", "holds"] == ""  # not run here
    for name in ("main", "ablation_components", "ablation_drag", "source_invariance", "plasticity", "shapes", "timing",
                 "convergence", "directions"):
        md = (r / f"tables/{name}.md").read_text().splitlines()
        assert md[0].startswith("|") and set(md[1]) <= set("|-")
        assert "\\begin{tabular}" in (r / f"tables/{name}.tex").read_text()
    # Speed/accuracy study: base + one point per changed knob value, Pareto front marked.
    trade = pd.read_csv(r / "tradeoff/tradeoff.csv")
    assert set(trade["name"]) == {"base", "cameras-2", "image-32x24"}
    assert trade["pareto"].any() and (trade["time_s"] > 0).all() and np.isfinite(trade["gap_last"]).all()
    assert np.isfinite(trade["chamfer_last_dx"]).all() and "time_to_90_s" in trade
    assert (r / "targets/bunny_32x1x1_32x24.h5").exists()
    md = (r / "tradeoff/tradeoff.md").read_text()
    assert "final gap per second" in md and "What to run for a budget" in md
    # Figures: real PNGs.
    for png in ("figures/sequences_main", "figures/drag_ablation", "figures/optimization_traces",
                "figures/gradient_coverage", "tradeoff/pareto"):
        data = (r / f"{png}.png").read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000


def test_changed_settings_rerun_exactly_the_runs_that_use_them(test_run):
    """A changed setting replans exactly the jobs whose params it reaches; a setting at its default,
    the thread count and where the mesh mirror lies replan nothing.
    Slow: ten Snakemake dry runs, each its own process building the test profile's whole DAG."""
    wd, mesh_dir = test_run
    base = (*TEST, "--config", f"mesh_dir={mesh_dir}")
    targets = ("tables", "tradeoff")
    assert planned_jobs(_run(wd, "-n", *targets, *base)) == {}
    # one experiment's own setting: that run, then the tables
    out = _run(wd, "-n", *targets, *base,
               "experiments={iso_bunny_physics_only: {source: iso, target: bunny, method: physics_only, drag: 0.5}}")
    assert planned_jobs(out) == {"morph": 1, "make_tables": 1, "tables": 1}, out.stdout[-3000:]
    assert "results/test/runs/iso_bunny_physics_only.h5" in planned_outputs(out)
    assert "Params have changed" in out.stdout + out.stderr
    # ... and of the study's base experiment: that run and the study's points
    # (a full run's tables read its exported surface: that job too)
    out = _run(wd, "-n", *targets, *base, "experiments={iso_bunny_full: {source: iso, target: bunny, method: full, drag: 0.5}}")
    assert planned_jobs(out) == {"morph": 1, "export_meshes": 1, "tradeoff_point": 3, "make_tables": 1,
                                 "make_tradeoff": 1, "tables": 1, "tradeoff": 1}, out.stdout[-3000:]
    assert "results/test/runs/iso_bunny_full.h5" in planned_outputs(out)
    # a global setting only the full method reads: the full run and the tradeoff points (iso_bunny_full)
    out = _run(wd, "-n", *targets, *base, "plasticity={eta: 0.1}")
    assert planned_jobs(out) == {"morph": 1, "export_meshes": 1, "tradeoff_point": 3, "make_tables": 1,
                                 "make_tradeoff": 1, "tables": 1, "tradeoff": 1}, out.stdout[-3000:]
    assert "results/test/runs/iso_bunny_physics_only.h5" not in planned_outputs(out)
    # a setting every run reads: every run, no data stage
    out = _run(wd, "-n", *targets, *base, "mpm={smoothing: 0.9}")
    assert planned_jobs(out) == {"morph": 2, "export_meshes": 1, "tradeoff_point": 3, "make_tables": 1,
                                 "make_tradeoff": 1, "tables": 1, "tradeoff": 1}, out.stdout[-3000:]
    # a sampling setting: the particles, the targets' ceilings (the target's own sampling) and the
    # runs on them; the prepared meshes stay
    out = _run(wd, "-n", "tables", *base, "sampling={sigma_scale: 0.8}")
    assert planned_jobs(out) == {"sample_particles": 2, "rasterize_target": 2, "morph": 2, "export_meshes": 1,
                                 "make_tables": 1, "tables": 1}
    # the thread count changes no result, nor does where the mesh mirror lies (or that there is none)
    assert planned_jobs(_run(wd, "-n", *targets, *base, "threads=1")) == {}
    assert planned_jobs(_run(wd, "-n", *targets, *TEST, "--config", f"mesh_dir={wd / 'elsewhere'}")) == {}
    assert planned_jobs(_run(wd, "-n", *targets, *TEST, "--config", "mesh_dir=null")) == {}
    # a setting at its default is left out of the params (physmorph.settings.workflow.params_json), so an
    # option added later at a default that changes nothing reruns nothing
    assert planned_jobs(_run(wd, "-n", *targets, *base, "mpm={mass_loss_blur_weight: 1.0}", "plasticity={max_anisotropy: 4.0}",
                             "sampling={sigma_scale: 0.7}")) == {}


def test_profiles_never_share_a_file(test_run):
    wd, mesh_dir = test_run
    out = _run(wd, "-n", "tables", "figures", "--config", f"mesh_dir={mesh_dir}")  # the default profile
    outs = planned_outputs(out)
    assert "results/default/runs/iso_bunny_full.h5" in outs
    assert not [p for p in outs if p.startswith("results/test/")]
    # and the test profile's finished tree is still complete and up to date
    assert planned_jobs(_run(wd, "-n", "tables", *TEST, "--config", f"mesh_dir={mesh_dir}")) == {}


def test_report_holds_tables_figures_and_pareto(test_run):
    wd, mesh_dir = test_run
    _run(wd, "tables", "figures", "tradeoff", *TEST, "--config", f"mesh_dir={mesh_dir}", "--report", "report.html")
    html = (wd / "report.html").read_text(errors="replace")
    for name in ("main.csv", "timing.csv", "sequences_main.png", "pareto.png", "tradeoff.csv"):
        assert name in html, name


def test_a_mesh_given_by_path_is_prepared_from_that_file(test_run):
    """A user's mesh given by a path relative to the working directory (a brick, not in the mirror)
    is prepared from that file, nothing fetched. (Its sampling, rasterizing and full morph from a
    path: tests/cli/test_morph_command.py, whose config names its meshes by path.)"""
    import trimesh

    wd, mesh_dir = test_run
    mesh = trimesh.creation.box(extents=(10.0, 7.0, 5.0))
    (wd / "my").mkdir()
    mesh.export(wd / "my/brick.obj")
    (wd / "mine.yaml").write_text("shapes:\n  brick: {kind: file, path: my/brick.obj, size: 14.0}\n"
                                  "experiments:\n  iso_brick: {source: iso, target: brick, method: full, frames: 3}\n")
    _run(wd, "results/test/meshes/brick.h5", *TEST, "mine.yaml", "--config", f"mesh_dir={mesh_dir}")
    with h5py.File(wd / "results/test/meshes/brick.h5") as f:
        assert f.attrs["raw_sha256"] == hashlib.sha256((wd / "my/brick.obj").read_bytes()).hexdigest()
        assert f.attrs["source"] == "brick.obj"
    assert not (wd / "resources/meshes/brick.obj").exists()  # nothing fetched
    out = _run(wd, "-n", "results/test/runs/iso_brick.h5", *TEST, "mine.yaml", "--config", f"mesh_dir={mesh_dir}")
    assert planned_jobs(out) == {"rasterize_target": 1, "morph": 1}  # from the prepared brick (the iso's particles exist)


def test_export_writes_every_file_of_each_full_run(test_run):
    """`snakemake export` on the test profile: for each full run an MP4 of K + 1 frames (and a
    WebM), a watertight final mesh within 5 % of the particles' volume at that frame (sum V_p det F,
    recomputed here from the run and particle files), splat files whose covariances rebuild
    sigma0^2 F F^T within 1e-5, and the viewer; then an edited video setting replans only the
    video and viewer jobs. Slow: `snakemake export` runs the video (13 frames into an MP4 and a
    WebM), splat and viewer jobs, each its own process, then a dry run."""
    import imageio_ffmpeg
    import trimesh

    from physmorph.reports.export.splats import read_splat_covariances

    wd, mesh_dir = test_run
    args = (*TEST, "--config", f"mesh_dir={mesh_dir}")
    _run(wd, "export", *args)
    r = wd / "results/test"
    with h5py.File(r / "runs/iso_bunny_full.h5") as f:
        frames = int(f.attrs["frames_completed"])
        sigma0 = float(f.attrs["sigma0"])
        saved = sorted(int(k.removeprefix("frame_")) for k in f["states"])
        F_last = f[f"states/frame_{saved[-1]:04d}/F"][()].astype(np.float64)
        F_by_frame = {k: f[f"states/frame_{k:04d}/F"][()].astype(np.float64) for k in saved}
    with h5py.File(r / "particles/iso_32x1x1.h5") as p:
        volume = p["volume"][()].astype(np.float64)
    assert imageio_ffmpeg.count_frames_and_secs(str(r / "videos/iso_bunny_full.mp4"))[0] == frames + 1
    assert imageio_ffmpeg.count_frames_and_secs(str(r / "videos/iso_bunny_full.webm"))[0] == frames + 1
    final = trimesh.load(r / "meshes/iso_bunny_full/final.glb", force="mesh")
    assert final.is_watertight
    body = float((volume * np.linalg.det(F_last)).sum())
    assert abs(final.volume - body) <= 0.05 * body, (final.volume, body)
    for k in saved:
        assert trimesh.load(r / f"meshes/iso_bunny_full/frame_{k:04d}.ply").is_watertight
        cov = read_splat_covariances(r / f"splats/iso_bunny_full/frame_{k:04d}.ply")
        want = sigma0 ** 2 * np.einsum("nij,nkj->nik", F_by_frame[k], F_by_frame[k])
        err = np.linalg.norm(cov - want, axis=(1, 2)) / np.linalg.norm(want, axis=(1, 2))
        assert err.max() <= 1e-5, err.max()
    measures = pd.read_csv(r / "meshes/iso_bunny_full/measures.csv")
    assert list(measures["frame"]) == saved and measures["closed"].all()
    conv = pd.read_csv(r / "tables/convergence.csv").set_index("experiment")
    assert conv.loc["iso_bunny_full", "stray_%"] == pytest.approx(100 * measures["stray_share"].iloc[-1])
    assert np.isnan(conv.loc["iso_bunny_physics_only", "stray_%"])
    html = (r / "viewer/index.html").read_text()
    assert "iso_bunny_full" in html and "../videos/iso_bunny_full.mp4" in html
    assert planned_jobs(_run(wd, "-n", "export", *TEST, "--config", f"mesh_dir={mesh_dir}", "export={fps: 12}")) == \
        {"export_video": 1, "export_viewer": 1, "export_viewer_run": 1, "export": 1}


def _stored_params(wd: Path) -> dict[str, tuple[str, list]]:
    """output -> (rule, params) of every job Snakemake recorded in ``wd`` (.snakemake/metadata:
    one JSON file per output, its name the output path in base64)."""
    import base64
    import json

    out = {}
    for f in (wd / ".snakemake" / "metadata").iterdir():
        path = base64.b64decode(f.name.replace("_", "/") + "==").decode()
        record = json.loads(f.read_text())
        out[path] = (record["rule"], record["params"])
    return out


def test_data_and_morph_jobs_keep_the_params_recorded_before_the_core_was_restructured(test_run):
    """An unchanged config reruns no data or morph job: the params Snakemake compares are those a
    run of the test profile stored with the code before the core's restructuring
    (tests/data/test_profile_params.json), byte for byte; a default changed on purpose since then
    is re-recorded there (its defaults_changed_since says which)."""
    import json

    wd, _ = test_run
    recorded = json.loads((REPO / "tests/data/test_profile_params.json").read_text())["jobs"]
    stored = _stored_params(wd)
    compared = {path for path in recorded if path.startswith("results/test/")}
    rules = {recorded[p]["rule"] for p in compared}
    assert {"prepare_mesh", "sample_particles", "rasterize_target", "morph"} <= rules
    assert compared <= set(stored), sorted(compared - set(stored))
    for path in sorted(compared):
        assert stored[path] == (recorded[path]["rule"], recorded[path]["params"]), path
