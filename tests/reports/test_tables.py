"""Tables from run files (physmorph.reports.tables), on small hand-made run files.

A run file as build_tables reads it (physmorph.records.runfile.read_metrics): per-frame metrics in group
/metrics (index 0 = initial state) and the run's attributes (method, ceiling_alpha_mse, ...).
"""

import json
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pytest

from physmorph.reports.metrics import TABLE_NAMES
from physmorph.reports.layout import load_layout
from physmorph.morph.quality import GAP_REL_TOL
from physmorph.reports.tables import BODY_COLUMNS, build_tables

LAYOUT = load_layout(Path(__file__).resolve().parents[2] / "config" / "paper_results.yaml")


def write_run(path, alpha_mse, attrs, iou=None, volume_iou=None, overfilled_mass=None):
    """A minimal run file: the metrics every table reads, plus ``iou``, ``volume_iou`` and
    ``overfilled_mass`` when given (older run files carry only alpha MSE and the ceiling attributes)."""
    a = np.asarray(alpha_mse, dtype=float)
    n = len(a)
    with h5py.File(path, "w") as f:
        g = f.create_group("metrics")
        g["alpha_mse"] = a
        g["physics_loss"] = np.linspace(1.0, 0.1, n)
        g["physics_loss_initial"] = np.linspace(1.0, 0.2, n)
        g["total_volume"] = np.full(n, 100.0)
        g["fp_det_min"] = np.ones(n)
        g["fp_det_max"] = np.ones(n)
        for key in ("t_physics", "t_render", "t_plasticity", "t_mask", "t_frame"):
            g[key] = np.full(n, 0.5)
        if iou is not None:
            g["iou"] = np.asarray(iou, dtype=float)
        if volume_iou is not None:
            g["volume_iou"] = np.asarray(volume_iou, dtype=float)
        if overfilled_mass is not None:
            g["overfilled_mass"] = np.asarray(overfilled_mass, dtype=float)
        f.attrs.update({"status": "complete", "n_particles": 100, "peak_rss_mb": 10.0, **attrs})
    return path


@pytest.fixture
def runs(tmp_path):
    # iso -> bunny full: best at frame 2 (0.02), final 0.03, ceiling 0.01:
    # closed (0.06 - 0.02) / (0.06 - 0.01) = 80 % at best, (0.06 - 0.03) / 0.05 = 60 % at the end.
    full = write_run(tmp_path / "iso_bunny_full.h5", [0.06, 0.04, 0.02, 0.03],
                     {"method": "full", "ceiling_alpha_mse": 0.01, "ceiling_iou": 0.95}, iou=[0.5, 0.7, 0.9, 0.8],
                     volume_iou=[0.55, 0.7, 0.85, 0.82], overfilled_mass=[0.0, 0.3, 0.1, 0.05])
    # An older-style run (no iou): best at frame 1 (0.03), final 0.045, ceiling 0.02:
    # closed 0.02 / 0.03 = 66.7 % at best, 0.005 / 0.03 = 16.7 % at the end.
    cross = write_run(tmp_path / "duck_cow_full.h5", [0.05, 0.03, 0.045],
                      {"method": "full", "ceiling_alpha_mse": 0.02, "ceiling_iou": 0.9})
    return {"iso_bunny_full": full, "duck_cow_full": cross, "iso_cow_full": tmp_path / "not_run.h5"}


def test_convergence_table_reports_the_share_of_the_reachable_gap(runs, tmp_path):
    out = tmp_path / "tables"
    tables = build_tables(runs, out, LAYOUT)
    assert "convergence" in TABLE_NAMES and set(tables) == set(TABLE_NAMES)
    conv = pd.read_csv(out / "convergence.csv").set_index("experiment")
    assert list(conv.index) == ["iso_bunny_full", "duck_cow_full"]  # only the runs that were made
    bunny, cross = conv.loc["iso_bunny_full"], conv.loc["duck_cow_full"]
    assert bunny["method"] == "full" and bunny["frames"] == 3
    assert bunny["alpha_mse_0"] == pytest.approx(0.06) and bunny["alpha_mse_best"] == pytest.approx(0.02)
    assert bunny["best_frame"] == 2 and bunny["alpha_mse_final"] == pytest.approx(0.03)
    assert bunny["ceiling"] == pytest.approx(0.01)
    assert bunny["closed_best_%"] == pytest.approx(80.0) and bunny["closed_final_%"] == pytest.approx(60.0)
    assert (bunny["iou_0"], bunny["iou_best"], bunny["iou_final"], bunny["ceiling_iou"]) == pytest.approx((0.5, 0.9, 0.8, 0.95))
    assert (bunny["volume_iou_0"], bunny["volume_iou_final"], bunny["overfilled_mass_final"]) == pytest.approx((0.55, 0.82, 0.05))
    # written before the 3D checks existed
    assert np.isnan(cross["volume_iou_0"]) and np.isnan(cross["volume_iou_final"]) and np.isnan(cross["overfilled_mass_final"])
    assert bunny["paper_alpha_mse"] == pytest.approx(0.0546)  # the paper's best (drag ablation)
    assert cross["best_frame"] == 1
    assert cross["closed_best_%"] == pytest.approx(200 / 3) and cross["closed_final_%"] == pytest.approx(50 / 3)
    assert np.isnan(cross["iou_0"]) and np.isnan(cross["iou_best"]) and np.isnan(cross["paper_alpha_mse"])
    md = (out / "convergence.md").read_text().splitlines()
    assert md[0].startswith("| experiment") and "closed_best_%" in md[0] and len(md) == 4
    tex = (out / "convergence.tex").read_text()
    assert "\\begin{tabular}" in tex and "closed\\_best\\_\\%" in tex and "iso\\_bunny\\_full" in tex
    # The source-invariance table gives the same shares for the runs it lists.
    src = pd.read_csv(out / "source_invariance.csv").set_index("experiment")
    assert src.loc["iso_bunny_full", "closed_best_%"] == pytest.approx(80.0)
    assert src.loc["iso_bunny_full", "closed_final_%"] == pytest.approx(60.0)
    assert np.isnan(src.loc["cow_bunny_full", "closed_best_%"])


def test_share_closed_is_bounded_when_the_source_starts_at_the_ceiling(tmp_path):
    """A run whose source already renders at the ceiling: finite shares, 100 % if it stays. The
    start is raised to a0' = ceiling + tol, tol = GAP_REL_TOL x ceiling (physmorph.morph.quality), so
    the share is (a0' - a) / tol: 100 % at a = ceiling, and at a = 1.2 ceiling
    100 (1.1 - 1.2) / 0.1 = -100 % (with GAP_REL_TOL = 0.1)."""
    c = 0.01
    run = write_run(tmp_path / "bunny_bunny_full.h5", [c, c, c * 1.2],
                    {"method": "full", "ceiling_alpha_mse": c, "ceiling_iou": 0.9})
    conv = build_tables({"bunny_bunny_full": run}, tmp_path / "tables", LAYOUT)["convergence"].iloc[0]
    start = c + GAP_REL_TOL * c  # a0' = max(a0, ceiling + tol), a0 = c
    assert conv["closed_best_%"] == pytest.approx(100.0, abs=1e-6)
    assert conv["closed_final_%"] == pytest.approx(100.0 * (start - 1.2 * c) / (start - c), abs=1e-6)


def test_run_without_ceiling_names_the_file(tmp_path):
    run = write_run(tmp_path / "iso_duck_full.h5", [0.05, 0.03], {"method": "full"})
    with pytest.raises(ValueError, match=r"iso_duck_full\.h5.*ceiling_alpha_mse.*rerun the rasterize_target"):
        build_tables({"iso_duck_full": run}, tmp_path / "tables", LAYOUT)


def test_directions_table_states_each_paper_direction_from_the_runs(tmp_path):
    """Lower is better in every row; 'holds' when the paper's choice (ours) is below its baseline.
    Hand-made curves: physics-only reaches 90 % of its improvement at frame 2 (0.02), where full
    is at 0.018 (+10 %); F-injection ends at 0.025 against position injection's 0.022 (-13.6 %);
    in-run rebound 100 (0.019 - 0.018) / 0.042 = 2.38 % vs 100 (0.025 - 0.02) / 0.04 = 12.5 %;
    released, 100 (0.02 - 0.019) / 0.041 = 2.44 % vs 100 (0.05 - 0.025) / 0.035 = 71.4 %."""
    ceiling = {"ceiling_alpha_mse": 0.01, "ceiling_iou": 0.9}
    runs = {
        "iso_bunny_physics_only": write_run(tmp_path / "po.h5", [0.06, 0.03, 0.02, 0.02],
                                            {"method": "physics_only", **ceiling}),
        "iso_bunny_full": write_run(tmp_path / "full.h5", [0.06, 0.03, 0.018, 0.019],
                                    {"method": "full", "release_alpha_mse": "[0.019, 0.02]", **ceiling}),
        "iso_bunny_f_inject": write_run(tmp_path / "fi.h5", [0.06, 0.03, 0.02, 0.025],
                                        {"method": "f_inject", "release_alpha_mse": "[0.025, 0.05]", **ceiling}),
        "iso_bunny_position_inject": write_run(tmp_path / "xi.h5", [0.06, 0.03, 0.02, 0.022],
                                               {"method": "position_inject", **ceiling}),
    }
    out = tmp_path / "tables"
    d = build_tables(runs, out, LAYOUT)["directions"]
    assert "directions" in TABLE_NAMES
    main = d[d["direction"].str.startswith("full beats")].set_index("case")
    assert list(main.index) == ["bunny", "cow", "duck"]
    assert main.loc["bunny", "ours"] == pytest.approx(0.018) and main.loc["bunny", "baseline"] == pytest.approx(0.02)
    assert main.loc["bunny", "ours_vs_baseline_%"] == pytest.approx(10.0) and main.loc["bunny", "holds"] == "yes"
    assert "frame 2" in main.loc["bunny", "measure"] and main.loc["bunny", "paper"] == "+25.8 %"
    assert main.loc["cow", "holds"] == "" and np.isnan(main.loc["cow", "ours"])  # not run
    inj = d[d["direction"].str.startswith("F-injection")].iloc[0]
    assert (inj["ours"], inj["baseline"]) == pytest.approx((0.025, 0.022))
    assert inj["ours_vs_baseline_%"] == pytest.approx(100 * (0.022 - 0.025) / 0.022) and inj["holds"] == "no"
    reb = d[d["direction"] == "plasticity lowers rebound"].set_index("measure")
    assert len(reb) == 2 and (reb["holds"] == "yes").all()
    in_run = reb.loc["rebound % after the best frame"]
    assert (in_run["ours"], in_run["baseline"]) == pytest.approx((100 / 42, 12.5))
    released = reb.loc["release rebound % (control off)"]
    assert (released["ours"], released["baseline"]) == pytest.approx((100 / 41, 2500 / 35))
    md = (out / "directions.md").read_text()
    assert md.startswith("| direction | case |") and "F-injection beats position injection" in md
    assert d["noise"].isna().all()  # no noise pair: holds says only which is lower


def test_directions_hold_only_where_the_margin_exceeds_the_noise(tmp_path):
    """With tables.noise (iso -> bunny full from a second particle sample), each row's noise is
    its measure's spread between the two runs: at the matched frame 2 |0.018 - 0.0195| = 0.0015
    against a margin 0.02 - 0.018 = 0.002 (holds); final alpha MSE |0.019 - 0.0185| = 0.0005 against
    F-injection's margin 0.022 - 0.025 = -0.003 (does not hold); in-run rebound
    |100 / 42 - 100 (0.0185 - 0.0185) / 0.0415| = 2.38 points against 12.5 - 2.38 = 10.1 (holds).
    The same runs with a second sample far off the first make the bunny row 'within noise'."""
    ceiling = {"ceiling_alpha_mse": 0.01, "ceiling_iou": 0.9}
    runs = {
        "iso_bunny_physics_only": write_run(tmp_path / "po.h5", [0.06, 0.03, 0.02, 0.02],
                                            {"method": "physics_only", **ceiling}),
        "iso_bunny_full": write_run(tmp_path / "full.h5", [0.06, 0.03, 0.018, 0.019], {"method": "full", **ceiling}),
        "isob_bunny_full": write_run(tmp_path / "fullb.h5", [0.06, 0.03, 0.0195, 0.0185], {"method": "full", **ceiling}),
        "iso_bunny_f_inject": write_run(tmp_path / "fi.h5", [0.06, 0.03, 0.02, 0.025], {"method": "f_inject", **ceiling}),
        "iso_bunny_position_inject": write_run(tmp_path / "xi.h5", [0.06, 0.03, 0.02, 0.022],
                                               {"method": "position_inject", **ceiling}),
    }
    d = build_tables(runs, tmp_path / "tables", LAYOUT, noise=("iso_bunny_full", "isob_bunny_full"))["directions"]
    bunny = d[d["direction"].str.startswith("full beats")].set_index("case").loc["bunny"]
    assert bunny["margin"] == pytest.approx(0.002) and bunny["noise"] == pytest.approx(0.0015)
    assert bunny["holds"] == "yes"
    inj = d[d["direction"].str.startswith("F-injection")].iloc[0]
    assert inj["margin"] == pytest.approx(-0.003) and inj["noise"] == pytest.approx(0.0005) and inj["holds"] == "no"
    reb = d[d["direction"] == "plasticity lowers rebound"].set_index("measure").loc["rebound % after the best frame"]
    assert reb["noise"] == pytest.approx(100 / 42) and reb["margin"] == pytest.approx(12.5 - 100 / 42)
    assert reb["holds"] == "yes"
    runs["isob_bunny_full"] = write_run(tmp_path / "fullc.h5", [0.06, 0.03, 0.0225, 0.02], {"method": "full", **ceiling})
    d = build_tables(runs, tmp_path / "tables2", LAYOUT, noise=("iso_bunny_full", "isob_bunny_full"))["directions"]
    bunny = d[d["direction"].str.startswith("full beats")].set_index("case").loc["bunny"]
    assert bunny["noise"] == pytest.approx(0.0045) and bunny["holds"] == "within noise"


# ------------------------------------------------------------------ every table's values from its run files
def _fake_run(path, rng, frames, attrs, nan_frame=None):
    """A run file with random per-frame metrics (a noisy falling alpha MSE, physics losses, volume,
    frame times with a slow frame 0, as the compiling first frame is) and ``attrs``; the table tests
    recompute each cell from what is stored here."""
    n = frames + 1
    a = 0.06 * np.exp(-np.linspace(0.0, 1.5, n)) * (1.0 + 0.15 * rng.random(n))
    if nan_frame is not None:
        a[nan_frame] = np.nan  # a frame whose metric is missing: the best value skips it
    with h5py.File(path, "w") as f:
        g = f.create_group("metrics")
        g["alpha_mse"] = a
        g["physics_loss"] = rng.uniform(0.05, 1.0, n)
        g["physics_loss_initial"] = rng.uniform(1.0, 3.0, n)
        g["total_volume"] = 100.0 * (1.0 + 0.1 * rng.normal(size=n))
        g["fp_det_min"] = np.ones(n)
        g["fp_det_max"] = np.ones(n)
        for key in ("t_physics", "t_render", "t_plasticity", "t_mask", "t_frame"):
            t = rng.uniform(0.1, 2.0, n)
            t[0] = 100.0  # frame 0: the timing table leaves it out
            g[key] = t
        f.attrs.update({"status": "complete", "n_particles": int(rng.integers(100, 5000)),
                        "peak_rss_mb": float(rng.uniform(100, 900)), "ceiling_alpha_mse": 0.005,
                        "ceiling_iou": 0.9, **attrs})
    return path


def _stored(path) -> dict:
    """A fake run's metrics and attributes as stored (h5py, not the tables' loader)."""
    with h5py.File(path, "r") as f:
        out = {k: np.array(f["metrics"][k]) for k in f["metrics"]}
        out["attrs"] = dict(f.attrs)
    return out


@pytest.fixture(scope="module")
def every_table(tmp_path_factory):
    """Fake runs for every table (cow's main pair, two shapes and the d=0.5 physics-only run left
    out) and the tables build_tables makes of them; duck's full run stops 3 frames before its
    physics-only run (the matched frame can lie past it), the drag ablation's full run misses a frame."""
    d = tmp_path_factory.mktemp("every_table")
    rng = np.random.default_rng(2026)
    frames = {"iso_bunny_physics_only": 12, "iso_bunny_full": 12, "iso_duck_physics_only": 12, "iso_duck_full": 3,
              "iso_bunny_f_inject_d05": 10, "iso_bunny_full_d05": 10, "iso_bunny_f_inject": 12, "duck_cow_full": 8,
              "iso_A_full": 6, "cow_S_full": 5}
    runs = {}
    for name, k in frames.items():
        attrs = {"method": name.split("_", 2)[2].removesuffix("_d05")}
        if name in ("iso_bunny_full", "iso_bunny_f_inject"):
            attrs["release_alpha_mse"] = json.dumps(list(0.02 + 0.01 * rng.random(int(rng.integers(2, 6)))))
        runs[name] = _fake_run(d / f"{name}.h5", rng, k, attrs, nan_frame=4 if name == "iso_bunny_full_d05" else None)
    runs["iso_bunny_physics_only_d05"] = d / "not_run.h5"
    tables = build_tables(runs, d / "tables", LAYOUT)
    return tables, {name: _stored(p) for name, p in runs.items() if p.exists()}


def _matched_frame(baseline) -> int:
    """The first frame where the curve has made 90 % of its total improvement a0 - min a (paper Table 1)."""
    a0, best = baseline[0], min(baseline)
    for k, v in enumerate(baseline):
        if a0 - v >= 0.9 * (a0 - best):
            return k
    raise AssertionError("unreachable")


def test_main_table_values_are_the_runs_at_the_matched_frame(every_table):
    """main: physics-only and full alpha MSE at the frame where physics-only first made 90 % of its
    improvement (the full run's last frame where it is shorter), and 100 (po - full) / po."""
    tables, m = every_table
    main = tables["main"].set_index("target")
    assert list(main.index) == ["bunny", "cow", "duck"]
    clamped = False
    for target in ("bunny", "duck"):
        po, full = m[f"iso_{target}_physics_only"]["alpha_mse"], m[f"iso_{target}_full"]["alpha_mse"]
        k = _matched_frame(list(po))
        if k > len(full) - 1:
            k, clamped = len(full) - 1, True
        row = main.loc[target]
        assert row["frame"] == k
        assert row["physics_only"] == pytest.approx(po[k], rel=1e-12)
        assert row["ours"] == pytest.approx(full[k], rel=1e-12)
        assert row["improvement_%"] == pytest.approx(100.0 * (po[k] - full[k]) / po[k], rel=1e-12)
    assert clamped  # the duck's short full run puts the matched frame past its end
    assert main.loc["bunny", "paper_physics_only"] == 0.0799 and main.loc["bunny", "paper_improvement_%"] == 25.8
    assert np.isnan(main.loc["cow", "physics_only"]) and np.isnan(main.loc["cow", "ours"])  # not run


def test_ablation_tables_values_are_the_runs_final_and_best(every_table):
    """ablation_components: final alpha MSE and Delta E % = 100 (E0 - E_K) / E0 with E0 the physics
    loss before frame 1's optimisation and E_K the last frame's; ablation_drag: the best (NaN frames
    skipped) and the final alpha MSE."""
    tables, m = every_table
    comp = tables["ablation_components"].set_index("experiment")
    assert list(comp.index) == ["iso_bunny_physics_only_d05", "iso_bunny_f_inject_d05", "iso_bunny_full_d05"]
    for name in ("iso_bunny_f_inject_d05", "iso_bunny_full_d05"):
        r = m[name]
        e0, ek = r["physics_loss_initial"][1], r["physics_loss"][-1]
        assert comp.loc[name, "alpha_mse"] == pytest.approx(r["alpha_mse"][-1], rel=1e-12)
        assert comp.loc[name, "delta_E_%"] == pytest.approx(100.0 * (e0 - ek) / e0, rel=1e-12)
    assert comp.loc["iso_bunny_full_d05", "paper_alpha_mse"] == 0.1040
    assert np.isnan(comp.loc["iso_bunny_physics_only_d05", "alpha_mse"])  # not run
    drag = tables["ablation_drag"].set_index("experiment")
    assert list(drag.index) == ["iso_bunny_physics_only", "iso_bunny_full_d05", "iso_bunny_full"]
    for name in drag.index:
        a = m[name]["alpha_mse"]
        assert drag.loc[name, "best"] == pytest.approx(min(v for v in a if np.isfinite(v)), rel=1e-12)
        assert drag.loc[name, "final"] == pytest.approx(a[-1], rel=1e-12)
    assert np.isnan(m["iso_bunny_full_d05"]["alpha_mse"][4])  # the best skipped it


def test_plasticity_table_values_are_the_runs_rebound(every_table):
    """plasticity: best, final, rebound % = 100 (a_K - min a) / (a_0 - min a), and for a released
    run its release frames, last release alpha MSE and 100 (release_last - a_K) / (a_0 - a_K)."""
    tables, m = every_table
    plast = tables["plasticity"]
    assert list(plast["experiment"]) == ["iso_bunny_full", "iso_bunny_f_inject"]
    assert list(plast["variant"]) == ["with plasticity", "without plasticity"]
    for _, row in plast.iterrows():
        r = m[row["experiment"]]
        a = r["alpha_mse"]
        best = a.min()
        release = json.loads(r["attrs"]["release_alpha_mse"])
        assert row["best"] == pytest.approx(best, rel=1e-12) and row["final"] == pytest.approx(a[-1], rel=1e-12)
        assert row["rebound_%"] == pytest.approx(100.0 * (a[-1] - best) / (a[0] - best), rel=1e-12)
        assert row["release_frames"] == len(release) - 1
        assert row["release_final"] == pytest.approx(release[-1], rel=1e-12)
        assert row["release_rebound_%"] == pytest.approx(100.0 * (release[-1] - a[-1]) / (a[0] - a[-1]), rel=1e-12)
    assert plast["paper_rebound_%"].iloc[0] == "< 8"


def test_shapes_table_values_are_the_runs_best_final_and_volume_change(every_table):
    """shapes: best and final alpha MSE and the volume change 100 (V_K - V_0) / V_0."""
    tables, m = every_table
    shapes = tables["shapes"].set_index("experiment")
    assert list(shapes.index) == list(LAYOUT.tables.shapes)
    for name in ("duck_cow_full", "iso_A_full", "cow_S_full"):
        r = m[name]
        v = r["total_volume"]
        assert shapes.loc[name, "best"] == pytest.approx(r["alpha_mse"].min(), rel=1e-12)
        assert shapes.loc[name, "final"] == pytest.approx(r["alpha_mse"][-1], rel=1e-12)
        assert shapes.loc[name, "volume_change_%"] == pytest.approx(100.0 * (v[-1] - v[0]) / v[0], rel=1e-12)
    assert np.isnan(shapes.loc["cow_bunny_full", "best"])  # not run


def test_timing_table_values_are_the_runs_mean_frame_times_after_frame_0(every_table):
    """timing: one row per run, by name: frames, status, the mean of each per-frame time over
    frames 1.. (frame 0, which compiles, left out), peak RSS and particle count from the attributes."""
    tables, m = every_table
    timing = tables["timing"]
    assert list(timing["experiment"]) == sorted(m)
    for _, row in timing.iterrows():
        r = m[row["experiment"]]
        assert row["frames"] == len(r["alpha_mse"]) - 1 and row["status"] == "complete"
        for col, key in (("physics_s", "t_physics"), ("render_s", "t_render"), ("plasticity_s", "t_plasticity"),
                         ("mask_s", "t_mask"), ("frame_s", "t_frame")):
            after = r[key][1:]
            assert row[col] == pytest.approx(sum(after) / len(after), rel=1e-12), col
            assert row[col] < 2.0  # frame 0's 100 s is not in the mean
        assert row["peak_rss_mb"] == pytest.approx(r["attrs"]["peak_rss_mb"], rel=1e-12)
        assert row["particles"] == r["attrs"]["n_particles"]


def test_the_convergence_table_shows_the_last_exported_bodys_measures(tmp_path):
    """The last row of a run's measures.csv (physmorph.reports.export.measures) fills the body
    columns (shares in %); a measures.csv written before a measure existed leaves that one NaN, and
    a run not exported leaves them all NaN."""
    c = 0.01
    runs = {name: write_run(tmp_path / f"{name}.h5", [0.05, 0.02, c * 1.1],
                            {"method": "full", "ceiling_alpha_mse": c, "ceiling_iou": 0.9})
            for name in ("iso_bunny_full", "cow_S_full", "iso_duck_full")}
    new = tmp_path / "new.csv"
    pd.DataFrame([{"frame": 0, "stray_share": 0.5, "surface_distance_dx": 3.0, "closed": True, "faces": 10,
                   "outside_largest_body": 0.3, "components": 2, "genus": 2, "target_genus": 0,
                   "surface_p95_dx": 9.0, "roughness_percent": 7.0},
                  {"frame": 2, "stray_share": 0.012, "surface_distance_dx": 0.7, "closed": True, "faces": 10,
                   "outside_largest_body": 0.004, "components": 1, "genus": 1, "target_genus": 0,
                   "surface_p95_dx": 2.5, "roughness_percent": 4.0}]).to_csv(new, index=False)
    old = tmp_path / "old.csv"
    pd.DataFrame([{"frame": 2, "stray_share": 0.02, "surface_distance_dx": 0.9, "closed": True,
                   "faces": 10}]).to_csv(old, index=False)
    conv = build_tables(runs, tmp_path / "tables", LAYOUT, measures={"iso_bunny_full": new, "cow_S_full": old}
                        )["convergence"].set_index("experiment")
    row = conv.loc["iso_bunny_full"]
    assert (row["stray_%"], row["surface_dx"], row["surface_p95_dx"]) == pytest.approx((1.2, 0.7, 2.5))
    assert (row["outside_body_%"], row["components"], row["genus"], row["target_genus"], row["rough_%"]) == \
        pytest.approx((0.4, 1, 1, 0, 4.0))
    assert conv.loc["cow_S_full", "stray_%"] == pytest.approx(2.0)
    assert np.isnan(conv.loc["cow_S_full", ["surface_p95_dx", "genus", "rough_%"]].astype(float)).all()
    assert np.isnan(conv.loc["iso_duck_full", list(BODY_COLUMNS)].astype(float)).all()
