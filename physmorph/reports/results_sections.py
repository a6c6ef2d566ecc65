"""The sections of a profile's results page (physmorph.reports.userdocs.results_markdown), each from one
of the CSV tables physmorph.reports.tables writes: how far each run got, the paper's directions, its main
table, the component and drag ablations, source invariance, persistence, and the cross-shape and
letter morphs. A table's rows whose runs the profile does not have are left out, and a section
with none."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from physmorph.base.markdown import markdown_table


def fmt(v, digits: int = 4) -> str:
    if v is None or isinstance(v, float) and not np.isfinite(v):
        return ""
    if isinstance(v, (float, np.floating)):
        return f"{v:.{digits}g}"
    return str(v)


def pct(v) -> str:
    return "" if v is None or not np.isfinite(float(v)) else f"{float(v):.1f} %"


def md_table(header: list[str], rows: list[list[str]]) -> str:
    """A GitHub table of cells already formatted as text."""
    return markdown_table(pd.DataFrame(rows, columns=header))


def read_table(tables_dir: Path, name: str) -> pd.DataFrame:
    path = tables_dir / f"{name}.csv"
    if not path.exists():
        raise FileNotFoundError(f"{path}: missing; build the tables first (snakemake --cores 2 tables)")
    try:
        return pd.read_csv(path)
    except pd.errors.EmptyDataError:
        return pd.DataFrame()


def with_data(df: pd.DataFrame, column: str) -> pd.DataFrame:
    """The rows of ``df`` with a number in ``column`` (a table lists the paper's cases whether or not
    this profile ran them; their measured columns are empty, or absent when none was run)."""
    if column not in df:
        return df.iloc[0:0]
    return df[pd.to_numeric(df[column], errors="coerce").notna()]


# the bar the body is held to (the share of the target's volume both cover, 1 = the target's own
# sampling): a run whose silhouettes closed most of their gap with a body below it is named as such
BODY_VOLUME_IOU = 0.85
SILHOUETTES_CLOSED_PERCENT = 90.0


def convergence_section(conv: pd.DataFrame) -> list[str]:
    """The results page's "How far each run got" (the silhouettes, frame by frame) and "The body in
    3D" (the last frame's body, turned around): one row per run of the convergence table each."""
    out: list[str] = []
    out.append("## How far each run got\n")
    out.append("Share of the reachable gap closed at the best and the last frame (100 % = the target's own "
               "particles rendered at rest), the drop between them (points), and how still the last 10 frames "
               "are (swing: the median frame-to-frame change of the alpha MSE; sign changes: how often it "
               "turned). The gap is measured on the ring cameras' silhouettes: the next section turns the body "
               "around.\n")
    rows = []
    for _, r in conv.iterrows():
        rows.append([str(r["experiment"]), str(r["method"]), f"{pct(r['closed_best_%'])} (frame {int(r['best_frame'])})",
                     pct(r["closed_final_%"]), pct(r.get("drop_points", np.nan)).replace(" %", ""),
                     pct(r.get("swing_%", np.nan)), pct(r.get("sign_changes", np.nan)).replace(".0 %", "")])
    out.append(md_table(["experiment", "method", "closed, best (frame)", "closed, last", "drop", "swing",
                         "sign changes"], rows))
    out += body_section(conv)
    return out


def body_section(conv: pd.DataFrame) -> list[str]:
    """The results page's "The body in 3D": each run's volume IoU at the first and last frame and its
    packing, and for the exported full runs the last surface's measures; the runs whose silhouettes
    closed their gap with a body short of BODY_VOLUME_IOU named below the table."""
    out = ["## The body in 3D\n",
           "The volume IoU at the first and last frame (the share of the target's volume both cover, 1 = the "
           "target's own sampling), the share of the mass packed above twice the target's density at the end, "
           "and, for the exported full runs, the last surface's: stray share (mass more than 2 cells outside the "
           "target), mass outside the largest connected body, genus against the target mesh's (tunnels at least about a "
           "cell wide; a spurious one adds one), mean and 95th-percentile distance to the target mesh (cells) and roughness (the "
           "area its lumps add).\n"]
    rows, short = [], []
    for _, r in conv.iterrows():
        genus = r.get("genus", np.nan)
        target_genus = r.get("target_genus", np.nan)
        genus_text = "" if not np.isfinite(genus) else "open" if genus < 0 else (
            f"{int(genus)} ({int(target_genus)})" if np.isfinite(target_genus) else f"{int(genus)}")
        rows.append([str(r["experiment"]), f"{fmt(r['volume_iou_0'], 2)} -> {fmt(r['volume_iou_final'], 2)}",
                     pct(100 * r["overfilled_mass_final"]) if np.isfinite(r["overfilled_mass_final"]) else "",
                     pct(r.get("stray_%", np.nan)), pct(r.get("outside_body_%", np.nan)), genus_text,
                     f"{fmt(r.get('surface_dx', np.nan), 2)} / {fmt(r.get('surface_p95_dx', np.nan), 2)}"
                     if np.isfinite(r.get("surface_dx", np.nan)) else "", pct(r.get("rough_%", np.nan))])
        if r["closed_final_%"] >= SILHOUETTES_CLOSED_PERCENT and r["volume_iou_final"] < BODY_VOLUME_IOU:
            short.append(f"{r['experiment']} ({pct(r['closed_final_%'])} of the gap, volume IoU "
                         f"{fmt(r['volume_iou_final'], 3)})")
    out.append(md_table(["experiment", "volume IoU", "overfilled", "stray", "outside the body", "genus (target)",
                         "surface, mean / 95 % (cells)", "roughness"], rows))
    if short:
        out.append(f"Silhouettes closed, body short: {len(short)} run(s) closed at least "
                   f"{SILHOUETTES_CLOSED_PERCENT:.0f} % of their silhouettes' gap with a volume IoU below "
                   f"{BODY_VOLUME_IOU}: {', '.join(short)}.\n")
    return out


def paper_sections(direc: pd.DataFrame, main: pd.DataFrame, source: pd.DataFrame,
                    plast: pd.DataFrame) -> list[str]:
    """The results page's sections beside the paper's: its three directions, its main table, source
    invariance and persistence. Rows whose runs this profile does not have are left out, and a
    section with none."""
    out: list[str] = []
    direc = with_data(direc, "ours")
    if len(direc):
        out.append("## The paper's three directions\n")
        noisy = "noise" in direc and direc["noise"].notna().any()
        out.append("Each row compares the paper's choice (ours) with its baseline; lower is better, the margin is "
                   "baseline minus ours, and `holds` is yes when ours is lower"
                   + (" by more than the noise: the same measure's spread between two runs of one experiment "
                      "from two particle samples (`tables.noise`), `within noise` where the margin is smaller; a row "
                      "with no noise (the rebound after the release: the two runs are not released) says yes "
                      "where ours is lower.\n"
                      if noisy else " (no noise measured: `tables.noise` names no pair of runs here).\n"))
        rows = [[str(r["direction"]), str(r["case"]), str(r["measure"]), fmt(r["ours"]), fmt(r["baseline"]),
                 pct(r["ours_vs_baseline_%"])]
                + ([fmt(r.get("margin", np.nan)), fmt(r.get("noise", np.nan))] if noisy else [])
                + [fmt(r["holds"]) if isinstance(r["holds"], str) else "",
                   fmt(r["paper"]) if isinstance(r["paper"], str) else ""] for _, r in direc.iterrows()]
        out.append(md_table(["direction", "case", "measure", "ours", "baseline", "gain"]
                            + (["margin", "noise"] if noisy else []) + ["holds", "paper"], rows))

    main, source, plast = with_data(main, "ours"), with_data(source, "best"), with_data(plast, "rebound_%")
    if len(main):
        out.append("## Main table: full vs physics-only at the matched frame\n")
        rows = [[str(r["target"]), fmt(r.get("frame"), 3), fmt(r.get("physics_only")), fmt(r.get("ours")),
                 pct(r.get("improvement_%", np.nan)), f"{r['paper_improvement_%']:+g} %"]
                for _, r in main.iterrows()]
        out.append(md_table(["target", "matched frame", "physics-only", "full", "improvement", "paper"], rows))

    if len(source):
        out.append("## Source invariance\n")
        rows = [[str(r["experiment"]), fmt(r["best"]), fmt(r["paper_best"]), pct(r["closed_best_%"])]
                for _, r in source.iterrows() if r["experiment"] not in ("mean", "std")]
        out.append(md_table(["source -> bunny", "best alpha MSE", "paper", "closed, best"], rows))

    if len(plast):
        out.append("## Does the morph persist?\n")
        rows = []
        for _, r in plast.iterrows():
            rows.append([str(r["experiment"]), str(r["variant"]), pct(r.get("rebound_%", np.nan)),
                         pct(r.get("release_rebound_%", np.nan)),
                         fmt(r.get("release_frames", np.nan), 3)])
        out.append(md_table(["experiment", "variant", "rebound in the run", "rebound released", "release frames"],
                            rows))
    return out


def optional_table(tables_dir: Path, name: str) -> pd.DataFrame:
    """The table ``name`` of ``tables_dir``, empty where it was not built (tables made before it existed)."""
    return read_table(tables_dir, name) if (Path(tables_dir) / f"{name}.csv").exists() else pd.DataFrame()


def _closed(conv: pd.DataFrame, experiment: str) -> tuple[str, str]:
    """The convergence table's share of the gap closed at the best and the last frame of one run."""
    row = conv[conv["experiment"] == experiment] if "experiment" in conv else conv.iloc[0:0]
    if not len(row):
        return "", ""
    return pct(row["closed_best_%"].iloc[0]), pct(row["closed_final_%"].iloc[0])


def ablation_sections(tables_dir: Path, conv: pd.DataFrame) -> list[str]:
    """The results page's component ablation (drag 0.5), drag ablation and cross-shape / letter
    morphs: each run's alpha MSE beside the paper's, and its share of the gap from ``conv`` (the
    paper's alpha MSE is on its own renderer's scale; the share compares across both)."""
    out: list[str] = []
    comp = with_data(optional_table(tables_dir, "ablation_components"), "alpha_mse")
    if len(comp):
        out.append("## Component ablation (drag 0.5)\n")
        out.append("The last frame's alpha MSE and the physics loss's decrease over the run (delta E), "
                   "beside the paper's.\n")
        rows = [[str(r["experiment"]), fmt(r["alpha_mse"]), fmt(r["paper_alpha_mse"]), pct(r["delta_E_%"]),
                 pct(r["paper_delta_E_%"]), _closed(conv, r["experiment"])[1]] for _, r in comp.iterrows()]
        out.append(md_table(["experiment", "alpha MSE, last", "paper", "delta E", "paper delta E", "closed, last"],
                            rows))
    drag = with_data(optional_table(tables_dir, "ablation_drag"), "best")
    if len(drag):
        out.append("## Drag ablation\n")
        out.append("iso -> bunny at the profile's drag and at drag 0.5 (`_d05`): best and last alpha MSE "
                   "beside the paper's.\n")
        rows = [[str(r["experiment"]), fmt(r["best"]), fmt(r["final"]), fmt(r["paper_best"]), fmt(r["paper_final"]),
                 *_closed(conv, r["experiment"])] for _, r in drag.iterrows()]
        out.append(md_table(["experiment", "best alpha MSE", "last", "paper best", "paper last", "closed, best",
                             "closed, last"], rows))
    shapes = with_data(optional_table(tables_dir, "shapes"), "best")
    if len(shapes):
        out.append("## Cross-shape and letter morphs\n")
        out.append("Best and last alpha MSE, the share of the gap closed, and the change of the body's "
                   "volume from the first frame to the last.\n")
        rows = [[str(r["experiment"]), fmt(r["best"]), fmt(r["final"]), *_closed(conv, r["experiment"]),
                 f"{r['volume_change_%']:+.1f} %"] for _, r in shapes.iterrows()]
        out.append(md_table(["experiment", "best alpha MSE", "last", "closed, best", "closed, last",
                             "volume change"], rows))
    return out
