"""What a generated page records about itself, and what reads it back.

Every generated page (docs/results*.md, docs/paper_scale.md, docs/tradeoff.md, docs/stability.md)
ends with one HTML comment, ``<!-- physmorph-page {...} -->``: its profile, the commit(s) of the
runs it was made from, whether any of them came from a tree with local changes, their method
settings (physmorph.records.provenance) and, for a results page, the summary the README's profile table
shows. So the README table and ``python -m physmorph.reports.userdocs check`` need only the pages: they work
on a fresh clone with no results/.
"""

from __future__ import annotations

import json
import re
from collections import Counter
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pandas as pd

from physmorph.records.provenance import differing_keys, git_state, merge_settings, method_settings, method_sha

BLOCK_RE = re.compile(r"<!-- physmorph-page (\{.*\}) -->")


CONFIG_DIR = Path(__file__).resolve().parents[2] / "config"


@lru_cache(maxsize=16)
def shipped_method_settings(profile: str = "default") -> dict[str, Any]:
    """The method settings this code ships for ``profile`` (what its page's method is compared
    with): MorphConfig's defaults, which config/config.yaml states, and where the profile has a file
    of its own (config/{profile}.yaml, declaring that profile) the method keys that file sets on
    purpose, as the paper profile sets the volume term's weight: its first full experiment's settings."""
    import yaml

    from physmorph.settings.morph import MorphConfig

    own = CONFIG_DIR / f"{profile}.yaml"
    if profile == "default" or not own.is_file() or (yaml.safe_load(own.read_text()) or {}).get("profile") != profile:
        return method_settings(json.loads(json.dumps(asdict(MorphConfig(method="full")), default=str)))
    from physmorph.settings.params import to_plain
    from physmorph.settings.workflow import load_settings

    settings = load_settings(CONFIG_DIR / "config.yaml", own)
    full = next(name for name, exp in settings.experiments.items() if exp.method == "full")
    return method_settings(to_plain(settings.experiment_config(full)))


@dataclass
class PageProvenance:
    """The code and method behind a page's numbers."""

    commit: str  # "abc1234", or "abc1234 (12 runs), e4f5a6b (6 runs)"; "unknown" without git
    dirty: str  # "yes": some input was made by a tree with local changes; "no"; "unknown": not recorded
    method: dict = field(default_factory=dict)  # merged method settings (provenance.merge_settings)

    @property
    def sha(self) -> str:
        return method_sha(self.method)

    def line(self, profile: str = "default") -> str:
        """The provenance sentence of a page: commit, local changes, method settings (and how they
        differ from the method this code ships for ``profile``, when they do)."""
        dirty = {"yes": "with local changes", "no": "no local changes"}.get(self.dirty, "local changes not recorded")
        text = f"made by the code at {self.commit} ({dirty}), method settings `{self.sha}`"
        keys = differing_keys(self.method, shipped_method_settings(profile))
        if keys:
            shown = ", ".join(f"`{k}`" for k in keys[:6]) + (f" and {len(keys) - 6} more" if len(keys) > 6 else "")
            text += f" (not the shipped method: {shown})"
        return text

    def record(self) -> dict:
        return {"commit": self.commit, "dirty": self.dirty, "method_sha": self.sha, "method": self.method}


def _commits_text(counts: Counter, noun: str) -> str:
    if not counts:
        return "unknown"
    if len(counts) == 1:
        return f"commit {next(iter(counts))}"
    return "commits " + ", ".join(f"{rev} ({n} {noun}{'s' if n != 1 else ''})" for rev, n in counts.most_common())


def from_runs(run_files, noun: str = "run") -> PageProvenance | None:
    """The provenance of the run files that exist among ``run_files`` (None: none exists)."""
    import h5py

    commits: Counter[str] = Counter()
    dirty: set[str] = set()
    methods = []
    for path in map(Path, run_files):
        if not path.exists():
            continue
        with h5py.File(path, "r") as f:
            rev = str(f.attrs.get("git_commit", "unknown"))
            dirty.add(str(f.attrs.get("git_dirty", "unknown")))
            methods.append(method_settings(json.loads(str(f.attrs.get("config", "{}")))))
        if rev != "unknown":
            commits[rev[:7]] += 1
    if not methods:
        return None
    flag = "yes" if "yes" in dirty else "unknown" if "unknown" in dirty else "no"
    return PageProvenance(_commits_text(commits, noun), flag, merge_settings(methods))


def from_checkout(config: dict | None = None) -> PageProvenance:
    """This checkout's provenance, for a page made from no run file (``config``: a MorphConfig
    as a dict; default the shipped method)."""
    rev, dirty = git_state()
    method = method_settings(config) if config is not None else shipped_method_settings()
    return PageProvenance("unknown" if rev == "unknown" else f"commit {rev[:7]}", dirty, method)


def block(kind: str, profile: str, prov: PageProvenance, summary: dict | None = None) -> str:
    """The page's closing comment (one line)."""
    record = {"kind": kind, "profile": profile, **prov.record(), "summary": summary or {}}
    return f"<!-- physmorph-page {json.dumps(record, sort_keys=True, default=str)} -->\n"


def read_block(text: str) -> dict | None:
    """The record of a page's closing comment (None: the page has none)."""
    found = BLOCK_RE.search(text)
    return json.loads(found.group(1)) if found else None


# --------------------------------------------------------------------------------------------
# a results page's summary: one value per README cell
# --------------------------------------------------------------------------------------------

def _images(targets_dir: Path) -> str:
    import h5py

    for path in sorted(targets_dir.glob("*.h5")):
        with h5py.File(path, "r") as f:
            if "alpha" in f:
                views, height, width = f["alpha"].shape
                return f"{views} × {width}×{height}"
    return ""


def results_summary(tables_dir: Path, wall_s: float) -> dict:
    """The profile table's cells for the results of ``tables_dir`` (physmorph.reports.tables CSVs)."""
    timing = pd.read_csv(tables_dir / "timing.csv") if (tables_dir / "timing.csv").exists() else pd.DataFrame()
    conv = pd.read_csv(tables_dir / "convergence.csv") if (tables_dir / "convergence.csv").exists() else pd.DataFrame()
    out: dict = {"runs": int(len(timing))}
    if len(timing):
        particles = [int(p) for p in timing["particles"] if np.isfinite(p) and p > 0]
        out["particles"] = [min(particles), max(particles)] if particles else None
        out["frames"] = sorted({int(f) for f in timing["frames"]})
        out["peak_rss_mb"] = float(np.nanmax(timing["peak_rss_mb"]))
    out["wall_s"] = float(wall_s) if np.isfinite(wall_s) else None
    out["images"] = _images(tables_dir.parent / "targets")
    iso_full = conv[conv["experiment"].astype(str).str.match(r"iso_[A-Za-z]+_full$")] if len(conv) else conv
    if len(iso_full):
        pick = iso_full[iso_full["experiment"] == "iso_bunny_full"]
        row = (pick if len(pick) else iso_full).iloc[0]
        out["iso_full_last"] = {"experiment": str(row["experiment"]), "closed_last_%": float(row["closed_final_%"])}
    return out


# --------------------------------------------------------------------------------------------
# userdocs check
# --------------------------------------------------------------------------------------------

def generated_pages(docs_dir: Path) -> list[Path]:
    """The pages under docs/ (docs/study/ aside) that a userdocs command writes."""
    return sorted(p for p in Path(docs_dir).glob("*.md") if "physmorph-page" in p.read_text())


def check_pages(docs_dir: Path) -> tuple[list[str], bool]:
    """(one line per page made with other than the shipped method, or with no record of it;
    whether the default profile's page is among them)."""
    lines, default_bad = [], False
    others = {p for p in (Path(docs_dir) / "stability.md", Path(docs_dir) / "tradeoff.md") if p.exists()}
    pages = sorted(set(generated_pages(docs_dir)) | set(results_pages(docs_dir)) | others
                   | {Path(docs_dir) / "results.md"})
    for page in pages:
        record = read_block(page.read_text()) if page.exists() else None
        name = page.name
        if record is None:
            lines.append(f"{name}: records no method settings (regenerate it)")
            default_bad |= name == "results.md"
            continue
        keys = differing_keys(record.get("method", {}), shipped_method_settings(record.get("profile") or "default"))
        if keys:
            lines.append(f"{name} ({record.get('profile')}): method settings differ from the shipped ones in "
                         + ", ".join(keys))
            default_bad |= record.get("profile") == "default" and record.get("kind") == "results"
    return lines, default_bad


# --------------------------------------------------------------------------------------------
# the README's profile table
# --------------------------------------------------------------------------------------------

README_START = "<!-- profile table: generated by `python -m physmorph.reports.userdocs readme` -->"
README_END = "<!-- end of the profile table -->"


def _wall(seconds) -> str:
    if seconds is None:
        return ""
    minutes = seconds / 60
    return f"{minutes:.0f} min" if minutes < 90 else f"{minutes / 60:.1f} h"


def _per_run(seconds, runs) -> str:
    """The jobs' time over the runs: about what one more morph of the profile takes, its data jobs included."""
    if seconds is None or not runs:
        return ""
    each = seconds / runs
    return f"{each:.0f} s" if each < 120 else _wall(each)


def _particles(span) -> str:
    if not span:
        return ""
    lo, hi = span
    fmt = (lambda n: f"{n / 1000:.1f}K") if hi < 100_000 else (lambda n: f"{n / 1000:.0f}K")
    return fmt(lo) if lo == hi else f"{fmt(lo)}-{fmt(hi)}"


def results_pages(docs_dir: Path) -> list[Path]:
    """The results pages (docs/results*.md and docs/paper_scale.md), recorded or not."""
    docs_dir = Path(docs_dir)
    return sorted(list(docs_dir.glob("results*.md")) + [p for p in [docs_dir / "paper_scale.md"] if p.exists()])


def _page_profile(page: Path) -> str:
    if page.name == "paper_scale.md":
        return "paper"
    return page.stem.removeprefix("results_") if page.stem != "results" else "default"


def readme_table(docs_dir: Path) -> str:
    """The README's profile table from the results pages' records: one row a page, one value a
    cell; a row whose page ran other than the shipped method is marked † (``userdocs check`` names
    the keys)."""
    header = ["profile", "runs", "particles", "images", "frames", "jobs' time, summed", "per run", "peak RSS",
              "iso full, last", "page"]
    rows, marked, unrecorded = [], False, False
    for page in results_pages(docs_dir):
        record = read_block(page.read_text())
        if record is None:  # a page made before pages recorded what made them
            unrecorded = True
            rows.append([f"`{_page_profile(page)}` ‡"] + [""] * (len(header) - 2) + [f"[{page.name}](docs/{page.name})"])
            continue
        if record.get("kind") != "results":
            continue
        s = record.get("summary", {})
        shipped = shipped_method_settings(record["profile"])
        mark = " †" if differing_keys(record.get("method", {}), shipped) else ""
        marked |= bool(mark)
        iso = s.get("iso_full_last")
        iso_cell = f"{iso['closed_last_%']:.1f} % ({iso['experiment'].split('_')[1]})" if iso else ""
        rss = s.get("peak_rss_mb")
        rows.append([f"`{record['profile']}`{mark}", str(s.get("runs", "")), _particles(s.get("particles")),
                     s.get("images", ""), "/".join(map(str, s.get("frames", []))), _wall(s.get("wall_s")),
                     _per_run(s.get("wall_s"), s.get("runs")),
                     f"{rss / 1024:.1f} GB" if rss else "", iso_cell, f"[{page.name}](docs/{page.name})"])
    order = {"default": 0, "test": 1, "fast": 2, "mid": 3, "paper": 4}
    rows.sort(key=lambda r: (order.get(r[0].split("`")[1], 9), r[0]))
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    if marked:
        lines.append("\n† made with other method settings than the ones this code ships "
                     "(`python -m physmorph.reports.userdocs check` names them): rerun to update.")
    if unrecorded:
        lines.append("\n‡ its page does not record what made it: rerun to fill the row.")
    return "\n".join(lines)


def update_readme(readme: Path, docs_dir: Path) -> None:
    """Replace the README's profile table (between its two marker comments)."""
    text = readme.read_text()
    start, end = text.find(README_START), text.find(README_END)
    if start < 0 or end < start:
        raise ValueError(f"{readme}: no profile table markers ({README_START!r} ... {README_END!r})")
    text = text[:start + len(README_START)] + "\n" + readme_table(docs_dir) + "\n" + text[end:]
    readme.write_text(text)


def run_wall_time_s(run_h5: Path) -> float:
    """A finished run's wall time over all its sittings (its ``wall_time_s``; NaN without one)."""
    if not run_h5.exists():
        return float("nan")
    try:
        with h5py.File(run_h5, "r") as f:
            return float(f.attrs.get("wall_time_s", np.nan))
    except OSError:
        return float("nan")


def jobs_wall_time_s(results_dir: Path) -> float:
    """Sum of the jobs' wall times recorded in results_dir/benchmarks/ (NaN when there are none).
    A morph job resumed after a kill records only its last sitting there, so a morph counts the
    run's own wall time over its sittings where that is longer."""
    total, found = 0.0, False
    for tsv in sorted((results_dir / "benchmarks").rglob("*.tsv")):
        try:
            df = pd.read_csv(tsv, sep="\t")
        except (pd.errors.EmptyDataError, pd.errors.ParserError):
            continue
        if "s" in df and len(df):
            job = float(df["s"].iloc[-1])
            if tsv.parent.name == "morph":
                job = np.nanmax([job, run_wall_time_s(results_dir / "runs" / f"{tsv.stem}.h5")])
            total += job
            found = True
    return total if found else float("nan")
