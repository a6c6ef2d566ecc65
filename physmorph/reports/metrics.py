"""Metrics the paper's tables report, computed on per-frame curves (index 0 = initial state).

- matched-convergence frame: the first frame at which the physics-only curve has achieved at
  least ``fraction`` (90 %) of its total improvement a[0] - min(a) (paper Table 1);
- improvement %: 100 (baseline - ours) / baseline at that frame;
- rebound %: the share of the achieved improvement lost after the best frame,
  100 (a[K] - min a) / (a[0] - min a);
- delta E %: relative reduction of the physics loss, 100 (E_0 - E_K) / E_0;
- swing %: how still the last frames are, the median over the last ``window`` (10) frames of
  100 |a[k] - a[k-1]| / a[k]; sign changes: how often a[k] - a[k-1] changes sign over them (a
  run still descending has none; a period-two cycle has window - 2); a run is at rest when it
  has at most two or its swing is at most 1 %;
- drop: the share of the gap closed at the best frame minus at the last, in points;
- source spread: mean, sample standard deviation (ddof = 1) and sigma/mu of best values
  (the paper's 0.0546 / 0.0460 / 0.0558 give sigma = 0.0054, sigma/mu = 10.3 %).
"""

from __future__ import annotations

import numpy as np

# The tables `snakemake tables` writes (physmorph.reports.tables builds them).
TABLE_NAMES = ("main", "ablation_components", "ablation_drag", "source_invariance", "plasticity", "shapes", "timing",
               "convergence", "directions")
# The figures `snakemake figures` writes (physmorph.reports.figures builds them).
FIGURE_NAMES = ("sequences_main", "sequences_cross_shape", "sequences_letters", "sequences_other", "drag_ablation",
                "trajectory_divergence", "trajectory_frames", "plasticity_effect", "optimization_traces",
                "gradient_coverage")
# Figures whose runs are chosen from the profile's runs rather than listed in the layout
# (sequences_other: the full runs whose target no other sequence figure shows).
CHOSEN_FIGURES = ("sequences_other",)


def matched_convergence_frame(baseline: np.ndarray, fraction: float = 0.9) -> int:  # baseline [K+1]
    a = np.asarray(baseline, dtype=float)
    if a.size == 0 or not np.isfinite(a[0]):
        raise ValueError("baseline curve must be non-empty with a finite initial value")
    total = a[0] - np.nanmin(a)
    if total <= 0:
        return 0
    reached = (a[0] - a) >= fraction * total - 1e-15
    return int(np.argmax(reached))


def improvement_percent(baseline_value: float, ours_value: float) -> float:
    return 100.0 * (baseline_value - ours_value) / baseline_value


def rebound_percent(curve: np.ndarray) -> float:  # curve [K+1]
    a = np.asarray(curve, dtype=float)
    best = np.nanmin(a)
    gained = a[0] - best
    if gained <= 0:
        return 0.0
    return 100.0 * (a[-1] - best) / gained


def release_rebound_percent(curve: np.ndarray, release: np.ndarray) -> float:  # curve [K+1], release [R+1]
    """Share of a run's gain lost once the control is off: 100 (a_release - a_K) / (a_0 - a_K),
    with a_release the last frame of the release (0 %: the rest state keeps the morph; 100 %: back
    where the run started). NaN when the run gained nothing."""
    a, r = np.asarray(curve, dtype=float), np.asarray(release, dtype=float)
    gained = a[0] - a[-1]
    if not gained > 0:
        return float("nan")
    return 100.0 * (r[-1] - a[-1]) / gained


REST_WINDOW = 10  # the last frames the rest measures look at
REST_SIGN_CHANGES = 2  # at most this many sign changes of a[k] - a[k-1] there: at rest ...
REST_SWING_PERCENT = 1.0  # ... or a swing of at most this


def _last_steps(curve: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:  # curve [K+1] -> [w], [w]
    """The last ``window`` frame-to-frame changes a[k] - a[k-1] of a curve and the a[k] they end at."""
    a = np.asarray(curve, dtype=float)
    if a.size < 2:
        return np.zeros(0), np.zeros(0)
    w = min(int(window), a.size - 1)
    return np.diff(a)[-w:], a[-w:]


def swing_percent(curve: np.ndarray, window: int = REST_WINDOW) -> float:  # curve [K+1]
    """Median over the last ``window`` frames of 100 |a[k] - a[k-1]| / a[k] (NaN for a run of one frame)."""
    step, end = _last_steps(curve, window)
    if step.size == 0:
        return float("nan")
    return float(np.median(100.0 * np.abs(step) / np.abs(end)))


def sign_changes(curve: np.ndarray, window: int = REST_WINDOW) -> int:  # curve [K+1]
    """How often a[k] - a[k-1] changes sign over the last ``window`` frames (a zero change keeps the sign before it)."""
    step, _ = _last_steps(curve, window)
    signs = np.sign(step)
    signs = signs[signs != 0]
    return int(np.count_nonzero(signs[1:] != signs[:-1]))


def at_rest(curve: np.ndarray, window: int = REST_WINDOW, max_swing: float = REST_SWING_PERCENT) -> bool:  # curve [K+1]
    """Whether a run's last frames are still: at most REST_SIGN_CHANGES sign changes or a swing of at most ``max_swing`` %."""
    return sign_changes(curve, window) <= REST_SIGN_CHANGES or swing_percent(curve, window) <= max_swing


def delta_e_percent(initial: float, final: float) -> float:
    return 100.0 * (initial - final) / initial if initial > 0 else 0.0


def spread(values) -> dict[str, float]:
    v = np.asarray(values, dtype=float)
    mean = float(v.mean())
    std = float(v.std(ddof=1)) if v.size > 1 else 0.0
    return {"mean": mean, "std": std, "cv_percent": 100.0 * std / mean if mean else float("nan")}
