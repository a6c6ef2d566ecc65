"""The paper's tables from run files: CSV, Markdown and LaTeX, with the paper's figures beside ours.

Each table reads experiments by name (the names of config/config.yaml), as the layout
(physmorph.reports.layout, config/paper_results.yaml) lists them with the paper's numbers. An experiment that was
not run in this profile shows as empty cells, so a partial profile still produces every table.
The convergence table has one row per run and reports, besides raw alpha MSE (which depends on
image size, particle count and sigma0), the share of the reachable gap closed: how far each run
got from its start towards the ceiling, its target's own particles rendered at rest
(physmorph.morph.quality; docs/outputs.md explains every table and column).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from physmorph.reports.metrics import (TABLE_NAMES, delta_e_percent, improvement_percent, matched_convergence_frame,
                               rebound_percent, release_rebound_percent, sign_changes, spread, swing_percent)
from physmorph.reports.layout import PaperLayout, TableLayout
from physmorph.base.markdown import markdown_table
from physmorph.records.runfile import read_metrics
from physmorph.morph.quality import gap_closed


def _load(runs: dict[str, str | Path]) -> dict[str, dict]:
    """Metrics of every run file that exists, each with its path under 'path'."""
    return {name: {**read_metrics(path), "path": str(path)} for name, path in runs.items()
            if path is not None and Path(path).exists()}


def _ceiling(r: dict, key: str = "ceiling_alpha_mse") -> float:
    """The run's ceiling attribute (copied from its target); a run without one names its file."""
    value = float(r["attrs"].get(key, np.nan))
    if not np.isfinite(value):
        raise ValueError(f"{r.get('path', '?')}: run file has no '{key}' attribute (made before the ceiling was "
                         "stored): rerun the rasterize_target stage of its target and then its morph")
    return value


def _closed_percent(r: dict) -> tuple[float, float]:
    """Share (%) of the reachable gap closed at the best (lowest alpha MSE) and at the last frame."""
    a = np.asarray(r["alpha_mse"], dtype=float)
    c = _ceiling(r)
    return 100.0 * gap_closed(a[0], a[int(np.nanargmin(a))], c), 100.0 * gap_closed(a[0], a[-1], c)


def main_table(m: dict[str, dict], t: TableLayout) -> pd.DataFrame:
    rows = []
    for target, c in t.main.items():
        phys, full = m.get(c.physics_only), m.get(c.full)
        row = {"target": target, "paper_physics_only": c.paper_physics_only, "paper_ours": c.paper_full,
               "paper_improvement_%": c.paper_improvement_percent}
        if phys is not None and full is not None:
            k = min(matched_convergence_frame(phys["alpha_mse"]), len(full["alpha_mse"]) - 1)
            a, b = phys["alpha_mse"][k], full["alpha_mse"][k]
            row.update(frame=k, physics_only=a, ours=b, **{"improvement_%": improvement_percent(a, b)})
        rows.append(row)
    return pd.DataFrame(rows)


def components_table(m: dict[str, dict], t: TableLayout) -> pd.DataFrame:
    rows = []
    for name, p in t.components.items():
        row = {"experiment": name, "paper_alpha_mse": p.alpha_mse, "paper_delta_E_%": p.delta_e_percent}
        if name in m:
            r = m[name]
            phys = r["physics_loss"]
            row.update(alpha_mse=r["alpha_mse"][-1], **{"delta_E_%": delta_e_percent(r["physics_loss_initial"][1], phys[-1])})
        rows.append(row)
    return pd.DataFrame(rows)


def drag_table(m: dict[str, dict], t: TableLayout) -> pd.DataFrame:
    rows = []
    for name, p in t.drag.items():
        row = {"experiment": name, "paper_best": p.best, "paper_final": p.final}
        if name in m:
            a = m[name]["alpha_mse"]
            row.update(best=float(np.nanmin(a)), final=float(a[-1]))
        rows.append(row)
    return pd.DataFrame(rows)


def source_table(m: dict[str, dict], t: TableLayout) -> pd.DataFrame:
    """Best alpha MSE and share of the reachable gap closed (best, final frame) per source, then
    mean, sample std and sigma/mu % of each column."""
    cols = ("paper_best", "best", "closed_best_%", "closed_final_%")
    rows = []
    for n, p in t.source_invariance.items():
        row = {"experiment": n, "paper_best": p, "best": np.nan, "closed_best_%": np.nan, "closed_final_%": np.nan}
        if n in m:
            row["best"] = float(np.nanmin(m[n]["alpha_mse"]))
            row["closed_best_%"], row["closed_final_%"] = _closed_percent(m[n])
        rows.append(row)
    stats = {}
    for col in cols:
        vals = np.array([r[col] for r in rows], dtype=float)
        vals = vals[np.isfinite(vals)]
        stats[col] = spread(vals) if len(vals) > 1 else {"mean": np.nan, "std": np.nan, "cv_percent": np.nan}
    for key, label in (("mean", "mean"), ("std", "std"), ("cv_percent", "sigma/mu %")):
        rows.append({"experiment": label, **{col: stats[col][key] for col in cols}})
    return pd.DataFrame(rows)


def _per_frame(r: dict, key: str, n: int) -> np.ndarray:  # [n]
    """A per-frame metric of a run, NaN throughout for a run written before the metric existed."""
    return np.asarray(r[key], dtype=float) if key in r else np.full(n, np.nan)


def convergence_table(m: dict[str, dict], layout: PaperLayout) -> pd.DataFrame:
    """One row per run: alpha MSE at frame 0, best (and its frame) and final frame, the ceiling
    (the target's own particles at rest, physmorph.morph.quality), the share of the reachable gap closed
    at the best and final frame (%), silhouette IoU at frame 0, its maximum and final frame, the
    ceiling IoU, the 3D checks (physmorph.morph.quality.volume_metrics): the volume IoU at frame 0 and
    the final frame (1 for the target's own sampling) and the final share of the mass packed above
    twice the target's density (0 for it), how still the last frames are (physmorph.reports.metrics: the
    swing %, the sign changes of the alpha MSE's frame-to-frame change over the last 10 frames,
    and the drop, the best frame's share of the gap minus the last's, in points), the last
    exported surface's measures where the run was exported (physmorph.reports.export.measures: the
    stray share (%), the mean and 95th-percentile distance to the target mesh (grid cells), the mass
    outside the largest body (%), the surface's components and genus beside the target's, its
    roughness (%)), and the
    paper's alpha MSE for the experiment where it has one (and which one). Runs written before a
    metric existed show it as NaN."""
    rows = []
    for name, r in m.items():
        a = np.asarray(r["alpha_mse"], dtype=float)
        k = int(np.nanargmin(a))
        closed_best, closed_final = _closed_percent(r)
        iou, viou, over = (_per_frame(r, key, len(a)) for key in ("iou", "volume_iou", "overfilled_mass"))
        has_iou = bool(np.isfinite(iou).any())
        paper, paper_which = layout.paper_alpha_mse(name)
        rows.append({"experiment": name, "method": str(r["attrs"].get("method", "")), "frames": len(a) - 1,
                     "alpha_mse_0": a[0], "alpha_mse_best": a[k], "best_frame": k, "alpha_mse_final": a[-1],
                     "ceiling": _ceiling(r), "closed_best_%": closed_best, "closed_final_%": closed_final,
                     "iou_0": iou[0], "iou_best": float(np.nanmax(iou)) if has_iou else np.nan, "iou_final": iou[-1],
                     "ceiling_iou": float(r["attrs"].get("ceiling_iou", np.nan)),
                     "volume_iou_0": viou[0], "volume_iou_final": viou[-1], "overfilled_mass_final": over[-1],
                     "swing_%": swing_percent(a), "sign_changes": sign_changes(a),
                     "drop_points": closed_best - closed_final,
                     **_body_columns(r.get("export_last", {})),
                     "paper_alpha_mse": paper, "paper_which": paper_which})
    columns = ["experiment", "method", "frames", "alpha_mse_0", "alpha_mse_best", "best_frame", "alpha_mse_final",
               "ceiling", "closed_best_%", "closed_final_%", "iou_0", "iou_best", "iou_final", "ceiling_iou",
               "volume_iou_0", "volume_iou_final", "overfilled_mass_final", "swing_%", "sign_changes", "drop_points",
               *BODY_COLUMNS, "paper_alpha_mse", "paper_which"]
    return pd.DataFrame(rows, columns=columns)


# the last exported surface's measures (physmorph.reports.export.measures) the convergence table shows,
# each under its column: measures.csv's name -> (the table's name, its scale)
EXPORT_COLUMNS = {"stray_share": ("stray_%", 100.0), "surface_distance_dx": ("surface_dx", 1.0),
                  "surface_p95_dx": ("surface_p95_dx", 1.0), "outside_largest_body": ("outside_body_%", 100.0),
                  "components": ("components", 1.0), "genus": ("genus", 1.0), "target_genus": ("target_genus", 1.0),
                  "roughness_percent": ("rough_%", 1.0)}
BODY_COLUMNS = tuple(column for column, _ in EXPORT_COLUMNS.values())


def _body_columns(last: dict) -> dict:
    """The convergence table's columns of the last exported surface (NaN where the run was not
    exported, or exported before a measure existed)."""
    return {column: scale * last.get(key, np.nan) for key, (column, scale) in EXPORT_COLUMNS.items()}


def plasticity_table(m: dict[str, dict], t: TableLayout) -> pd.DataFrame:
    rows = []
    pair = t.plasticity
    variants = [] if pair is None else [(pair.with_, "with plasticity", pair.paper_rebound),
                                        (pair.without, "without plasticity", "")]
    for name, label, paper in variants:
        row = {"experiment": name, "variant": label, "paper_rebound_%": paper}
        if name in m:
            a = m[name]["alpha_mse"]
            row.update(best=float(np.nanmin(a)), final=float(a[-1]), **{"rebound_%": rebound_percent(a)})
            if "release_alpha_mse" in m[name]["attrs"]:  # the morph with the control off afterwards
                release = json.loads(m[name]["attrs"]["release_alpha_mse"])
                row.update(release_frames=len(release) - 1, release_final=release[-1],
                           **{"release_rebound_%": release_rebound_percent(a, release)})
        rows.append(row)
    return pd.DataFrame(rows)


def shapes_table(m: dict[str, dict], t: TableLayout) -> pd.DataFrame:
    rows = []
    for name in t.shapes:
        row = {"experiment": name}
        if name in m:
            r = m[name]
            v = r["total_volume"]
            row.update(best=float(np.nanmin(r["alpha_mse"])), final=float(r["alpha_mse"][-1]),
                       **{"volume_change_%": 100.0 * (v[-1] - v[0]) / v[0]})
        rows.append(row)
    return pd.DataFrame(rows)


def timing_table(m: dict[str, dict]) -> pd.DataFrame:
    rows = []
    for name, r in sorted(m.items()):
        frames = slice(1, None)
        rows.append({"experiment": name, "frames": len(r["alpha_mse"]) - 1, "status": str(r["attrs"].get("status", "")),
                     "physics_s": float(np.nanmean(r["t_physics"][frames])), "render_s": float(np.nanmean(r["t_render"][frames])),
                     "plasticity_s": float(np.nanmean(r["t_plasticity"][frames])), "mask_s": float(np.nanmean(r["t_mask"][frames])),
                     "frame_s": float(np.nanmean(r["t_frame"][frames])), "peak_rss_mb": float(r["attrs"].get("peak_rss_mb", np.nan)),
                     "particles": int(r["attrs"].get("n_particles", 0))})
    return pd.DataFrame(rows)


DIRECTION_COLUMNS = ["direction", "case", "measure", "ours", "baseline", "ours_vs_baseline_%", "margin", "noise",
                     "holds", "paper"]


def _noise_of(m: dict[str, dict], noise: tuple[str, ...]):
    """The spread of a measure between the two runs of ``noise`` (one experiment from two particle
    samples, config tables.noise): a function of the measure (a curve -> a number) giving
    |measure(first) - measure(second)|, NaN where the pair is not configured or not run."""
    pair = [m.get(name) for name in noise]
    if len(pair) != 2 or any(r is None for r in pair):
        return lambda measure: float("nan")
    return lambda measure: float(abs(measure(pair[0]["alpha_mse"]) - measure(pair[1]["alpha_mse"])))


def directions_table(m: dict[str, dict], t: TableLayout, main: pd.DataFrame, plast: pd.DataFrame,
                     noise: tuple[str, ...] = ()) -> pd.DataFrame:
    """The paper's three directions, each as a comparison where lower is better: ``ours`` (the
    paper's choice) against ``baseline``; ``ours_vs_baseline_%`` = 100 (baseline - ours) / baseline;
    ``margin`` = baseline - ours; ``noise`` the same measure's spread between the two runs of
    ``noise`` (one experiment from two particle samples: config tables.noise), NaN without them.
    ``holds``: yes where the margin exceeds the noise, no where it is below minus the noise,
    "within noise" between, and without a noise measure yes where ours is lower; empty when a run
    is missing. Rows: full vs physics-only alpha MSE at the matched-convergence frame (one per
    main-table target); F- vs position injection, final alpha MSE; plasticity vs none, rebound % in
    the run and, where the runs were released (morph.release_frames), after the release (no noise
    measure: the noise pair is not released). ``main`` and ``plast``: the main and plasticity
    tables of the same runs."""
    rows = []
    spread_of = _noise_of(m, tuple(noise))

    def add(direction, case, measure, ours, baseline, paper, noise_value=float("nan")):
        row = {"direction": direction, "case": case, "measure": measure, "ours": ours, "baseline": baseline,
               "ours_vs_baseline_%": np.nan, "margin": np.nan, "noise": noise_value, "holds": "", "paper": paper}
        if np.isfinite(ours) and np.isfinite(baseline):
            margin = baseline - ours
            row["margin"] = margin
            if np.isfinite(noise_value):
                row["holds"] = "yes" if margin > noise_value else "no" if margin < -noise_value else "within noise"
            else:
                row["holds"] = "yes" if ours < baseline else "no"
            if baseline != 0:
                row["ours_vs_baseline_%"] = improvement_percent(baseline, ours)
        rows.append(row)

    main = main.set_index("target")
    for target, c in t.main.items():
        r = main.loc[target]
        has_frame = "frame" in r and np.isfinite(r["frame"])
        frame = f" (frame {int(r['frame'])})" if has_frame else ""
        at_frame = (lambda a, k=int(r["frame"]): float(a[min(k, len(a) - 1)])) if has_frame else None
        add("full beats physics-only at matched convergence", target, "alpha MSE at the matched frame" + frame,
            float(r.get("ours", np.nan)), float(r.get("physics_only", np.nan)), f"{c.paper_improvement_percent:+g} %",
            spread_of(at_frame) if at_frame is not None else float("nan"))
    if t.injection is not None:
        f, x = m.get(t.injection.f_inject), m.get(t.injection.position_inject)
        add("F-injection beats position injection", f"{t.injection.f_inject} vs {t.injection.position_inject}",
            "final alpha MSE", np.nan if f is None else float(f["alpha_mse"][-1]),
            np.nan if x is None else float(x["alpha_mse"][-1]), t.injection.paper, spread_of(lambda a: float(a[-1])))
    if len(plast) == 2:
        with_, without = plast.iloc[0], plast.iloc[1]
        case = f"{with_['experiment']} vs {without['experiment']}"
        for column, measure in (("rebound_%", "rebound % after the best frame"),
                                ("release_rebound_%", "release rebound % (control off)")):
            if column in plast:
                in_run = column == "rebound_%"
                add("plasticity lowers rebound", case, measure, float(with_[column]), float(without[column]),
                    f"{t.plasticity.paper_rebound} %" if in_run else "",
                    spread_of(rebound_percent) if in_run else float("nan"))
    return pd.DataFrame(rows, columns=DIRECTION_COLUMNS)


def build_tables(runs: dict[str, str | Path], out_dir: str | Path, layout: PaperLayout,
                 measures: dict[str, str | Path] | None = None,
                 noise: tuple[str, ...] = ()) -> dict[str, pd.DataFrame]:
    """Write every table as {out_dir}/{name}.csv, .md and .tex; returns the DataFrames. ``layout``
    (physmorph.reports.layout): which runs each table compares and the paper's numbers; ``measures``: run
    name -> the measures.csv of its exported surfaces (physmorph.reports.export.measures), whose last row
    gives the convergence table's stray and surface columns; ``noise``: the two runs (one
    experiment, two particle samples) whose spread is the directions table's noise."""
    m = _load(runs)
    for name, path in (measures or {}).items():
        if name in m and Path(path).exists():
            last = pd.read_csv(path).iloc[-1]
            # a measures.csv written before a measure existed gives NaN for it
            m[name]["export_last"] = {k: float(last[k]) if k in last else np.nan for k in EXPORT_COLUMNS}
    t = layout.tables
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tables = {"main": main_table(m, t), "ablation_components": components_table(m, t), "ablation_drag": drag_table(m, t),
              "source_invariance": source_table(m, t), "plasticity": plasticity_table(m, t), "shapes": shapes_table(m, t),
              "timing": timing_table(m), "convergence": convergence_table(m, layout)}
    tables["directions"] = directions_table(m, t, tables["main"], tables["plasticity"], noise)
    assert set(tables) == set(TABLE_NAMES), "physmorph.reports.metrics.TABLE_NAMES lists the tables written here"
    for name, df in tables.items():
        df.to_csv(out / f"{name}.csv", index=False)
        (out / f"{name}.md").write_text(markdown_table(df))
        # escape: column names and labels carry _ and % (a LaTeX comment otherwise)
        (out / f"{name}.tex").write_text(df.to_latex(index=False, float_format="%.4g", na_rep="--", escape=True))
    return tables

