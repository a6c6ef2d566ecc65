"""The user docs cannot drift: README.md stays short, no page speaks of history (dates, commits,
findings: those live in docs/study/ and git), every table is well formed, every relative link
resolves, and the generated pages' provenance reads back (physmorph.reports.page_meta)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from physmorph.reports.page_meta import README_END, README_START, check_pages, read_block, readme_table

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
USER_DOCS = [README] + sorted((ROOT / "docs").glob("*.md"))  # docs/study/ aside
TABLE_DOCS = [ROOT / "config" / "README.md"] + sorted((ROOT / "docs").rglob("*.md"))

# 7-40 hex characters holding a letter and a digit (a commit hash), a YYYY-MM-DD date, "finding N"
COMMIT_RE = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")
DATE_RE = re.compile(r"\b\d{4}-\d{2}-\d{2}\b")
FINDING_RE = re.compile(r"\bfindings? \d+", re.IGNORECASE)
LINK_RE = re.compile(r"\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def _history(line: str) -> list[str]:
    return [m.group(0) for rx in (COMMIT_RE, DATE_RE, FINDING_RE) for m in rx.finditer(line)]


def _provenance_line(line: str) -> bool:
    """A generated page's provenance line (its "Generated ..." sentence, its closing record)."""
    return line.startswith("Generated ") or line.startswith("<!-- physmorph-page ")


def test_readme_is_short():
    size = len(README.read_bytes())
    assert size <= 12 * 1024, f"README.md is {size} bytes (at most 12 KB: the manual, not a diary)"


@pytest.mark.parametrize("doc", USER_DOCS, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_user_docs_hold_no_history(doc):
    bad = []
    for n, line in enumerate(doc.read_text().splitlines(), 1):
        if not _provenance_line(line) and _history(line):
            bad.append(f"{doc.name}:{n}: {', '.join(_history(line))}")
    assert not bad, "dates, commits or finding numbers belong in docs/study/ and git:\n" + "\n".join(bad[:20])


def _cells(row: str) -> int:
    """Cells of a Markdown table row: unescaped pipes split it (``\\|`` is a literal)."""
    body = row.strip()
    body = body[1:] if body.startswith("|") else body
    body = body[:-1] if body.endswith("|") and not body.endswith("\\|") else body
    return len(re.split(r"(?<!\\)\|", body))


def _tables(text: str):
    """(line number, rows) of each Markdown table: a header row followed by a |---| rule."""
    lines = text.splitlines()
    fenced = False
    i = 0
    while i < len(lines):
        if lines[i].lstrip().startswith("```"):
            fenced = not fenced
        if (not fenced and i + 1 < len(lines) and lines[i].lstrip().startswith("|")
                and re.fullmatch(r"\s*\|?(\s*:?-{3,}:?\s*\|)+\s*:?-*:?\s*", lines[i + 1])):
            j = i + 2
            while j < len(lines) and lines[j].lstrip().startswith("|"):
                j += 1
            yield i + 1, lines[i:j]
            i = j
            continue
        i += 1


@pytest.mark.parametrize("doc", TABLE_DOCS, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_table_row_has_its_header_cells(doc):
    bad = []
    for start, rows in _tables(doc.read_text()):
        want = _cells(rows[0])
        for k, row in enumerate(rows):
            if k != 1 and _cells(row) != want:
                bad.append(f"{doc.relative_to(ROOT)}:{start + k}: {_cells(row)} cells, header {want}")
    assert not bad, "\n".join(bad[:20])


def test_table_parser_counts_escaped_pipes_as_text():
    assert _cells("| a | b \\| c | d |") == 3
    assert _cells("| a | b | c | d |") == 4
    rows = list(_tables("x\n\n| a | b |\n|---|---|\n| 1 | 2 |\n| 1 | 2 | 3 |\n\ny"))
    assert rows == [(3, ["| a | b |", "|---|---|", "| 1 | 2 |", "| 1 | 2 | 3 |"])]


@pytest.mark.parametrize("doc", USER_DOCS + [ROOT / "config" / "README.md"], ids=lambda p: p.relative_to(ROOT).as_posix())
def test_relative_links_resolve(doc):
    bad = []
    for n, line in enumerate(doc.read_text().splitlines(), 1):
        for target in LINK_RE.findall(line):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue
            path = (doc.parent / target.split("#", 1)[0]).resolve()
            if not path.exists():
                bad.append(f"{doc.name}:{n}: {target}")
    assert not bad, "links to nothing:\n" + "\n".join(bad)


def test_history_patterns_catch_what_they_should():
    assert _history("made by fad1b8d on 2026-11-25 (finding 206)") == ["fad1b8d", "2026-11-25", "finding 206"]
    assert _history("a 128-particle grid, 1e-5, deadbeef, 0.975, 1234567") == []


def test_readme_table_is_the_generated_one():
    """README.md's profile table is what ``python -m physmorph.reports.userdocs readme`` writes from the pages."""
    text = README.read_text()
    start, end = text.index(README_START) + len(README_START), text.index(README_END)
    assert text[start:end].strip() == readme_table(ROOT / "docs").strip(), \
        "README.md's profile table is stale: run python -m physmorph.reports.userdocs readme"


def test_default_page_ran_the_shipped_method():
    """``userdocs check`` passes: docs/results.md was made with the method this code ships."""
    lines, default_bad = check_pages(ROOT / "docs")
    assert not default_bad, "\n".join(lines)
    assert read_block((ROOT / "docs" / "results.md").read_text())["profile"] == "default"


def test_readme_opens_with_the_morph_gif_under_two_megabytes():
    """The opening picture is the generated one, and its caption gives the run's numbers."""
    from physmorph.reports.readme_picture import MARKER, PICTURE

    text = README.read_text()
    caption, first_image = re.search(r"!\[([^\]]*)\]\(([^)]+)\)", text).groups()
    assert first_image == PICTURE.as_posix() and f"{MARKER}\n![" in text
    assert re.search(r"the default profile: \d+ % of the gap closed at the last frame, volume IoU \d\.\d\d", caption)
    gif = ROOT / PICTURE
    assert gif.read_bytes()[:6] in (b"GIF87a", b"GIF89a") and gif.stat().st_size <= 2_000_000
