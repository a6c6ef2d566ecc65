"""The speed/accuracy study: one resolution knob at a time around a base experiment.

A point is the base experiment with one knob changed: ``grid_res``, ``ppc_surface``, ``image``
(target/render image size, WxH), ``cameras`` or ``grad_iters``. Its name is ``{knob}-{value}``
(``base`` for the unchanged base). For each point the study records the best alpha MSE over the
run, the best Chamfer distance (mean particle-to-target-surface distance, resolution independent),
the morph wall time (sum of frame times) and the peak RSS; it marks the Pareto front of accuracy
against time and ranks the knobs by accuracy bought per second.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

KNOBS = ("grid_res", "ppc_surface", "image", "cameras", "grad_iters")


@dataclass(frozen=True)
class TradeoffPoint:
    name: str
    knob: str  # "" for the base point
    value: str
    grid_res: int
    ppc_surface: int
    ppc_interior: int
    width: int
    height: int
    cameras: int
    grad_iters: int

    @property
    def res_tag(self) -> str:
        return f"{self.grid_res}x{self.ppc_surface}x{self.ppc_interior}"

    @property
    def image_tag(self) -> str:
        return f"{self.width}x{self.height}"


def tradeoff_points(settings) -> dict[str, TradeoffPoint]:
    """Every point of the study (base first), from the settings' ``tradeoff`` section
    (``settings``: physmorph.config.Settings)."""
    t = settings.tradeoff
    exp = settings.experiment(t.experiment)
    s, tg = settings.sampling, settings.target
    base = dict(grid_res=s.grid_res, ppc_surface=s.ppc_surface, ppc_interior=s.ppc_interior,
                width=tg.width, height=tg.height, cameras=exp.cameras or tg.cameras,
                grad_iters=exp.grad_iters or settings.mpm.grad_iters)
    points = {"base": TradeoffPoint("base", "", "", **base)}
    for knob, values in t.knobs.items():
        if knob not in KNOBS:
            raise ValueError(f"config key 'tradeoff.knobs.{knob}': unknown knob (known: {', '.join(KNOBS)})")
        for i, v in enumerate(values):
            p = dict(base)
            try:
                if knob == "image":
                    if not isinstance(v, (list, tuple)) or len(v) != 2:
                        raise ValueError
                    p["width"], p["height"] = int(v[0]), int(v[1])
                    label = f"{int(v[0])}x{int(v[1])}"
                else:
                    p[knob] = int(v)
                    label = str(int(v))
            except (TypeError, ValueError):
                want = "[width, height]" if knob == "image" else "an integer"
                raise ValueError(f"config key 'tradeoff.knobs.{knob}[{i}]': expected {want}, got {v!r}") from None
            if p == base:
                continue
            if knob == "cameras" and p["cameras"] > tg.cameras:
                raise ValueError(f"config key 'tradeoff.knobs.cameras': {p['cameras']} exceeds target.cameras {tg.cameras}")
            name = f"{knob}-{label}"
            points[name] = TradeoffPoint(name, knob, label, **p)
    return points


def pareto_front(time_s: np.ndarray, error: np.ndarray) -> np.ndarray:
    """[n] bool: points no other point beats in both time and error (ties in both kept)."""
    t, e = np.asarray(time_s, float), np.asarray(error, float)
    keep = np.ones(len(t), bool)
    for i in range(len(t)):
        dominated = (t <= t[i]) & (e <= e[i]) & ((t < t[i]) | (e < e[i]))
        keep[i] = not dominated.any()
    return keep


def summarize_points(rows: list[dict]) -> pd.DataFrame:
    """rows: name, knob, value, best_alpha_mse, best_chamfer, time_s, peak_rss_mb. Adds the
    Pareto flag and, per point, alpha MSE gained per extra second relative to the base."""
    df = pd.DataFrame(rows)
    df["pareto"] = pareto_front(df["time_s"].to_numpy(), df["best_alpha_mse"].to_numpy())
    base = df[df["name"] == "base"].iloc[0]
    dt = df["time_s"] - base["time_s"]
    gain = base["best_alpha_mse"] - df["best_alpha_mse"]
    df["alpha_gain_per_s"] = np.where(np.abs(dt) > 1e-9, gain / dt.where(np.abs(dt) > 1e-9, 1.0), 0.0)
    return df


def knob_ranking(df: pd.DataFrame) -> pd.DataFrame:
    """One row per knob: its best point by alpha MSE, the gain over the base, its cost and a
    verdict (free: faster and better, its gain_per_s inf; costs time; worse)."""
    base = df[df["name"] == "base"].iloc[0]
    rows = []
    for knob, g in df[df["knob"] != ""].groupby("knob"):
        best = g.loc[g["best_alpha_mse"].idxmin()]
        gain = base["best_alpha_mse"] - best["best_alpha_mse"]
        extra = best["time_s"] - base["time_s"]
        # a knob that is both faster and better has no cost to divide by: "free" ranks it first
        verdict = ("worse" if gain <= 0 else "free (faster and better)" if extra <= 1e-9 else "costs time")
        rows.append({"knob": knob, "best_value": best["value"], "alpha_mse": best["best_alpha_mse"],
                     "gain_vs_base": gain, "extra_time_s": extra,
                     "gain_per_s": gain / extra if extra > 1e-9 else (np.inf if gain > 0 else 0.0),
                     "verdict": verdict})
    return pd.DataFrame(rows).sort_values("gain_per_s", ascending=False, ignore_index=True)


def build_tradeoff(points: dict[str, TradeoffPoint], runs: dict[str, Path], out_dir: Path) -> pd.DataFrame:
    """Write tradeoff.csv, tradeoff.md (with the knob ranking) and pareto.png; return the table."""
    from physmorph.runfile import read_metrics
    from physmorph.tables import markdown_table

    rows = []
    for name, path in runs.items():
        m = read_metrics(path)
        p = points[name]
        rows.append({"name": name, "knob": p.knob, "value": p.value, "particles": int(m["attrs"]["n_particles"]),
                     "best_alpha_mse": float(np.nanmin(m["alpha_mse"])), "best_chamfer": float(np.nanmin(m["chamfer"])),
                     "time_s": float(np.nansum(m["t_frame"])), "peak_rss_mb": float(m["attrs"]["peak_rss_mb"])})
    df = summarize_points(rows)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    df.to_csv(out / "tradeoff.csv", index=False)
    rank = knob_ranking(df)
    (out / "tradeoff.md").write_text("## Points\n\n" + markdown_table(df) + "\n## Which knob buys the most accuracy per second\n\n"
                                     + markdown_table(rank))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for knob, g in df.groupby("knob"):
        ax.scatter(g["time_s"], g["best_alpha_mse"], label=knob or "base", s=36, zorder=3)
        for _, r in g.iterrows():
            ax.annotate(r["name"], (r["time_s"], r["best_alpha_mse"]), fontsize=6, xytext=(3, 3), textcoords="offset points")
    front = df[df["pareto"]].sort_values("time_s")
    ax.step(front["time_s"], front["best_alpha_mse"], where="post", color="k", lw=1, label="Pareto front")
    ax.set_xscale("log")
    ax.set_xlabel("morph wall time (s)")
    ax.set_ylabel("best alpha MSE")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title("speed / accuracy: one knob at a time around the default", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "pareto.png", dpi=120)
    plt.close(fig)
    return df
