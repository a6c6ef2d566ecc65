"""Provenance that cannot lie: files and pages record the commit, whether the tree had local
changes, and the method settings (physmorph.records.provenance, physmorph.reports.page_meta)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import h5py
import pytest

from physmorph.records import h5io
from physmorph.reports import page_meta
from physmorph.settings.workflow import load_settings
from physmorph.settings.params import to_plain
from physmorph.reports.page_meta import (PageProvenance, check_pages, from_runs, read_block, readme_table,
                                 shipped_method_settings)
from physmorph.records.provenance import ABSENT, differing_keys, git_state, merge_settings, method_settings, method_sha
from physmorph.settings.retired import ADDED_METHOD_SETTINGS, RETIRED_METHOD_SETTINGS
from physmorph.reports.userdocs import results_markdown
from test_userdocs import _fake_tables

ROOT = Path(__file__).resolve().parents[2]


def _profile_method(*profiles: str) -> dict:
    files = [ROOT / "config" / "config.yaml"] + [ROOT / "config" / f"{p}.yaml" for p in profiles]
    return method_settings(to_plain(load_settings(*files).experiment_config("iso_bunny_full")))


def test_resolution_profiles_run_the_shipped_method():
    """mid sets resolution only: its method settings are the default profile's, which are the
    shipped ones; the paper profile's differ in the volume term's weight alone, which its own file
    sets, so the paper profile ships that; the test profile's differ in exactly the keys it sets."""
    shipped = shipped_method_settings()
    assert _profile_method() == shipped
    assert method_sha(_profile_method("mid")) == method_sha(shipped) == method_sha(shipped_method_settings("mid"))
    assert differing_keys(_profile_method("paper"), shipped) == ["mpm.volume_weight"]
    assert shipped_method_settings("paper") == _profile_method("paper")
    # a profile with no file of its own, or a file that is not a profile's, ships the defaults
    assert shipped_method_settings("mid_heldout") == shipped_method_settings("paper_results") == shipped
    assert differing_keys(_profile_method("test"), shipped) == ["mpm.learning_rate", "plasticity.k_neighbors",
                                                                "plasticity.start_frame"]
    assert "mpm.grid_res" not in shipped and "frames" not in shipped and "mpm.drag" not in shipped
    assert shipped["settle"] == "after_first_rise"


def test_run_record_is_read_through_its_resolved_part():
    resolved = {"frames": 40, "gamma": 0.1, "mpm": {"learning_rate": 0.004, "grid_res": 32}}
    assert method_settings({"experiment": {"source": "iso"}, "morph": {}, "resolved": resolved}) == \
        {"gamma": 0.1, "mpm.learning_rate": 0.004}


def _git(cwd: Path, *args: str) -> str:
    return subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, check=True).stdout.strip()


def test_git_state_tells_a_dirty_tree(tmp_path):
    repo = tmp_path / "repo"
    (repo / "physmorph").mkdir(parents=True)
    code = repo / "physmorph" / "x.py"
    code.write_text("a = 1\n")
    _git(repo, "init", "-q")
    _git(repo, "add", ".")
    _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "x")
    rev = _git(repo, "rev-parse", "HEAD")
    assert git_state(str(repo)) == (rev, "no")
    (repo / "notes.txt").write_text("untracked, outside the code\n")
    assert git_state(str(repo)) == (rev, "no")
    code.write_text("a = 2\n")
    assert git_state(str(repo)) == (rev, "yes")
    assert git_state(str(tmp_path)) == ("unknown", "unknown")


def test_a_file_and_its_page_say_the_tree_was_dirty(tmp_path, monkeypatch):
    """A run file made by a tree with local changes records it, and the page made from it says so;
    the state is the one the process first saw (a run names the code it started with)."""
    monkeypatch.setattr(h5io, "_CODE_STATE", ("1234567abcdef", "yes"))
    config = {"resolved": {"gamma": 0.1, "mpm": {"learning_rate": 0.004}}}
    run = tmp_path / "runs" / "iso_bunny_full.h5"
    run.parent.mkdir()
    with h5py.File(run, "w") as f:
        h5io.write_provenance(f, config, started=0.0)
    with h5py.File(run, "r") as f:
        assert (f.attrs["git_commit"], f.attrs["git_dirty"]) == ("1234567abcdef", "yes")
        assert f.attrs["method_sha"] == method_sha(method_settings(config))
    prov = from_runs([run])
    assert (prov.commit, prov.dirty) == ("commit 1234567", "yes")
    tables = tmp_path / "tables"
    _fake_tables(tables)
    text = results_markdown(tables, "default", date="today", provenance=prov)
    assert "made by the code at commit 1234567 (with local changes)" in text
    assert read_block(text)["dirty"] == "yes"
    # a tree without local changes says that too, and one file of several dirty marks the page
    clean = tmp_path / "runs" / "clean.h5"
    monkeypatch.setattr(h5io, "_CODE_STATE", ("1234567abcdef", "no"))
    with h5py.File(clean, "w") as f:
        h5io.write_provenance(f, config, started=0.0)
    assert from_runs([clean]).dirty == "no"
    assert from_runs([clean, run]).dirty == "yes"


def _page(docs: Path, name: str, profile: str, method: dict, summary: dict | None = None) -> None:
    prov = PageProvenance("commit 1234567", "no", method)
    (docs / name).write_text(f"# {profile}\n\n" + page_meta.block("results", profile, prov, summary))


def test_check_names_the_keys_and_fails_on_the_default_page(tmp_path):
    shipped = shipped_method_settings()
    docs = tmp_path / "docs"
    docs.mkdir()
    _page(docs, "results.md", "default", shipped)
    _page(docs, "results_mid.md", "mid", {**shipped, "mpm.learning_rate": 0.002})
    (docs / "results_old.md").write_text("# made before pages kept a record\n")
    lines, default_bad = check_pages(docs)
    assert lines == ["results_mid.md (mid): method settings differ from the shipped ones in mpm.learning_rate",
                     "results_old.md: records no method settings (regenerate it)"]
    assert not default_bad
    _page(docs, "results.md", "default", {**shipped, "settle": "off"})
    lines, default_bad = check_pages(docs)
    assert default_bad and any("results.md (default)" in ln and ln.endswith("settle") for ln in lines)
    (docs / "results.md").write_text("# no record\n")
    lines, default_bad = check_pages(docs)
    assert default_bad and "results.md: records no method settings (regenerate it)" in lines
    # the paper profile's page is measured against what config/paper.yaml sets: its volume weight
    paper = shipped_method_settings("paper")
    _page(docs, "paper_scale.md", "paper", paper)
    assert not any(ln.startswith("paper_scale.md") for ln in check_pages(docs)[0])
    _page(docs, "paper_scale.md", "paper", {**paper, "mpm.volume_weight": shipped["mpm.volume_weight"]})
    assert "paper_scale.md (paper): method settings differ from the shipped ones in mpm.volume_weight" in \
        check_pages(docs)[0]


def test_readme_table_has_one_value_a_cell_and_marks_other_methods(tmp_path):
    shipped = shipped_method_settings()
    docs = tmp_path / "docs"
    docs.mkdir()
    summary = {"runs": 18, "particles": [6736, 8044], "images": "8 × 160×90", "frames": [40], "wall_s": 540.0,
               "peak_rss_mb": 600.0, "iso_full_last": {"experiment": "iso_bunny_full", "closed_last_%": 100.91}}
    _page(docs, "results.md", "default", shipped, summary)
    _page(docs, "results_mid.md", "mid", {**shipped, "settle": "off"}, {**summary, "particles": [35000, 44000]})
    (docs / "paper_scale.md").write_text("# no record\n")
    table = readme_table(docs).splitlines()
    # 540 s over 18 runs: 30 s a run
    assert table[2] == ("| `default` | 18 | 6.7K-8.0K | 8 × 160×90 | 40 | 9 min | 30 s | 0.6 GB | 100.9 % (bunny) "
                        "| [results.md](docs/results.md) |")
    assert table[3].startswith("| `mid` † | 18 | 35.0K-44.0K |")
    assert table[4].startswith("| `paper` ‡ |")
    assert any(ln.startswith("† made with other method settings") for ln in table)
    assert all(row.count(" | ") == 9 for row in table[2:5])


def test_the_repository_pages_read_back():
    """Every recorded page under docs/ parses, and its record's hash is that of its settings."""
    for page in page_meta.generated_pages(ROOT / "docs"):
        record = read_block(page.read_text())
        assert record is not None, page
        assert record["method_sha"] == method_sha(record["method"]), page
        json.dumps(record)


def test_a_retired_setting_counts_as_shipped_only_at_the_value_the_method_ran_with():
    """A page made before a setting was removed records it: at the value the shipped method always
    ran with (physmorph.settings.retired) it is no difference, at any other it is one; no retired
    key is still a setting."""
    shipped = shipped_method_settings()
    assert not set(RETIRED_METHOD_SETTINGS) & set(shipped)
    old = {**shipped, **RETIRED_METHOD_SETTINGS}
    assert differing_keys(old, shipped) == []
    assert differing_keys({**old, "mpm.control_in_F": True}, shipped) == ["mpm.control_in_F"]
    assert differing_keys({**old, "step_backoff": {"values": [1.0, 0.5]}}, shipped) == ["step_backoff"]
    assert differing_keys({**shipped, "no_such_key": 1}, shipped) == ["no_such_key"]
    # a setting added since: a record without it ran as the added setting's value does, so it is
    # a difference exactly where the shipped default is another value (plasticity.volume: target;
    # the push along the plan, its drawn destinations, the volume term and the spray put back, the
    # spray's pieces linked through faces alone, the injection gain kept between measurements, the
    # settling frames held)
    assert set(ADDED_METHOD_SETTINGS) <= set(shipped)
    before = {k: v for k, v in shipped.items() if k not in ADDED_METHOD_SETTINGS}
    changed = sorted(k for k, v in ADDED_METHOD_SETTINGS.items() if shipped[k] != v)
    assert changed == ["injection_calibration_every", "mpm.volume_weight", "plan_push_speed",
                       "plasticity.transport_projection", "plasticity.volume", "reabsorb_strays",
                       "settle_hold_below", "spray_links"]
    assert differing_keys(before, shipped) == changed
    before = {**before, **{k: shipped[k] for k in changed}}
    assert differing_keys(before, shipped) == []
    assert differing_keys(before, {**shipped, "stray_pull_density": 0.2}) == ["stray_pull_density"]
    # a page of runs from before and after the removal / the addition: those without the key ran as its value
    mixed = merge_settings([old, shipped])
    assert mixed["mpm.control_in_F"] == {"values": [False, ABSENT]}
    assert differing_keys(mixed, shipped) == []
    assert differing_keys(merge_settings([{**old, "mpm.control_in_F": True}, shipped]), shipped) == ["mpm.control_in_F"]
    assert differing_keys(merge_settings([before, shipped]), shipped) == []
    assert differing_keys(merge_settings([before, {**shipped, "stray_pull_density": 0.2}]), shipped) == \
        ["stray_pull_density"]
    assert differing_keys(merge_settings([{k: v for k, v in shipped.items() if k != "gamma"}, shipped]),
                          shipped) == ["gamma"]
    # the pages the repository holds were made before: the check reads them as the shipped method
    lines, default_differs = check_pages(ROOT / "docs")
    assert not default_differs, lines


@pytest.mark.parametrize("value", [0.002, "x", None])
def test_differing_keys_reads_a_key_the_runs_disagree_on(value):
    ref = {"a": 1, "b": 0.004}
    assert differing_keys({"a": 1, "b": {"values": [0.004, value]}}, ref) == ["b"]
    assert differing_keys({"a": 1, "b": {"values": [0.004]}}, ref) == []


def test_a_process_names_the_code_it_started_with(monkeypatch):
    """The tree moving on during a run (a commit, an edit) does not change what its file names."""
    states = iter([("aaaaaaa1111", "no"), ("bbbbbbb2222", "yes")])
    monkeypatch.setattr(h5io, "_CODE_STATE", None)
    monkeypatch.setattr(h5io, "git_state", lambda: next(states))
    assert h5io.code_state() == ("aaaaaaa1111", "no")
    assert h5io.code_state() == ("aaaaaaa1111", "no") and h5io.git_commit() == "aaaaaaa1111"
