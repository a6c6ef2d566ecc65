"""The workflow's report and study stages (physmorph.stages holds the data and morph stages): the
tables, figures, results page and trade-off study of a profile, each an entry point that a
three-line script in workflow/scripts/ calls, writing the job's log (physmorph.stages.stage_log)."""

from __future__ import annotations

import json
from pathlib import Path

from physmorph.settings.sections import TargetConfig
from physmorph.stages import stage_log, typed


def tables_stage(names: list[str], runs: list[str], layout: str, out_dir: str, log=None,
                 exported: dict[str, str] | None = None, noise: list[str] | None = None) -> dict:
    """``layout``: the YAML naming the runs of each table and the paper's numbers (physmorph.reports.layout);
    ``exported``: run name -> its exported meshes' folder (their measures.csv); ``noise``: the two
    runs whose spread is the directions table's noise (config tables.noise)."""
    from physmorph.reports.layout import load_layout
    from physmorph.reports.tables import build_tables

    measures = {n: str(Path(d) / "measures.csv") for n, d in (exported or {}).items()}
    with stage_log(log):
        return build_tables(dict(zip(names, runs)), out_dir, load_layout(layout), measures, tuple(noise or ()))


def figures_stage(names: list[str], runs: list[str], shapes: list[str], targets: list[str], target,
                  layout: str, out_dir: str, log=None, figures: list[str] | None = None) -> list:
    """``figures``: the figures to make (default: every one, physmorph.reports.metrics.FIGURE_NAMES)."""
    from physmorph.reports.figures import build_figures
    from physmorph.reports.layout import load_layout
    from physmorph.reports.metrics import FIGURE_NAMES

    t = typed(TargetConfig, target, "target")
    with stage_log(log):
        return build_figures({n: Path(p) for n, p in zip(names, runs)}, {s: Path(p) for s, p in zip(shapes, targets)},
                             t, Path(out_dir), load_layout(layout), tuple(figures or FIGURE_NAMES))


def results_doc_stage(tables_dir: str, figures_dir: str, output: str, profile: str, log=None):
    """The profile's results page (physmorph.reports.userdocs.write_results_doc): its tables' numbers and its
    figures, linked in place, and a link to the guide to the tables, docs/outputs.md of the
    directory the workflow runs in (its checkout)."""
    from physmorph.reports.userdocs import write_results_doc

    with stage_log(log):
        return write_results_doc(tables_dir, output, profile, figures_dir,
                                 command=f"snakemake --cores 2 results_page (profile {profile})",
                                 outputs_md=Path("docs") / "outputs.md")


def tradeoff_stage(points, names: list[str], runs: list[str], out_dir: str, domain_width: float, log=None):
    """``points``: {name: TradeoffPoint fields} (or its JSON), as the workflow's params hold them."""
    from physmorph.studies.tradeoff import build_tradeoff
    from physmorph.settings.study_points import TradeoffPoint

    if isinstance(points, str):
        points = json.loads(points)
    pts = {n: p if isinstance(p, TradeoffPoint) else TradeoffPoint(**p) for n, p in points.items()}
    with stage_log(log):
        return build_tradeoff(pts, {n: Path(p) for n, p in zip(names, runs)}, Path(out_dir), float(domain_width))
