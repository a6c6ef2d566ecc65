"""The speed/accuracy study: one knob at a time around a base experiment, on converging runs.

A point is the base experiment with one knob changed (physmorph.settings.study_points: the knobs, the
points the config asks for). Its name is ``{knob}-{value}`` (``base`` for the unchanged base).

Each point is judged by what a unit of time buys on a run that converges: the wall time to reach
90 % of the reachable gap (``time_to_90_s``; NaN when the run never gets there), the share of the
gap closed at the last frame, the volume IoU and the Chamfer distance in grid cells at the last
frame, the morph wall time (the sum of its frame times) and the peak RSS. The Pareto front is taken
on (wall time, gap left at the last frame); the points are ranked by time to 90 %, and each knob by
the final gap it buys per extra second.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from physmorph.base.markdown import markdown_table
# workflow/rules/common.smk takes the points from here, with the study
from physmorph.settings.study_points import TradeoffPoint, tradeoff_points  # noqa: F401

QUALITY = 0.9  # the share of the reachable gap that time-to-quality is measured to
# A knob's gain over the base within this share of the gap is no gain: the pages print the gap to a
# tenth of a point, and what changes only the arithmetic moves it by about 1e-6 (the study's
# threads-1 and precision-float64 points: two threads' sums, float64), which per second of extra
# time would otherwise rank as a gain bought.
GAP_TOLERANCE = 1e-3
VERDICTS = ("free (faster and better)", "costs time", "no gain", "worse")  # knob_ranking's, in its order


def pareto_front(time_s: np.ndarray, error: np.ndarray) -> np.ndarray:
    """[n] bool: points no other point beats in both time and error (ties in both kept)."""
    t, e = np.asarray(time_s, float), np.asarray(error, float)
    keep = np.ones(len(t), bool)
    for i in range(len(t)):
        dominated = (t <= t[i]) & (e <= e[i]) & ((t < t[i]) | (e < e[i]))
        keep[i] = not dominated.any()
    return keep


def time_to_quality(gap_closed: np.ndarray, frame_time_s: np.ndarray, quality: float = QUALITY) -> float:
    """Seconds of morphing until the first frame whose gap closed reaches ``quality``; NaN: never.
    ``gap_closed``, ``frame_time_s``: [K + 1] per frame (frame 0 is the source, its time NaN)."""
    g = np.asarray(gap_closed, float)
    t = np.nan_to_num(np.asarray(frame_time_s, float), nan=0.0)
    hit = np.flatnonzero(g >= quality)
    return float(np.cumsum(t)[hit[0]]) if len(hit) else float("nan")


def point_row(name: str, point: TradeoffPoint, metrics: dict, dx: float) -> dict:
    """One point's numbers from its run's metrics (physmorph.records.runfile.read_metrics); ``dx``: the
    point's grid cell in domain units."""
    g = np.asarray(metrics["gap_closed"], float)
    return {"name": name, "knob": point.knob, "value": point.value, "particles": int(metrics["attrs"]["n_particles"]),
            "time_to_90_s": time_to_quality(g, metrics["t_frame"]),
            "gap_last": float(g[-1]), "gap_best": float(np.nanmax(g[1:])) if len(g) > 1 else float("nan"),
            "volume_iou_last": float(metrics["volume_iou"][-1]),
            "chamfer_last_dx": float(metrics["chamfer"][-1]) / dx,
            "time_s": float(np.nansum(metrics["t_frame"])), "peak_rss_mb": float(metrics["attrs"]["peak_rss_mb"])}


def summarize_points(rows: list[dict]) -> pd.DataFrame:
    """rows: name, knob, value, time_to_90_s, gap_last, time_s (and more). Adds the Pareto flag
    (wall time against the gap left at the last frame) and, per point, the final gap closed per
    extra second relative to the base (as knob_ranking: a gain within GAP_TOLERANCE is none; a point
    faster than the base and better has no cost to divide by, inf; one faster and no better bought
    nothing, NaN); sorted by time to 90 % (never last)."""
    df = pd.DataFrame(rows)
    df["pareto"] = pareto_front(df["time_s"].to_numpy(), 1.0 - df["gap_last"].to_numpy())
    base = df[df["name"] == "base"].iloc[0]
    dt = df["time_s"] - base["time_s"]
    gain = _gain(df["gap_last"] - base["gap_last"])
    costs = dt > 1e-9
    df["gap_gain_per_s"] = np.where(costs, gain / dt.where(costs, 1.0),
                                    np.where(gain > 0, np.inf, np.where(dt.abs() <= 1e-9, 0.0, np.nan)))
    return df.sort_values(["time_to_90_s", "time_s"], na_position="last", ignore_index=True)


def _gain(gain):
    """A gain in the share of the gap closed (a float or an array), 0 where within GAP_TOLERANCE."""
    return np.where(np.abs(gain) > GAP_TOLERANCE, gain, 0.0)


def knob_ranking(df: pd.DataFrame) -> pd.DataFrame:
    """One row per knob: its best point by final gap closed, the gain over the base, its cost and a
    verdict (free: faster and better, its gain_per_s inf; costs time; no gain: within GAP_TOLERANCE
    of the base's gap, its gain_per_s 0; worse)."""
    base = df[df["name"] == "base"].iloc[0]
    rows = []
    for knob, g in df[df["knob"] != ""].groupby("knob"):
        best = g.loc[g["gap_last"].idxmax()]
        gain = best["gap_last"] - base["gap_last"]
        extra = best["time_s"] - base["time_s"]
        bought = float(_gain(gain))
        # a knob that is both faster and better has no cost to divide by: "free" ranks it first
        verdict = ("worse" if bought < 0 else "no gain" if bought == 0 else
                   "free (faster and better)" if extra <= 1e-9 else "costs time")
        rows.append({"knob": knob, "best_value": best["value"], "gap_last": best["gap_last"],
                     "gain_vs_base": gain, "extra_time_s": extra,
                     "gain_per_s": bought / extra if extra > 1e-9 else (np.inf if bought > 0 else 0.0),
                     "verdict": verdict})
    ranked = pd.DataFrame(rows)
    order = ranked["verdict"].map({v: i for i, v in enumerate(VERDICTS)})
    return ranked.assign(_order=order).sort_values(["_order", "gain_per_s"], ascending=[True, False],
                                                    ignore_index=True).drop(columns="_order")


def recommendations(df: pd.DataFrame, quality: float = QUALITY) -> pd.DataFrame:
    """What to run for a budget: the fastest point to reach ``quality`` at its last frame (fast), the
    base (default) and, of the points that reach it, the one with the highest volume IoU (accurate).
    The gap is measured against each point's own ceiling (its image size, its particles), so past the
    bar it does not compare points of different resolution; the volume IoU against the target mesh does."""
    rows = []
    ok = df[df["gap_last"] >= quality]
    if len(ok):
        rows.append(("fast", ok.loc[ok["time_s"].idxmin()]))
    rows.append(("default", df[df["name"] == "base"].iloc[0]))
    pool = ok if len(ok) else df
    rows.append(("accurate", pool.loc[pool["volume_iou_last"].idxmax()]))
    return pd.DataFrame([{"budget": b, "point": r["name"], "time_s": r["time_s"], "time_to_90_s": r["time_to_90_s"],
                          "gap_last": r["gap_last"], "volume_iou_last": r["volume_iou_last"]} for b, r in rows])


def pareto_figure(frames: dict[str, pd.DataFrame], out_png: Path, title: str) -> None:
    """Final gap closed against wall time, every point (``frames``: scale name -> its summary),
    each scale its own marker, each scale's front drawn; time to 90 % in the second panel."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    markers = "os^Dv<>"
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4.4))
    knobs = sorted({k for df in frames.values() for k in df["knob"]})
    colors = {k: plt.cm.tab20(i % 20) for i, k in enumerate(knobs)}  # 11 knobs with the base: tab10 repeats
    for j, (scale, df) in enumerate(frames.items()):
        m = markers[j % len(markers)]
        for _, r in df.iterrows():
            ax.scatter(r["time_s"], 100 * r["gap_last"], marker=m, color=colors[r["knob"]], s=36, zorder=3,
                       edgecolor="k" if r["pareto"] else "none")
            ax.annotate(r["name"], (r["time_s"], 100 * r["gap_last"]), fontsize=6, xytext=(3, 3), textcoords="offset points")
            if np.isfinite(r["time_to_90_s"]):
                ax2.scatter(r["time_to_90_s"], 100 * r["gap_last"], marker=m, color=colors[r["knob"]], s=36)
                ax2.annotate(r["name"], (r["time_to_90_s"], 100 * r["gap_last"]), fontsize=6, xytext=(3, 3),
                             textcoords="offset points")
        front = df[df["pareto"]].sort_values("time_s")
        ax.step(front["time_s"], 100 * front["gap_last"], where="post", color="k", lw=1, ls="-" if j == 0 else "--",
                label=f"{scale}: Pareto front")
        base_particles = int(df.loc[df["name"] == "base", "particles"].iloc[0])
        ax.scatter([], [], marker=m, color="grey", label=f"{scale} ({base_particles:,} particles at the base)")
    for k in knobs:
        ax.scatter([], [], marker="s", color=colors[k], label=k or "base")
    ax.axhline(100 * QUALITY, color="grey", lw=0.8, ls=":")
    _seconds_axis(ax)
    ax.set_xlabel("morph wall time (s)")
    ax.set_ylabel("gap closed at the last frame (%)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6, ncol=2)
    ax.set_title(title, fontsize=9)
    if any(np.isfinite(df["time_to_90_s"]).any() for df in frames.values()):
        _seconds_axis(ax2)
    else:
        ax2.text(0.5, 0.5, f"no point reached {100 * QUALITY:.0f} % of the gap", ha="center", transform=ax2.transAxes)
    ax2.set_xlabel(f"wall time to {100 * QUALITY:.0f} % of the gap (s; points that never get there are left out)")
    ax2.set_ylabel("gap closed at the last frame (%)")
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out_png, dpi=120)
    plt.close(fig)


def _seconds_axis(ax) -> None:
    """A log x axis labelled in plain seconds at 1-2-5 steps (matplotlib's default labels every
    minor tick as 2x10^1, 3x10^1, ..., which overlap)."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    ax.set_xscale("log")
    ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())


def tradeoff_markdown(df: pd.DataFrame) -> str:
    return ("## Points, by time to 90 % of the reachable gap (empty: never)\n\n" + markdown_table(df)
            + "\n## Which knob buys the most final gap per second\n\n" + markdown_table(knob_ranking(df))
            + "\n## What to run for a budget\n\n" + markdown_table(recommendations(df)))


def build_tradeoff(points: dict[str, TradeoffPoint], runs: dict[str, Path], out_dir: Path,
                   domain_width: float) -> pd.DataFrame:
    """Write tradeoff.csv, tradeoff.md (the ranked points, the knob ranking, the recommendations)
    and pareto.png; return the table. ``domain_width``: hi - lo of the simulation cube."""
    from physmorph.records.runfile import read_metrics

    rows = [point_row(name, points[name], read_metrics(path), domain_width / points[name].grid_res)
            for name, path in runs.items()]
    df = summarize_points(rows)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    df.to_csv(out / "tradeoff.csv", index=False)
    (out / "tradeoff.md").write_text(tradeoff_markdown(df))
    pareto_figure({"this profile": df}, out / "pareto.png", "speed / accuracy: one knob at a time around the base")
    return df
