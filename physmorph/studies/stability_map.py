"""The stability map's terms and its outputs: the base experiment and the knobs it moves, the one
outcome each cell ends in, the classifier that picks it from what the cell did, and the map's
table and figure. physmorph.studies.extremes makes and runs the cells; the generated page
(physmorph.reports.userdocs) reads the outcomes from here. The outcomes:

converged      every frame ran, every metric is finite, and the last frame closed at least
               ``CONVERGED_GAP`` of the reachable gap (physmorph.morph.quality)
not converged  every frame ran and every metric is finite, but the last frame closed less: a run
               that does not get there, said so (not a failure of the code)
warned         every frame ran and every metric is finite, with a warning: the config's CFLWarning
               or the run's stability monitor (physmorph.morph.stability); its text is kept
refused        the config check refused it before any job ran (physmorph.settings.workflow.ConfigError),
               naming the key; or, for what the config cannot know, a stage refused it naming the
               key (a grid whose particle region cannot hold a prepared mesh: STAGE_REFUSALS)
stopped        the run stopped at a frame, naming the quantity (MorphDivergenceError), and its
               partial run keeps every earlier frame
crash          anything else: an exception of another type, a killed process, a refusal or a stop
               that names no key or frame, lost frames, or a run that reports success with a
               non-finite metric (a silent NaN)
hang           the cell ran past its wall-clock limit

The last two must never appear (tests/studies/test_extremes.py, docs/stability.md). The key, frame and
quantity are the exceptions' attributes (``ERROR_FIELDS``, sent from a cell's process as data by
physmorph.base.isolated_call), never read from a message, so rewording one changes no outcome.
"""

from __future__ import annotations

import math
import signal
from dataclasses import dataclass, field
from pathlib import Path

from physmorph.base.markdown import markdown_table

MAP_EXPERIMENT = "iso_bunny_full"
# A run that ends with at least this share of its reachable gap closed converged (the base cell
# closes 50-59 % at the test profile's 12 frames).
CONVERGED_GAP = 0.25

OUTCOMES = ("converged", "not converged", "warned", "refused", "stopped", "crash", "hang")
FAILURES = ("crash", "hang")  # outcomes the map must never hold

# The attributes of a cell's exception that classify reads: the key a refusal names
# (ConfigError.key, MeshError.key), the frame and quantity a stop names (MorphDivergenceError).
ERROR_FIELDS = ("key", "frame", "quantity")
# Refusals a stage makes once it has what the config cannot know, by exception class: a shape's
# bounds around its centroid are known once its mesh is prepared, so a grid whose particle region
# cannot hold it is refused by the sampling (a MeshError whose key is sampling.grid_res).
STAGE_REFUSALS = ("MeshError",)


@dataclass(frozen=True)
class Knob:
    name: str
    key: str  # the config key it sets ({experiment}: the base experiment's name)
    title: str  # a row label of the figure


KNOBS = (
    Knob("dt", "mpm.dt", "dt (x stable step)"),
    Knob("youngs_modulus", "mpm.youngs_modulus", "Young's modulus E (Pa)"),
    Knob("poisson_ratio", "mpm.poisson_ratio", "Poisson ratio nu"),
    Knob("step_size", "mpm.learning_rate", "step size (x default)"),
    Knob("gamma", "morph.gamma", "injection gain gamma"),
    Knob("eta", "plasticity.eta", "plasticity rate eta"),
    Knob("drag", "experiments.{experiment}.drag", "drag (1/s)"),
    Knob("grid_res", "sampling.grid_res", "grid (cells per axis)"),
    Knob("particles", "sampling.ppc_surface, sampling.ppc_interior", "particles per cell per axis"),
)
KNOB_BY_NAME = {k.name: k for k in KNOBS}


# --------------------------------------------------------------------------------------------
# What happened, and its outcome
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class CellRun:
    """What one cell did, read from its config check, its process and its run file."""

    refusal: str | None = None  # why the config check refused it (ConfigError.reason)
    refused_key: str | None = None  # the key it refused (ConfigError.key)
    config_warnings: tuple[str, ...] = ()
    timed_out: bool = False
    returncode: int | None = 0
    error_type: str | None = None
    error_message: str | None = None
    error_data: dict = field(default_factory=dict)  # the exception's ERROR_FIELDS it carries
    status: str | None = None  # the run file's status ("complete"; "running" for a partial run)
    frames_planned: int = 0
    frames_completed: int = -1  # the last committed frame (-1: none)
    run_warnings: tuple[str, ...] = ()
    metrics_finite: bool = True  # every committed frame's metrics are finite
    gap_closed_last: float = math.nan
    gap_closed_best: float = math.nan


@dataclass(frozen=True)
class Outcome:
    outcome: str  # one of OUTCOMES
    detail: str  # the warning, the refusal's reason, the stop or the crash, in words
    key: str | None = None  # refused: the key named
    frame: int | None = None  # stopped: the frame
    quantity: str | None = None  # stopped: the quantity


def _signal_name(returncode: int) -> str:
    try:
        return signal.Signals(-returncode).name
    except ValueError:
        return f"signal {-returncode}"


def _classify_error(run: CellRun) -> Outcome:
    """The outcome of a cell whose process raised or ended badly: a stage's refusal, a stop, or a crash."""
    data = run.error_data
    if run.error_type in STAGE_REFUSALS and data.get("key"):
        return Outcome("refused", f"refused by the sampling stage: {run.error_message}", key=data["key"])
    if run.error_type == "MorphDivergenceError":
        frame, quantity = data.get("frame"), data.get("quantity")
        if frame is None or quantity is None:
            return Outcome("crash", f"a divergence that names no frame and quantity: {run.error_message}")
        if run.frames_completed != frame - 1:
            return Outcome("crash", f"stopped at frame {frame} but frames 0..{run.frames_completed} are kept: "
                                    f"{run.error_message}")
        if not run.metrics_finite:
            return Outcome("crash", f"stopped at frame {frame} with non-finite metrics in the kept frames")
        return Outcome("stopped", run.error_message or "", frame=int(frame), quantity=str(quantity))
    if run.error_type is not None:
        return Outcome("crash", f"{run.error_type}: {run.error_message}")
    how = _signal_name(run.returncode) if run.returncode < 0 else f"exit code {run.returncode}"
    return Outcome("crash", f"the process ended ({how}) without a result")


def classify(run: CellRun, converged_gap: float = CONVERGED_GAP) -> Outcome:
    """The one outcome of a cell (see the module docstring); crash and hang say what went wrong."""
    warned = run.config_warnings + run.run_warnings
    if run.refusal is not None:
        if run.refused_key is None:
            return Outcome("crash", f"a refusal that names no config key: {run.refusal}")
        return Outcome("refused", run.refusal, key=run.refused_key)
    if run.timed_out:
        return Outcome("hang", f"no result within its wall-clock limit (after frame {run.frames_completed})")
    if run.error_type is not None or run.returncode not in (0, None):
        return _classify_error(run)
    if run.status != "complete" or run.frames_completed != run.frames_planned:
        return Outcome("crash", f"the run reports {run.status!r} after {run.frames_completed} of "
                                f"{run.frames_planned} frames")
    if not (run.metrics_finite and math.isfinite(run.gap_closed_last)):
        return Outcome("crash", "the run reports success with a non-finite metric (a silent NaN)")
    if warned:
        return Outcome("warned", "; ".join(warned))
    if run.gap_closed_last >= converged_gap:
        return Outcome("converged", f"closed {100 * run.gap_closed_last:.0f} % of the gap")
    return Outcome("not converged", f"ran every frame but closed {100 * run.gap_closed_last:.0f} % of the gap "
                                    f"(converged: at least {100 * converged_gap:.0f} %)")


# --------------------------------------------------------------------------------------------
# The map: table and figure
# --------------------------------------------------------------------------------------------

OUTCOME_COLORS = {"converged": "#4daf4a", "not converged": "#c7e9c0", "warned": "#ff9f1c", "refused": "#9ecae1",
                  "stopped": "#b07cc6", "crash": "#e41a1c", "hang": "#000000"}
TABLE_COLUMNS = ("knob", "key", "value", "particles", "frames", "outcome", "gap_closed_last_%", "gap_closed_best_%",
                 "detail", "wall_s")


def map_table(records: list[dict]):
    """The map as a DataFrame, one row per cell in knob order, then value order."""
    import pandas as pd

    rank = {k.name: i for i, k in enumerate(KNOBS)}
    rows = []
    for r in sorted(records, key=lambda r: (rank.get(r["knob"], len(rank)), r["order"])):
        frames = "" if r["frames_planned"] is None else (
            f"{r['frames_completed']}/{r['frames_planned']}" + (f" ({r['note']})" if r["note"] else ""))
        rows.append({"knob": r["knob"], "key": r["key"], "value": r["value"],
                     "particles": "" if r["n_particles"] is None else f"{r['n_particles']:,}",
                     "frames": frames, "outcome": r["outcome"],
                     "gap_closed_last_%": 100 * r["gap_closed_last"], "gap_closed_best_%": 100 * r["gap_closed_best"],
                     "detail": _short_detail(r), "wall_s": round(r["wall_s"], 1)})
    return pd.DataFrame(rows, columns=list(TABLE_COLUMNS))


def _short_detail(r: dict) -> str:
    """The table's detail: the key of a refusal with its reason, a stop's frame and quantity with
    its message, the warning."""
    text = str(r["detail"]).replace("|", "\\|").replace("\n", " ")
    if r["outcome"] == "refused":
        return f"`{r['refused_key']}`: {text}"
    if r["outcome"] == "stopped":
        return f"frame {r['stop_frame']}, {r['stop_quantity']}: {text}"
    return text


def _annotation(r: dict) -> str:
    o = r["outcome"]
    if o == "refused":
        return f"refused\n{r['refused_key']}"
    if o == "stopped":
        return f"stopped\n{r['stop_quantity']} @ frame {r['stop_frame']}"
    if o in FAILURES:
        return o.upper()
    gap = f"{100 * r['gap_closed_last']:.0f} %"
    return f"warned\n{gap}" if o == "warned" else gap


def plot_map(records: list[dict], png: str | Path, title: str = "") -> None:
    """Knobs as rows, their values as columns, each cell coloured by its outcome and annotated
    with the gap closed at the last frame, the key of a refusal or the frame of a stop."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch, Rectangle

    rows = [k for k in KNOBS if any(r["knob"] == k.name for r in records)]
    by_knob = {k.name: sorted((r for r in records if r["knob"] == k.name), key=lambda r: r["order"]) for k in rows}
    ncols = max(len(v) for v in by_knob.values())
    fig, ax = plt.subplots(figsize=(1.55 * ncols + 2.6, 0.78 * len(rows) + 1.5))
    for i, knob in enumerate(rows):
        y = len(rows) - 1 - i
        for j, r in enumerate(by_knob[knob.name]):
            ax.add_patch(Rectangle((j, y), 0.96, 0.92, facecolor=OUTCOME_COLORS[r["outcome"]],
                                   edgecolor="k", lw=2.0 if r["is_default"] else 0.3))
            dark = r["outcome"] in ("hang", "crash", "stopped")
            ax.text(j + 0.48, y + 0.68, r["value"].replace(" (default)", "*"), ha="center", va="center",
                    fontsize=6.5, color="w" if dark else "k")
            ax.text(j + 0.48, y + 0.3, _annotation(r), ha="center", va="center", fontsize=6.5,
                    color="w" if dark else "k", fontweight="bold")
    ax.set_xlim(-0.05, ncols)
    ax.set_ylim(-0.05, len(rows))
    ax.set_yticks([len(rows) - 1 - i + 0.46 for i in range(len(rows))])
    ax.set_yticklabels([k.title for k in rows], fontsize=8)
    ax.set_xticks([])
    for s in ax.spines.values():
        s.set_visible(False)
    present = [o for o in OUTCOMES if any(r["outcome"] == o for r in records)]
    ax.legend(handles=[Patch(facecolor=OUTCOME_COLORS[o], edgecolor="k", lw=0.3, label=o) for o in present],
              loc="upper center", bbox_to_anchor=(0.5, -0.01), ncol=len(present), fontsize=7, frameon=False)
    ax.set_title(title or "stability map: one knob at a time from the default (* bold border)", fontsize=9)
    fig.tight_layout()
    fig.savefig(png, dpi=130)
    plt.close(fig)


def build_map(records: list[dict], out_dir: str | Path, title: str = ""):
    """Write stability_map.csv, stability_map.md and stability_map.png; return the table. The
    markdown says how many cells ended in each outcome; a crash or a hang is named first."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    df = map_table(records)
    df.to_csv(out / "stability_map.csv", index=False)
    counts = df["outcome"].value_counts()
    summary = ", ".join(f"{o} {int(counts[o])}" for o in OUTCOMES if o in counts)
    failures = df[df["outcome"].isin(FAILURES)]
    head = f"{len(df)} cells: {summary}.\n\n"
    if len(failures):
        head += ("**Cells that crashed or hung** (a bug: each must become a refusal, a warning or a named stop):\n\n"
                 + markdown_table(failures) + "\n")
    (out / "stability_map.md").write_text(head + markdown_table(df))
    plot_map(records, out / "stability_map.png", title)
    return df
