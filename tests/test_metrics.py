"""Table metrics on hand-made curves (and the paper's own numbers where it gives them)."""

import numpy as np
import pytest

from physmorph.metrics import (delta_e_percent, improvement_percent, matched_convergence_frame,
                               rebound_percent, release_rebound_percent, spread)


def test_matched_convergence_frame():
    a = np.array([1.0, 0.6, 0.3, 0.15, 0.11, 0.10, 0.12])  # total improvement 0.9, 90 % = 0.81
    assert matched_convergence_frame(a) == 3  # 1 - 0.15 = 0.85 >= 0.81; frame 2 only 0.7
    a2 = np.array([1.0, 0.6, 0.3, 0.2, 0.11, 0.10])
    assert matched_convergence_frame(a2) == 4
    assert matched_convergence_frame(np.array([1.0, 1.1, 1.2])) == 0  # never improves


def test_matched_convergence_frame_exact_threshold():
    a = np.array([1.0, 0.5, 0.1, 0.0])
    assert matched_convergence_frame(a, 0.9) == 2  # 1 - 0.1 = 0.9 exactly


def test_improvement_matches_paper_table():
    assert improvement_percent(0.0799, 0.0593) == pytest.approx(25.8, abs=0.05)
    assert improvement_percent(0.0689, 0.0345) == pytest.approx(49.9, abs=0.05)


def test_rebound():
    assert rebound_percent(np.array([1.0, 0.5, 0.2, 0.2])) == 0.0
    assert rebound_percent(np.array([1.0, 0.2, 0.4])) == pytest.approx(25.0)
    assert rebound_percent(np.array([1.0, 1.0])) == 0.0


def test_release_rebound():
    run = np.array([1.0, 0.6, 0.2])  # gained 0.8
    assert release_rebound_percent(run, np.array([0.2, 0.3, 0.4])) == pytest.approx(25.0)
    assert release_rebound_percent(run, np.array([0.2, 0.2])) == 0.0  # the rest state keeps it all
    assert release_rebound_percent(run, np.array([0.2, 1.0])) == pytest.approx(100.0)  # back at the start
    assert np.isnan(release_rebound_percent(np.array([1.0, 1.0]), np.array([1.0, 0.5])))  # nothing gained


def test_spread_reproduces_paper_source_invariance():
    s = spread([0.0546, 0.0460, 0.0558])
    assert s["mean"] == pytest.approx(0.0521, abs=5e-5)
    assert s["std"] == pytest.approx(0.0054, abs=1e-4)  # 0.00535 (sample std); the paper prints 0.0054
    assert s["cv_percent"] == pytest.approx(10.3, abs=0.06)  # 10.25 %, the paper rounds to 10.3


def test_delta_e():
    assert delta_e_percent(14079, 1167) == pytest.approx(91.7, abs=0.05)  # the paper's "92 %"
    assert delta_e_percent(0.0, 1.0) == 0.0
