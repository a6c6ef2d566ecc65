"""Speed/accuracy study: points, time to quality, Pareto front, knob ranking on hand-made numbers."""

import numpy as np
import pytest

from physmorph.settings.errors import ConfigError
from physmorph.settings.workflow import load_settings
from physmorph.studies.tradeoff import GAP_TOLERANCE, knob_ranking, pareto_front, point_row, recommendations, summarize_points, time_to_quality
from physmorph.settings.study_points import tradeoff_points

FIELDS = ("grid_res", "ppc_surface", "ppc_interior", "width", "cameras", "grad_iters", "learning_rate", "frames",
          "precision", "threads")


def test_pareto_front_hand_made():
    t = np.array([1.0, 2.0, 3.0, 2.5, 4.0])
    e = np.array([0.10, 0.08, 0.05, 0.09, 0.05])
    assert pareto_front(t, e).tolist() == [True, True, True, False, False]


def test_points_change_one_knob_each():
    cfg = load_settings("config/config.yaml")
    pts = tradeoff_points(cfg)
    base = pts["base"]
    assert base.res_tag == "32x2x1" and base.image_tag == "160x90"
    assert (base.frames, base.learning_rate, base.precision, base.threads) == (40, 0.004, "float32", 2)
    for name, p in pts.items():
        if name == "base":
            continue
        changed = [k for k in FIELDS if getattr(p, k) != getattr(base, k)]
        assert changed == [{"image": "width"}.get(p.knob, p.knob)], name
    assert {"grid_res-48", "cameras-2", "image-320x180", "learning_rate-0.008", "frames-60", "precision-float64",
            "threads-1", "ppc_interior-2"} <= set(pts)


def test_the_workflow_threads_leave_the_study_alone():
    """`threads` changes no result, so it must neither add nor drop a point (a threads knob value that
    equals the base) nor change a point's threads: the base's are `tradeoff.threads`."""
    from physmorph.settings.workflow import Settings
    from physmorph.settings.build import deep_merge
    from physmorph.settings.build import load_mapping

    m = load_mapping("config/config.yaml")
    pts = {t: tradeoff_points(Settings.from_mapping(deep_merge(m, {"threads": t}))) for t in (1, 2, 4)}
    assert pts[1] == pts[2] == pts[4]
    moved = tradeoff_points(Settings.from_mapping(deep_merge(m, {"tradeoff": {"threads": 1}})))
    assert moved["base"].threads == 1 and "threads-1" not in moved


def test_point_settings_carry_the_knob():
    s = load_settings("config/config.yaml")
    pts = tradeoff_points(s)
    assert s.point_config(pts["learning_rate-0.008"])[2].mpm.learning_rate == 0.008
    assert s.point_config(pts["precision-float64"])[2].mpm.precision == "float64"
    assert s.point_config(pts["frames-60"])[2].frames == 60
    # the study's experiment has a release probe; its points do not run it (nothing reads it)
    assert s.experiment_config(s.tradeoff.experiment).release_frames == 40
    assert {s.point_config(p)[2].release_frames for p in pts.values()} == {0}
    sampling, _, _ = s.point_config(pts["ppc_interior-2"])
    assert sampling.tag == "32x2x2"
    # float64 doubles the per-particle state: its memory estimate is the larger one
    est = {e.stage: e.mb for e in s.memory_estimates()}
    assert est["tradeoff point precision-float64"] > est["tradeoff point base"]


def test_bad_knobs_are_named():
    with pytest.raises(ConfigError, match="tradeoff.knobs.shininess") as refused:
        load_settings("config/config.yaml", overrides={"tradeoff": {"knobs": {"shininess": [1]}}})
    assert refused.value.key == "tradeoff.knobs.shininess"  # as data, not only in the message
    with pytest.raises(ConfigError) as refused:
        load_settings("config/config.yaml", overrides={"tradeoff": {"knobs": {"cameras": [1, 99]}}})
    assert refused.value.key == "tradeoff.knobs.cameras" and "exceeds target.cameras" in refused.value.reason
    with pytest.raises(ConfigError, match=r"tradeoff.knobs.image\[0\]'.*\[width, height\]"):
        load_settings("config/config.yaml", overrides={"tradeoff": {"knobs": {"image": [320]}}})
    with pytest.raises(ConfigError, match=r"tradeoff.knobs.precision\[0\]'.*float32 or float64"):
        load_settings("config/config.yaml", overrides={"tradeoff": {"knobs": {"precision": ["half"]}}})
    with pytest.raises(ConfigError, match=r"tradeoff.knobs.learning_rate\[1\]'.*positive"):
        load_settings("config/config.yaml", overrides={"tradeoff": {"knobs": {"learning_rate": [0.001, -1]}}})
    with pytest.raises(ConfigError, match=r"tradeoff.knobs.frames\[0\]'.*positive integer"):
        load_settings("config/config.yaml", overrides={"tradeoff": {"knobs": {"frames": [2.5]}}})


def test_time_to_quality_sums_frame_times_to_the_first_frame_past_the_bar():
    gap = np.array([0.0, 0.5, 0.85, 0.92, 0.88, 0.95])
    t = np.array([np.nan, 2.0, 3.0, 4.0, 5.0, 6.0])
    assert time_to_quality(gap, t) == pytest.approx(9.0)  # frames 1-3
    assert time_to_quality(gap, t, quality=0.94) == pytest.approx(20.0)
    assert np.isnan(time_to_quality(gap, t, quality=0.99))


def test_point_row_reads_the_last_frame_and_cells():
    from physmorph.settings.study_points import TradeoffPoint

    p = TradeoffPoint("grid_res-16", "grid_res", "16", 16, 2, 1, 160, 90, 8, 1, 0.004, 3, "float32", 2)
    m = {"gap_closed": np.array([0.0, 0.6, 0.95, 0.93]), "t_frame": np.array([np.nan, 1.0, 1.0, 2.0]),
         "volume_iou": np.array([0.5, 0.7, 0.9, 0.91]), "chamfer": np.array([3.0, 2.0, 1.2, 1.0]),
         "attrs": {"n_particles": 1000, "peak_rss_mb": 600.0}}
    r = point_row("grid_res-16", p, m, dx=2.0)
    assert r["time_to_90_s"] == pytest.approx(2.0) and r["time_s"] == pytest.approx(4.0)
    assert (r["gap_last"], r["gap_best"], r["volume_iou_last"]) == (0.93, 0.95, 0.91)
    assert r["chamfer_last_dx"] == pytest.approx(0.5)


def _rows():
    return [
        {"name": "base", "knob": "", "value": "", "gap_last": 0.90, "time_s": 10.0, "time_to_90_s": 8.0,
         "volume_iou_last": 0.9},
        {"name": "grid_res-48", "knob": "grid_res", "value": "48", "gap_last": 0.92, "time_s": 30.0,
         "time_to_90_s": 20.0, "volume_iou_last": 0.93},
        {"name": "cameras-4", "knob": "cameras", "value": "4", "gap_last": 0.89, "time_s": 8.0,
         "time_to_90_s": np.nan, "volume_iou_last": 0.9},
        {"name": "grad_iters-2", "knob": "grad_iters", "value": "2", "gap_last": 0.93, "time_s": 15.0,
         "time_to_90_s": 9.0, "volume_iou_last": 0.92},
        {"name": "image-80x45", "knob": "image", "value": "80x45", "gap_last": 0.91, "time_s": 9.0,
         "time_to_90_s": 6.0, "volume_iou_last": 0.9},
    ]


def test_summary_ranks_by_time_to_quality_and_marks_the_front():
    df = summarize_points(_rows())
    assert df["name"].tolist() == ["image-80x45", "base", "grad_iters-2", "grid_res-48", "cameras-4"]  # never: last
    front = set(df[df["pareto"]]["name"])
    assert front == {"cameras-4", "image-80x45", "grad_iters-2"}
    per_s = df.set_index("name")["gap_gain_per_s"]
    assert per_s["grid_res-48"] == pytest.approx(0.02 / 20)
    # faster and better: nothing to divide by; faster and worse: bought nothing (not -0.01 / -2 s)
    assert per_s["image-80x45"] == np.inf and np.isnan(per_s["cameras-4"]) and per_s["base"] == 0.0


def test_knob_ranking_gap_per_second():
    rank = knob_ranking(summarize_points(_rows()))
    # faster and better first, then 0.03 per 5 s before 0.02 per 20 s, then the worse one
    assert rank["knob"].tolist() == ["image", "grad_iters", "grid_res", "cameras"]
    assert rank["verdict"].tolist() == ["free (faster and better)", "costs time", "costs time", "worse"]
    assert rank.set_index("knob").loc["cameras", "gain_vs_base"] == pytest.approx(-0.01)


def test_a_gain_within_the_tolerance_is_no_gain():
    """What changes only the arithmetic (threads, float64) moves the gap by about 1e-6: neither a gain
    bought per second nor a loss."""
    rows = _rows()[:1] + [
        {"name": "threads-1", "knob": "threads", "value": "1", "gap_last": 0.90 + 2e-6, "time_s": 14.0,
         "time_to_90_s": 9.0, "volume_iou_last": 0.9},
        {"name": "precision-float64", "knob": "precision", "value": "float64", "gap_last": 0.90 - 1e-9,
         "time_s": 20.0, "time_to_90_s": 12.0, "volume_iou_last": 0.9},
        {"name": "cameras-4", "knob": "cameras", "value": "4", "gap_last": 0.90 + 2 * GAP_TOLERANCE, "time_s": 12.0,
         "time_to_90_s": 9.0, "volume_iou_last": 0.9}]
    df = summarize_points(rows)
    assert df.set_index("name").loc["threads-1", "gap_gain_per_s"] == 0.0
    rank = knob_ranking(df).set_index("knob")
    assert rank.loc["threads", "verdict"] == "no gain" and rank.loc["threads", "gain_per_s"] == 0.0
    assert rank.loc["precision", "verdict"] == "no gain"
    assert rank.loc["threads", "gain_vs_base"] == pytest.approx(2e-6)  # the measured difference still shown
    assert rank.loc["cameras", "verdict"] == "costs time"
    assert rank.loc["cameras", "gain_per_s"] == pytest.approx(2 * GAP_TOLERANCE / 2.0)
    assert knob_ranking(df)["knob"].tolist()[0] == "cameras"


def test_recommendations_read_the_budget_off_the_points():
    rec = recommendations(summarize_points(_rows())).set_index("budget")
    assert rec.loc["fast", "point"] == "image-80x45"  # the fastest at >= 90 % at its last frame
    assert rec.loc["default", "point"] == "base"
    # the highest volume IoU of those at >= 90 %, not the most gap (each point's gap has its own ceiling)
    assert rec.loc["accurate", "point"] == "grid_res-48"


def test_the_docs_page_reads_the_studys_csv_back(tmp_path):
    """python -m physmorph.reports.userdocs tradeoff: the CSV the workflow wrote (the base's knob and value
    written empty) makes the page and one figure for every scale."""
    from physmorph.reports.userdocs import write_tradeoff_doc

    df = summarize_points([{**r, "particles": 1000 + i, "gap_best": r["gap_last"], "chamfer_last_dx": 0.8,
                            "peak_rss_mb": 500.0} for i, r in enumerate(_rows())])
    df["gap_gain_per_s"] = 123.0  # a study summarised by earlier rules: the page works the gains out again
    for profile in ("default", "mid"):
        (tmp_path / "results" / profile / "tradeoff").mkdir(parents=True)
        df.to_csv(tmp_path / "results" / profile / "tradeoff" / "tradeoff.csv", index=False)
    page = write_tradeoff_doc(["default", "mid"], tmp_path / "results", tmp_path / "docs" / "tradeoff.md",
                              tmp_path / "docs" / "images" / "pareto.png").read_text()
    assert "# Profile `default` (1,000 particles at the base)" in page and "# Profile `mid`" in page
    assert "](images/pareto.png)" in page and (tmp_path / "docs" / "images" / "pareto.png").stat().st_size > 10_000
    assert "123" not in page and "| grid_res-48 |" in page
