"""The user documentation that is generated, so it cannot go stale.

* ``results_markdown`` / ``write_results_doc``: a profile's numbers (docs/results.md for the default
  profile) from ``results/{profile}/tables/`` and its figures.
* ``config_reference``: config/README.md, every key of the config schema with its meaning, unit,
  range, type and default, all from the settings' declarations (read by physmorph.settings.docs).
* ``write_tradeoff_doc``: docs/tradeoff.md, the speed/accuracy study of each profile that has one
  (``results/{profile}/tradeoff/tradeoff.csv``) and one Pareto figure with every scale.
* ``output_captions`` / ``write_captions``: the HTML report's caption of each table and figure, taken
  from docs/outputs.md (the paragraph after each ``### `name` `` heading), so the two say the same.

The functions write where their caller says. The command line writes into a checkout (``--root``,
default: the one holding this package): ``python -m physmorph.reports.userdocs results default`` (writes
docs/results.md and copies the figures to docs/images/), ``python -m physmorph.reports.userdocs config``
(config/README.md), ``python -m physmorph.reports.userdocs captions`` (workflow/report/captions/),
``python -m physmorph.reports.userdocs tradeoff default mid`` (docs/tradeoff.md, docs/images/pareto_scales.png),
``python -m physmorph.reports.userdocs readme`` (README.md's profile table, from the pages' records:
physmorph.reports.page_meta) and ``python -m physmorph.reports.userdocs check`` (which pages ran another method).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import re
import shutil
from pathlib import Path

import numpy as np
import pandas as pd

from physmorph.settings.docs import schema_keys
from physmorph.reports.figures import figure_runs
from physmorph.base.markdown import markdown_table
from physmorph.reports.metrics import FIGURE_NAMES, TABLE_NAMES
from physmorph.reports.page_meta import PageProvenance, block, check_pages, from_checkout, from_runs, jobs_wall_time_s, \
    results_summary, update_readme
from physmorph.reports.results_sections import ablation_sections, convergence_section, fmt, md_table, \
    paper_sections, read_table
from physmorph.studies.stability_map import FAILURES, MAP_EXPERIMENT, OUTCOMES

FIGURE_TITLES = {
    "sequences_main": "iso -> bunny, cow, duck (full method), frames 0 to the last and the target",
    "sequences_cross_shape": "cross-shape morphs (full method) and their targets",
    "sequences_letters": "letters (full method) and their targets",
    "sequences_other": "the profile's other targets (full method), frames 0 to the last and the target",
    "drag_ablation": "drag ablation, iso -> bunny: alpha MSE per frame",
    "trajectory_divergence": "physics-only vs full, iso -> duck: mass loss and alpha MSE per frame",
    "trajectory_frames": "physics-only vs full, iso -> duck, frames 10, 15 and 19",
    "plasticity_effect": "with (full) and without (f_inject) plasticity, iso -> bunny",
    "optimization_traces": "iso -> bunny (full): alpha MSE, gradient norm and losses per frame",
    "gradient_coverage": "which particles the render gradient reaches with 1, 4 and 8 cameras",
}


# --------------------------------------------------------------------------------------------
# docs/results.md
# --------------------------------------------------------------------------------------------

def results_markdown(tables_dir: str | Path, profile: str, figures: dict[str, str] | None = None,
                     date: str | None = None, command: str | None = None, outputs_link: str = "outputs.md",
                     provenance: PageProvenance | None = None, title: str | None = None) -> str:
    """A profile's results as Markdown, from the CSV tables in ``tables_dir`` (physmorph.reports.tables).
    ``figures``: figure name -> link to its image (relative to the page); ``date``: when the tables
    were made (default: the convergence table's modification date); ``provenance``: the code and
    method settings of the runs (default: this checkout's, with the shipped method)."""
    tables_dir = Path(tables_dir)
    conv = read_table(tables_dir, "convergence")
    direc = read_table(tables_dir, "directions")
    source = read_table(tables_dir, "source_invariance")
    plast = read_table(tables_dir, "plasticity")
    timing = read_table(tables_dir, "timing")
    main = read_table(tables_dir, "main")
    if date is None:
        date = _dt.date.fromtimestamp((tables_dir / "convergence.csv").stat().st_mtime).isoformat()
    command = command or f"python -m physmorph.reports.userdocs results {profile}"
    provenance = provenance or from_checkout()
    wall = jobs_wall_time_s(tables_dir.parent)
    out = [f"# {title or f'Results of the `{profile}` profile'}\n",
           f"Generated on {date} by `{command}` from `results/{profile}/{tables_dir.name}/`"
           + f", {provenance.line(profile)} (do not edit by hand: "
           "rebuild the tables, then run the command again). What each table and column means: "
           f"[docs/outputs.md]({outputs_link}).\n"]
    if len(timing):
        particles = sorted({int(p) for p in timing["particles"] if np.isfinite(p) and p > 0})
        frames = sorted({int(f) for f in timing["frames"]})
        span = (f"{particles[0]:,}" if particles[0] == particles[-1] else f"{particles[0]:,}-{particles[-1]:,}"
                ) if particles else "?"
        out.append(f"{len(timing)} runs of {span} particles and {'/'.join(map(str, frames))} frames")
        if np.isfinite(wall):
            out[-1] += f"; the jobs' wall times add up to {wall / 60:.1f} min (results/{profile}/benchmarks/)"
        out[-1] += ".\n"

    out += convergence_section(conv)

    out += paper_sections(direc, main, source, plast)
    out += ablation_sections(tables_dir, conv)

    if len(timing):
        out.append("## Time per frame (seconds, median over runs, each run's mean after frame 0) and memory\n")
        cols = ["physics_s", "render_s", "plasticity_s", "mask_s", "frame_s"]
        full = timing[[c for c in cols if c in timing]]
        out.append(md_table([c[:-2] for c in full.columns] + ["peak RSS, largest run (MB)"],
                          [[fmt(float(np.nanmedian(full[c])), 3) for c in full.columns]
                           + [fmt(float(np.nanmax(timing["peak_rss_mb"])), 4)]]))

    if figures:
        out.append("## Figures\n")
        for name in FIGURE_NAMES:
            if name in figures:
                out.append(f"**{name}**: {FIGURE_TITLES.get(name, name)}.\n\n![{name}]({figures[name]})\n")
    out.append(block("results", profile, provenance, results_summary(tables_dir, wall)))
    return "\n".join(out)


def results_doc_paths(profile: str, docs_dir: str | Path) -> tuple[Path, Path]:
    """Where a profile's results page and its figures go in ``docs_dir``: results.md and images/
    for the default profile, results_{profile}.md and images/{profile}/ for any other, so
    regenerating one profile's page never overwrites another's."""
    docs = Path(docs_dir)
    if profile == "default":
        return docs / "results.md", docs / "images"
    if profile == "paper":  # the paper's scale has its page of that name (also written by paper_main)
        return docs / "paper_scale.md", docs / "images" / profile
    return docs / f"results_{profile}.md", docs / "images" / profile


def write_results_doc(tables_dir: str | Path, out_md: str | Path, profile: str, figures_dir: str | Path | None = None,
                      images_dir: str | Path | None = None, command: str | None = None,
                      provenance: PageProvenance | None = None, title: str | None = None,
                      outputs_md: str | Path | None = None) -> Path:
    """Write ``results_markdown`` to ``out_md``. Figures from ``figures_dir`` are linked; with
    ``images_dir`` they are first copied there (docs/images/ for docs/results.md). ``outputs_md``:
    the guide to the tables (docs/outputs.md) the page links to; None: outputs.md beside the page."""
    out_md = Path(out_md)
    out_md.parent.mkdir(parents=True, exist_ok=True)
    figures = {}
    if figures_dir is not None:
        for name in FIGURE_NAMES:
            src = Path(figures_dir) / f"{name}.png"
            if not src.exists() or figure_runs(src) == []:  # [] : made, with none of its runs in this profile
                continue
            if images_dir is not None:
                Path(images_dir).mkdir(parents=True, exist_ok=True)
                dst = Path(images_dir) / src.name
                shutil.copyfile(src, dst)
                src = dst
            figures[name] = Path(_relpath(src, out_md.parent)).as_posix()
    outputs = "outputs.md" if outputs_md is None else Path(_relpath(outputs_md, out_md.parent)).as_posix()
    text = results_markdown(tables_dir, profile, figures, command=command, outputs_link=outputs,
                            provenance=provenance, title=title)
    tmp = out_md.with_suffix(".partial")
    tmp.write_text(text)
    tmp.replace(out_md)
    return out_md


def write_tradeoff_doc(profiles: list[str], results_root: str | Path, out_md: str | Path, out_png: str | Path,
                       provenance: PageProvenance | None = None) -> Path:
    """docs/tradeoff.md: for each profile whose study exists under ``results_root/{profile}/tradeoff/``
    its ranked points, knob ranking and budget recommendations, and one Pareto figure with every
    scale (``out_png``, linked relative to the page)."""
    from physmorph.studies.tradeoff import pareto_figure, summarize_points, tradeoff_markdown

    frames = {}
    for p in profiles:
        csv = Path(results_root) / p / "tradeoff" / "tradeoff.csv"
        if not csv.exists():
            raise FileNotFoundError(f"{csv}: no speed/accuracy study for profile '{p}' "
                                    f"(snakemake --cores 2 tradeoff, with that profile's --configfile)")
        df = pd.read_csv(csv)
        df[["knob", "value"]] = df[["knob", "value"]].fillna("")  # the base's (written empty)
        # the front and the gains per second from the points' own numbers, by the present rules
        frames[p] = summarize_points(df.drop(columns=["pareto", "gap_gain_per_s"], errors="ignore").to_dict("records"))
    out_md, out_png = Path(out_md), Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    pareto_figure(frames, out_png, "speed / accuracy: one knob at a time around each profile's base")
    date = _dt.date.today().isoformat()
    lines = ["# The speed/accuracy study", "",
             f"Generated {date} by `python -m physmorph.reports.userdocs tradeoff "
             + " ".join(profiles) + "` from each profile's `snakemake --cores 2 tradeoff`. Each point is the base "
             "experiment with one knob changed; times are the morph's frame times on this machine; the gap is "
             "the share of the reachable α-MSE gap closed; Chamfer is in grid cells of the point's own grid. The "
             f"points were {(provenance or from_checkout()).line()} (the bases').", "",
             f"![Pareto front per scale]({_relpath(out_png, out_md.parent)})", ""]
    for p, df in frames.items():
        lines += [f"# Profile `{p}` ({int(df.loc[df['name'] == 'base', 'particles'].iloc[0]):,} particles at the base)", "",
                  tradeoff_markdown(df).replace("## ", "### "), ""]
    lines.append(block("tradeoff", " ".join(profiles), provenance or from_checkout()))
    out_md.write_text("\n".join(lines))
    return out_md


def write_stability_doc(profile: str, results_root: str | Path, out_md: str | Path, out_png: str | Path,
                        provenance: PageProvenance | None = None) -> Path:
    """docs/stability.md: the stability map of ``results_root/{profile}/stability_map/`` (its figure
    copied to ``out_png``), the outcome counts, and every cell's row."""
    src = Path(results_root) / profile / "stability_map"
    csv = src / "stability_map.csv"
    if not csv.exists():
        raise FileNotFoundError(f"{csv}: no stability map for profile '{profile}' "
                                f"(snakemake --cores 2 stability_map, with that profile's --configfile)")
    df = pd.read_csv(csv, keep_default_na=False)
    out_md, out_png = Path(out_md), Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src / "stability_map.png", out_png)
    counts = df["outcome"].value_counts()
    failures = int(df["outcome"].isin(FAILURES).sum())
    knobs = df.groupby("knob", sort=False)["value"].count()
    lines = ["# The stability map of the extremes", "",
             f"Generated {_dt.date.today().isoformat()}"
             + f" by `python -m physmorph.reports.userdocs stability {profile}` from `snakemake --cores 2 stability_map"
             + ("" if profile == "default" else f" --configfile config/{profile}.yaml") + "`, "
             + f"{(provenance or from_checkout()).line(profile)} (the base experiment's).", "",
             "The base experiment (iso → bunny, full method) with one setting at a time moved from the profile's "
             "default to and past its limit. Every cell runs in its own process under a wall-clock limit and "
             "ends in one outcome: **converged** (every frame ran, metrics finite, the last frame closed at "
             "least a quarter of the reachable gap), **not converged** (ran and finite, closed less), "
             "**warned** (ran and finite, with the config's or the run's warning, quoted), **refused** (before "
             "any frame, naming the key), or **stopped** (at a named frame and quantity, every earlier frame "
             "kept in the partial run). **crash** (any other exception, a killed process, lost frames, a "
             "success with a non-finite metric) and **hang** (past the cell's limit) are bugs; "
             "tests/studies/test_extremes.py runs the most extreme cells on every test run.", "",
             f"![stability map]({_relpath(out_png, out_md.parent)})", "",
             f"{len(df)} cells over {len(knobs)} settings ({', '.join(f'{k} {n}' for k, n in knobs.items())}): "
             + ", ".join(f"{o} {int(counts[o])}" for o in OUTCOMES if o in counts)
             + f". Cells that crashed or hung: {failures}.", ""]
    cols = ["knob", "value", "particles", "frames", "outcome", "gap_closed_last_%", "detail", "wall_s"]
    table = df[cols].copy()
    table["gap_closed_last_%"] = [f"{float(v):.0f}" if str(v) not in ("", "nan") else "" for v in table["gap_closed_last_%"]]
    out_md.write_text("\n".join(lines) + "\n" + markdown_table(table.astype(str)) + "\n"
                      + block("stability", profile, provenance or from_checkout()))
    return out_md


def _relpath(path: Path, start: Path) -> str:
    import os

    return os.path.relpath(Path(path).resolve(), Path(start).resolve())


# --------------------------------------------------------------------------------------------
# config/README.md
# --------------------------------------------------------------------------------------------

def _type_text(sub: dict) -> str:
    if "enum" in sub:
        return " \\| ".join(f"`{e}`" for e in sub["enum"])
    if "anyOf" in sub:
        return " or ".join(_type_text(o) for o in sub["anyOf"])
    t = sub.get("type")
    if isinstance(t, list):
        t = t[0]
    if t == "array":
        return "list"
    if t == "object":
        return "mapping"
    return t or "any"


def _default_text(sub: dict) -> str:
    if "default" not in sub:
        return ""
    d = sub["default"]
    if d is None:
        return "`null`"
    if isinstance(d, bool):
        return f"`{str(d).lower()}`"
    if isinstance(d, float):
        return f"`{d:.6g}`"
    return f"`{d}`"


def config_reference() -> str:
    """config/README.md: every schema key with meaning, unit, range, type and default."""
    from physmorph.settings.docs import SECTIONS, field_docs

    keys = schema_keys()
    docs = field_docs()
    missing = [k for k, sub in keys if not docs.get(k, ("",))[0] and k not in SECTIONS]
    if missing:
        raise KeyError(f"config keys declared without a description (setting(...) in their class): {missing}")
    out = ["# Configuration reference\n",
           "Generated from the declarations of the typed settings (`physmorph.settings.workflow.Settings` and its sections: "
           "each field's default, range, unit and meaning, also in `workflow/schemas/config.schema.yaml`) and the "
           "section texts of `physmorph/settings/docs.py` by `python -m physmorph.reports.userdocs config`; do not edit by "
           "hand.\n",
           "A profile is a YAML file merged onto `config/config.yaml` key by key (`--configfile`); single keys "
           "can be set with `--config 'plasticity={eta: 0.1}'`. Every key is checked before any job runs: an unknown "
           "key, a wrong type or a value out of range stops Snakemake with the dotted key. The defaults below "
           "are the dataclasses'; `config/config.yaml` restates them (a test checks they agree). Why each "
           "default was chosen: [docs/method.md](../docs/method.md); the evidence: "
           "[docs/study/](../docs/study/README.md).\n",
           "Changing a key reruns exactly the jobs that read it (see them with `snakemake -n`).\n"]
    groups: dict[str, list[tuple[str, dict]]] = {}
    for key, sub in keys:
        top = key.split(".")[0]
        section = top if "." in key or top in SECTIONS and top != "" else ""
        if key in SECTIONS:
            continue
        groups.setdefault(section, []).append((key, sub))
    for section in [s for s in SECTIONS if s in groups]:
        out.append(f"## {section or 'Top level'}\n")
        out.append(SECTIONS[section] + "\n")
        rows = []
        for key, sub in groups[section]:
            meaning, unit, rng = docs[key]
            cells = [f"`{key}`", meaning, unit, rng, _type_text(sub), _default_text(sub)]
            # a literal | in a description would split its cell: escaped, as the type column's are
            rows.append("| " + " | ".join(re.sub(r"(?<!\\)\|", r"\\|", c) for c in cells) + " |")
        out.append("| key | meaning | unit | range | type | default |\n|---|---|---|---|---|---|\n"
                   + "\n".join(rows) + "\n")
    return "\n".join(out)


# --------------------------------------------------------------------------------------------
# Report captions from docs/outputs.md
# --------------------------------------------------------------------------------------------

def output_captions(outputs_md: str | Path) -> dict[str, str]:
    """name -> caption: the first paragraph after each ``### `name` `` heading of docs/outputs.md."""
    text = Path(outputs_md).read_text()
    out = {}
    for m in re.finditer(r"^### `([A-Za-z0-9_]+)`[^\n]*\n+(.+?)(?:\n\s*\n|\Z)", text, flags=re.M | re.S):
        out[m[1]] = " ".join(line.strip() for line in m[2].splitlines())
    return out


def caption_rst(caption: str) -> str:
    """A caption as reStructuredText (Markdown code spans and links made plain)."""
    text = re.sub(r"\[([^\]]+)\]\([^)]+\)", r"\1", caption)
    text = re.sub(r"(?<!`)`([^`]+)`(?!`)", r"``\1``", text)
    return text.replace("*", "") + "\n"


def write_captions(outputs_md: str | Path, out_dir: str | Path) -> list[Path]:
    """One caption file per table and figure (workflow/report/captions/{name}.rst)."""
    captions = output_captions(outputs_md)
    missing = [n for n in (*TABLE_NAMES, *FIGURE_NAMES) if n not in captions]
    if missing:
        raise KeyError(f"{outputs_md}: no '### `name`' section for {missing}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name in (*TABLE_NAMES, *FIGURE_NAMES):
        path = out / f"{name}.rst"
        path.write_text(caption_rst(captions[name]))
        paths.append(path)
    return paths


def runs_provenance(tables_dir: str | Path, runs_dir: str | Path) -> PageProvenance | None:
    """The provenance of the runs behind ``tables_dir`` (its timing table's experiments in ``runs_dir``)."""
    return from_runs(Path(runs_dir) / f"{exp}.h5" for exp in read_table(Path(tables_dir), "timing").get("experiment", []))


def profile_provenance(config_files: list[str | Path], experiment: str) -> PageProvenance:
    """This checkout with the method of ``experiment`` in the config merged from ``config_files``:
    for a page whose cells vary the method on purpose (the stability map's base experiment)."""
    from physmorph.settings.workflow import load_settings
    from physmorph.settings.params import to_plain

    settings = load_settings(*config_files)
    return from_checkout(to_plain(settings.experiment_config(experiment)))


def tradeoff_provenance(profiles: list[str], results_root: str | Path) -> PageProvenance | None:
    """The provenance of the speed/accuracy points of ``profiles``: the commits of every point,
    the method of the bases (the points move one knob each, some of them the method's)."""
    files, bases = [], []
    for p in profiles:
        csv = Path(results_root) / p / "tradeoff" / "tradeoff.csv"
        if csv.exists():
            files += [csv.parent / "runs" / f"{name}.h5" for name in pd.read_csv(csv)["name"]]
            bases.append(csv.parent / "runs" / "base.h5")
    every, base = from_runs(files, noun="point"), from_runs(bases)
    if every is None or base is None:
        return every or base
    return PageProvenance(every.commit, every.dirty, base.method)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m physmorph.reports.userdocs", description=__doc__.split("\n")[0])
    parser.add_argument("--root", type=Path, default=Path(__file__).resolve().parents[2],
                        help="the checkout whose results/ and config/ are read and whose docs/, config/README.md, "
                             "README.md and workflow/report/captions/ are written (default: the one holding physmorph)")
    sub = parser.add_subparsers(dest="what", required=True)
    res = sub.add_parser("results", help="docs/results.md (docs/results_{profile}.md for another profile, "
                                         "docs/paper_scale.md for paper) from results/{profile}/tables/")
    res.add_argument("profile", nargs="?", default="default")
    res.add_argument("--out", default=None, help="default: docs/results.md, or docs/results_{profile}.md")
    res.add_argument("--images", default=None,
                     help="copy the profile's figures here and link them ('' links them in place); "
                          "default: docs/images/, or docs/images/{profile}/")
    pm = sub.add_parser("paper_main", help="docs/paper_scale.md from results/{profile}/main_tables/ and main_figures/ "
                                           "(the main table's six runs alone; `results paper` writes it from every run)")
    pm.add_argument("profile", nargs="?", default="paper")
    sub.add_parser("config", help="config/README.md from the settings")
    sub.add_parser("captions", help="workflow/report/captions/ from docs/outputs.md")
    tr = sub.add_parser("tradeoff", help="docs/tradeoff.md from results/{profile}/tradeoff/ of each profile")
    tr.add_argument("profiles", nargs="+")
    st = sub.add_parser("stability", help="docs/stability.md from results/{profile}/stability_map/")
    st.add_argument("profile", nargs="?", default="test")
    sub.add_parser("check", help="list the pages under docs/ made with other method settings than the shipped "
                                 "ones (exit 1 when the default profile's page is one)")
    sub.add_parser("readme", help="README.md's profile table from the results pages under docs/")
    return parser


def _results_page(args, root: Path) -> Path:
    """The ``results`` command: a profile's page, and for the default profile the README's picture."""
    docs, tree = root / "docs", root / "results" / args.profile
    out_md, images = results_doc_paths(args.profile, docs)
    out_md = args.out or out_md
    images = images if args.images is None else (args.images or None)
    path = write_results_doc(tree / "tables", out_md, args.profile, tree / "figures", images,
                             command=f"python -m physmorph.reports.userdocs results {args.profile}",
                             provenance=runs_provenance(tree / "tables", tree / "runs"),
                             outputs_md=docs / "outputs.md")
    if args.profile == "default":  # the README's opening picture
        _readme_picture(root, tree)
    return path


def _readme_picture(root: Path, tree: Path) -> None:
    """The default profile's best-looking honest run's video as README.md's GIF, with its numbers
    (physmorph.reports.readme_picture)."""
    from physmorph.reports.export.video import write_gif
    from physmorph.reports.readme_picture import PICTURE, caption, pick_run, update_readme_picture
    from physmorph.settings.workflow import load_settings

    row = pick_run(tree / "tables" / "convergence.csv", tree / "videos")
    if row is None:
        return
    exp = load_settings(root / "config" / "config.yaml").experiment(row["experiment"])
    print(f"wrote {write_gif(tree / 'videos' / (row['experiment'] + '.mp4'), root / PICTURE)}")
    update_readme_picture(root / "README.md", caption(row, exp.source, exp.target, "default"))


def main(argv: list[str] | None = None) -> None:
    """The command line (module docstring); every path it reads or writes is under ``--root``."""
    args = _parser().parse_args(argv)
    root = Path(args.root)
    docs, results = root / "docs", root / "results"
    if args.what == "check":
        lines, default_bad = check_pages(docs)
        print("\n".join(lines) if lines else "every page under docs/ was made with the shipped method settings")
        raise SystemExit(1 if default_bad else 0)
    if args.what == "results":
        path = _results_page(args, root)
    elif args.what == "paper_main":
        tree = results / args.profile
        path = write_results_doc(tree / "main_tables", docs / "paper_scale.md", args.profile,
                                 tree / "main_figures", docs / "images" / args.profile,
                                 command=f"python -m physmorph.reports.userdocs paper_main {args.profile}",
                                 provenance=runs_provenance(tree / "main_tables", tree / "runs"),
                                 title=f"The main table at the `{args.profile}` profile's scale",
                                 outputs_md=docs / "outputs.md")
    elif args.what == "config":
        path = root / "config" / "README.md"
        path.write_text(config_reference())
    elif args.what == "tradeoff":
        path = write_tradeoff_doc(args.profiles, results, docs / "tradeoff.md", docs / "images" / "pareto_scales.png",
                                  provenance=tradeoff_provenance(args.profiles, results))
    elif args.what == "stability":
        profile_yaml = root / "config" / f"{args.profile}.yaml"
        files = [root / "config" / "config.yaml"] + ([profile_yaml] if profile_yaml.exists() else [])
        path = write_stability_doc(args.profile, results, docs / "stability.md", docs / "images" / "stability_map.png",
                                   provenance=profile_provenance(files, MAP_EXPERIMENT))
    elif args.what == "readme":
        path = root / "README.md"
        update_readme(path, docs)
    else:
        path = root / "workflow" / "report" / "captions"
        write_captions(docs / "outputs.md", path)
    print(f"wrote {path}")


if __name__ == "__main__":  # pragma: no cover
    main()
