"""Speed/accuracy study: points, Pareto front, knob ranking on hand-made numbers."""

import numpy as np
import pytest

from physmorph.config import ConfigError, load_settings
from physmorph.tradeoff import knob_ranking, pareto_front, summarize_points, tradeoff_points


def test_pareto_front_hand_made():
    t = np.array([1.0, 2.0, 3.0, 2.5, 4.0])
    e = np.array([0.10, 0.08, 0.05, 0.09, 0.05])
    assert pareto_front(t, e).tolist() == [True, True, True, False, False]


def test_points_change_one_knob_each():
    cfg = load_settings("config/config.yaml")
    pts = tradeoff_points(cfg)
    base = pts["base"]
    assert base.res_tag == "32x2x1" and base.image_tag == "160x90"
    for name, p in pts.items():
        if name == "base":
            continue
        changed = [k for k in ("grid_res", "ppc_surface", "width", "cameras", "grad_iters") if getattr(p, k) != getattr(base, k)]
        assert len(changed) == 1, name
    assert "grid_res-64" in pts and "cameras-1" in pts and "image-320x180" in pts


def test_unknown_knob_is_named():
    with pytest.raises(ConfigError, match="tradeoff.knobs.shininess"):
        load_settings("config/config.yaml", overrides={"tradeoff": {"knobs": {"shininess": [1]}}})
    with pytest.raises(ConfigError, match=r"tradeoff.knobs.image\[0\]'.*\[width, height\]"):
        load_settings("config/config.yaml", overrides={"tradeoff": {"knobs": {"image": [320]}}})


def test_knob_ranking_accuracy_per_second():
    rows = [
        {"name": "base", "knob": "", "value": "", "best_alpha_mse": 0.10, "time_s": 10.0},
        {"name": "grid_res-48", "knob": "grid_res", "value": "48", "best_alpha_mse": 0.08, "time_s": 30.0},
        {"name": "cameras-4", "knob": "cameras", "value": "4", "best_alpha_mse": 0.11, "time_s": 8.0},
        {"name": "grad_iters-2", "knob": "grad_iters", "value": "2", "best_alpha_mse": 0.07, "time_s": 15.0},
        {"name": "image-80x45", "knob": "image", "value": "80x45", "best_alpha_mse": 0.09, "time_s": 9.0},
    ]
    df = summarize_points(rows)
    assert df.set_index("name").loc["grid_res-48", "alpha_gain_per_s"] == pytest.approx(0.02 / 20)
    rank = knob_ranking(df)
    # faster and better first, then 0.03 per 5 s before 0.02 per 20 s, then the worse one
    assert rank["knob"].tolist() == ["image", "grad_iters", "grid_res", "cameras"]
    assert rank["verdict"].tolist() == ["free (faster and better)", "costs time", "costs time", "worse"]
    assert rank.set_index("knob").loc["cameras", "gain_vs_base"] == pytest.approx(-0.01)
