"""The generated user documentation (physmorph.reports.userdocs): the results page from a profile's tables,
the config reference against the schema, and the report captions against docs/outputs.md."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from physmorph.settings.docs import SECTIONS, field_docs
from physmorph.reports.metrics import FIGURE_NAMES, TABLE_NAMES
from physmorph.reports.userdocs import caption_rst, config_reference, output_captions, results_markdown, runs_provenance, tradeoff_provenance, write_results_doc
from physmorph.settings.docs import schema_keys
from physmorph.reports.page_meta import PageProvenance, read_block, shipped_method_settings
from physmorph.reports import page_meta
from physmorph.reports import userdocs

ROOT = Path(__file__).resolve().parents[2]


def _fake_tables(d):
    d.mkdir(parents=True)
    pd.DataFrame([{"experiment": "iso_bunny_full", "method": "full", "frames": 40, "alpha_mse_0": 0.06,
                   "alpha_mse_best": 0.011, "best_frame": 37, "alpha_mse_final": 0.0112, "ceiling": 0.0101,
                   "closed_best_%": 98.04, "closed_final_%": 97.6, "iou_0": 0.6, "iou_best": 0.9, "iou_final": 0.9,
                   "ceiling_iou": 0.91, "volume_iou_0": 0.53, "volume_iou_final": 0.95,
                   "overfilled_mass_final": 0.012, "swing_%": 0.31, "sign_changes": 3, "drop_points": 0.44,
                   "stray_%": 0.4, "surface_dx": 0.61, "surface_p95_dx": 1.9, "outside_body_%": 0.2,
                   "components": 1, "genus": 1, "target_genus": 0, "rough_%": 3.2,
                   "paper_alpha_mse": 0.0546, "paper_which": "best"}]
                 ).to_csv(d / "convergence.csv", index=False)
    pd.DataFrame([{"direction": "full beats physics-only at matched convergence", "case": "bunny",
                   "measure": "alpha MSE at the matched frame (frame 9)", "ours": 0.01306, "baseline": 0.01569,
                   "ours_vs_baseline_%": 16.76, "holds": "yes", "paper": "+25.8 %"}]
                 ).to_csv(d / "directions.csv", index=False)
    pd.DataFrame([{"target": "bunny", "paper_physics_only": 0.0799, "paper_ours": 0.0593,
                   "paper_improvement_%": 25.8, "frame": 9, "physics_only": 0.01569, "ours": 0.01306,
                   "improvement_%": 16.76}]).to_csv(d / "main.csv", index=False)
    pd.DataFrame([{"experiment": "iso_bunny_full", "paper_best": 0.0546, "best": 0.0106, "closed_best_%": 98.0,
                   "closed_final_%": 97.6},
                  {"experiment": "sigma/mu %", "paper_best": 10.25, "best": 8.4, "closed_best_%": 1.5,
                   "closed_final_%": 2.0}]).to_csv(d / "source_invariance.csv", index=False)
    pd.DataFrame([{"experiment": "iso_bunny_full", "variant": "with plasticity", "paper_rebound_%": "< 8",
                   "best": 0.011, "final": 0.0112, "rebound_%": 0.0, "release_frames": 40, "release_final": 0.0115,
                   "release_rebound_%": 1.2}]).to_csv(d / "plasticity.csv", index=False)
    pd.DataFrame([{"experiment": "iso_bunny_full", "frames": 40, "status": "complete", "physics_s": 0.64,
                   "render_s": 0.08, "plasticity_s": 0.2, "mask_s": 0.03, "frame_s": 1.02, "peak_rss_mb": 707.0,
                   "particles": 6736}]).to_csv(d / "timing.csv", index=False)


def test_results_page_carries_the_tables_numbers(tmp_path):
    tables = tmp_path / "results" / "default" / "tables"
    _fake_tables(tables)
    prov = PageProvenance("commit abc1234", "no", shipped_method_settings())
    text = results_markdown(tables, "default", date="2026-11-24", provenance=prov)
    assert "Generated on 2026-11-24" in text and "results/default/tables/" in text
    assert f"made by the code at commit abc1234 (no local changes), method settings `{prov.sha}`" in text
    assert "not the shipped method" not in text
    record = read_block(text)
    assert (record["profile"], record["commit"], record["dirty"], record["method_sha"]) == \
        ("default", "commit abc1234", "no", prov.sha)
    assert record["summary"]["runs"] == 1 and record["summary"]["particles"] == [6736, 6736]
    assert record["summary"]["iso_full_last"] == {"experiment": "iso_bunny_full", "closed_last_%": 97.6}
    assert "| iso_bunny_full | full | 98.0 % (frame 37) | 97.6 % | 0.4 | 0.3 % | 3 |" in text
    # the body in 3D: volume IoU, packing, stray, outside the body, genus (target's), surface, roughness
    assert "| iso_bunny_full | 0.53 -> 0.95 | 1.2 % | 0.4 % | 0.2 % | 1 (0) | 0.61 / 1.9 | 3.2 % |" in text
    assert "Silhouettes closed, body short" not in text  # its volume IoU is above the bar
    assert "| 0.01306 | 0.01569 | 16.8 % | yes | +25.8 % |" in text      # a direction and whether it holds
    assert "| bunny | 9 | 0.01569 | 0.01306 | 16.8 % | +25.8 % |" in text  # the main table beside the paper
    assert "| sigma/mu % | 8.4 | 10.25 | 1.5 % |" in text                   # source invariance
    assert "| 0.0 % | 1.2 % | 40 |" in text                                 # released rebound
    assert "6,736 particles" in text


def test_results_page_links_and_copies_figures(tmp_path):
    tables = tmp_path / "tree" / "tables"
    _fake_tables(tables)
    figures = tmp_path / "tree" / "figures"
    figures.mkdir()
    (figures / "sequences_main.png").write_bytes(b"png")
    out = write_results_doc(tables, tmp_path / "docs" / "results.md", "default", figures,
                            images_dir=tmp_path / "docs" / "images")
    text = out.read_text()
    assert "![sequences_main](images/sequences_main.png)" in text
    assert (tmp_path / "docs" / "images" / "sequences_main.png").read_bytes() == b"png"
    assert "drag_ablation" not in text  # a figure not made is not linked


def test_a_profile_without_the_papers_runs_gets_no_empty_sections_or_figures(tmp_path):
    """A held-out or user profile: the tables still list the paper's cases with empty measured
    columns (or none at all), and the figures stage draws a placeholder for a figure with none of
    its runs. The page leaves those out and keeps the rest."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from physmorph.reports.figures import RUNS_KEY

    tables = tmp_path / "tree" / "tables"
    _fake_tables(tables)
    pd.DataFrame([{"direction": "full beats physics-only at matched convergence", "case": "bunny",
                   "measure": "alpha MSE at the matched frame", "ours": None, "baseline": None,
                   "ours_vs_baseline_%": None, "holds": None, "paper": "+25.8 %"}]).to_csv(tables / "directions.csv",
                                                                                     index=False)
    pd.DataFrame([{"target": "bunny", "paper_physics_only": 0.0799, "paper_ours": 0.0593,
                   "paper_improvement_%": 25.8}]).to_csv(tables / "main.csv", index=False)  # no measured column
    pd.DataFrame([{"experiment": "iso_bunny_full", "paper_best": 0.0546, "best": None, "closed_best_%": None,
                   "closed_final_%": None}]).to_csv(tables / "source_invariance.csv", index=False)
    pd.DataFrame([{"experiment": "iso_bunny_full", "variant": "with plasticity", "paper_rebound_%": "< 8"}]
                 ).to_csv(tables / "plasticity.csv", index=False)
    figures = tmp_path / "tree" / "figures"
    figures.mkdir()
    for name, runs in (("sequences_main", ""), ("sequences_other", "iso_torus_full")):
        fig = plt.figure(figsize=(1, 1))
        fig.savefig(figures / f"{name}.png", metadata={RUNS_KEY: runs})
        plt.close(fig)
    text = write_results_doc(tables, tmp_path / "docs" / "results_heldout.md", "heldout", figures,
                             images_dir=tmp_path / "docs" / "images" / "heldout").read_text()
    for gone in ("three directions", "Main table", "Source invariance", "Does the morph persist", "sequences_main"):
        assert gone not in text, gone
    assert "## How far each run got" in text and "## Time per frame" in text
    assert "![sequences_other](images/heldout/sequences_other.png)" in text
    assert not (tmp_path / "docs" / "images" / "heldout" / "sequences_main.png").exists()


def test_each_profile_regenerates_its_own_page(tmp_path):
    """python -m physmorph.reports.userdocs results PROFILE: the default profile writes docs/results.md and
    docs/images/, any other docs/results_PROFILE.md and docs/images/PROFILE/, so regenerating mid's
    page leaves the default page and its images alone; all of it under --root, nothing elsewhere."""
    for profile in ("default", "mid"):
        _fake_tables(tmp_path / "results" / profile / "tables")
        figures = tmp_path / "results" / profile / "figures"
        figures.mkdir()
        (figures / "sequences_main.png").write_bytes(profile.encode())
    userdocs.main(["--root", str(tmp_path), "results"])
    userdocs.main(["--root", str(tmp_path), "results", "mid"])
    docs = tmp_path / "docs"
    assert "results/default/tables/" in (docs / "results.md").read_text()
    assert "[docs/outputs.md](outputs.md)" in (docs / "results.md").read_text()
    assert "results/mid/tables/" in (docs / "results_mid.md").read_text()
    assert "![sequences_main](images/mid/sequences_main.png)" in (docs / "results_mid.md").read_text()
    assert (docs / "images" / "sequences_main.png").read_bytes() == b"default"
    assert (docs / "images" / "mid" / "sequences_main.png").read_bytes() == b"mid"


def test_results_page_has_the_ablations_and_the_shapes(tmp_path):
    """The component and drag ablations and the cross-shape morphs reach the page beside the paper's
    numbers and each run's share of the gap; a row the profile did not run is left out, and a page
    whose tables predate them has none of these sections."""
    tables = tmp_path / "tables"
    _fake_tables(tables)
    text = results_markdown(tables, "paper", date="2026-11-29")
    assert "## Component ablation" not in text and "## Drag ablation" not in text and "## Cross-shape" not in text
    pd.DataFrame([{"experiment": "iso_bunny_f_inject_d05", "paper_alpha_mse": 0.1043, "paper_delta_E_%": 95.8,
                   "alpha_mse": 0.00995, "delta_E_%": 94.02},
                  {"experiment": "iso_bunny_full_d05", "paper_alpha_mse": 0.104, "paper_delta_E_%": 95.9}]
                 ).to_csv(tables / "ablation_components.csv", index=False)
    pd.DataFrame([{"experiment": "iso_bunny_full", "paper_best": 0.0546, "paper_final": 0.0637, "best": 0.011,
                   "final": 0.0112}, {"experiment": "iso_bunny_full_d05", "paper_best": 0.0735, "paper_final": 0.0786}]
                 ).to_csv(tables / "ablation_drag.csv", index=False)
    pd.DataFrame([{"experiment": "iso_bunny_full", "best": 0.011, "final": 0.0112, "volume_change_%": -8.23},
                  {"experiment": "cow_S_full"}]).to_csv(tables / "shapes.csv", index=False)
    text = results_markdown(tables, "paper", date="2026-11-29")
    assert "| iso_bunny_f_inject_d05 | 0.00995 | 0.1043 | 94.0 % | 95.8 % |  |" in text
    assert "| iso_bunny_full | 0.011 | 0.0112 | 0.0546 | 0.0637 | 98.0 % | 97.6 % |" in text
    assert "| iso_bunny_full | 0.011 | 0.0112 | 98.0 % | 97.6 % | -8.2 % |" in text
    assert "iso_bunny_full_d05 |" not in text and "cow_S_full" not in text


def test_main_table_page_names_its_tables_and_title(tmp_path):
    """The paper-scale page (python -m physmorph.reports.userdocs paper_main) is the results page of the main
    table's own tables: its title, and the tables directory it was made from."""
    tables = tmp_path / "results" / "paper" / "main_tables"
    _fake_tables(tables)
    text = results_markdown(tables, "paper", date="2026-11-25", title="The main table at the `paper` profile's scale")
    assert text.startswith("# The main table at the `paper` profile's scale\n")
    assert "from `results/paper/main_tables/`" in text
    assert "| bunny | 9 | 0.01569 | 0.01306 | 16.8 % | +25.8 % |" in text


def test_results_page_names_the_commits_of_its_runs(tmp_path):
    import h5py

    tables, runs = tmp_path / "tables", tmp_path / "runs"
    tables.mkdir()
    runs.mkdir()
    commits = {"a": "1234567aaaa", "b": "1234567aaaa", "c": "89abcdefbbb", "d": "unknown", "e": None}
    pd.DataFrame({"experiment": list(commits) + ["not_run"]}).to_csv(tables / "timing.csv", index=False)
    for name, rev in commits.items():
        with h5py.File(runs / f"{name}.h5", "w") as f:
            if rev is not None:
                f.attrs["git_commit"] = rev
    assert runs_provenance(tables, runs).commit == "commits 1234567 (2 runs), 89abcde (1 run)"
    pd.DataFrame({"experiment": ["a", "b"]}).to_csv(tables / "timing.csv", index=False)
    assert runs_provenance(tables, runs).commit == "commit 1234567"
    pd.DataFrame({"experiment": ["d", "e", "not_run"]}).to_csv(tables / "timing.csv", index=False)
    assert runs_provenance(tables, runs).commit == "unknown"
    pd.DataFrame({"experiment": ["not_run"]}).to_csv(tables / "timing.csv", index=False)
    assert runs_provenance(tables, runs) is None
    # the speed/accuracy page: the points of every profile's study
    for profile, names in (("p1", ["a", "c"]), ("p2", ["b", "d"])):
        (tmp_path / profile / "tradeoff").mkdir(parents=True)
        (tmp_path / profile / "tradeoff" / "runs").symlink_to(runs)
        pd.DataFrame({"name": names}).to_csv(tmp_path / profile / "tradeoff" / "tradeoff.csv", index=False)
    assert tradeoff_provenance(["p1", "p2"], tmp_path).commit == "commits 1234567 (2 points), 89abcde (1 point)"
    assert tradeoff_provenance(["p2"], tmp_path).commit == "commit 1234567"


def test_config_reference_documents_every_schema_key():
    keys = [k for k, _ in schema_keys()]
    docs = field_docs()  # from each setting's declaration
    undocumented = [k for k in keys if k not in SECTIONS and not docs.get(k, ("",))[0]]
    assert not undocumented, f"give these settings a description where they are declared: {undocumented}"
    text = (ROOT / "config" / "README.md").read_text()
    for k in keys:
        if k not in SECTIONS:
            assert f"`{k}`" in text, k
    assert text == config_reference(), "config/README.md is stale: python -m physmorph.reports.userdocs config"


def test_report_captions_come_from_outputs_md():
    captions = output_captions(ROOT / "docs" / "outputs.md")
    for name in (*TABLE_NAMES, *FIGURE_NAMES):
        assert name in captions, f"docs/outputs.md has no section ### `{name}`"
        path = ROOT / "workflow" / "report" / "captions" / f"{name}.rst"
        assert path.read_text() == caption_rst(captions[name]), \
            f"{path} is stale: python -m physmorph.reports.userdocs captions"


def test_each_profile_writes_its_own_results_page(tmp_path):
    """The default profile's page is docs/results.md, the paper profile's docs/paper_scale.md (the
    page the README's paper row links), any other's docs/results_{profile}.md, each with its images."""
    paths = {p: userdocs.results_doc_paths(p, tmp_path) for p in ("default", "paper", "mid")}
    assert paths["default"] == (tmp_path / "results.md", tmp_path / "images")
    assert paths["paper"] == (tmp_path / "paper_scale.md", tmp_path / "images" / "paper")
    assert paths["mid"] == (tmp_path / "results_mid.md", tmp_path / "images" / "mid")


def test_a_resumed_morph_counts_its_wall_time_over_every_sitting(tmp_path):
    """A morph job's benchmark file records only its last sitting; the summed jobs' time takes the
    run's own wall time over its sittings where that is longer."""
    import h5py

    for rule, name, s in (("morph", "iso_bunny_full", 100.0), ("morph", "iso_cow_full", 300.0), ("prepare_mesh", "bunny", 5.0)):
        (tmp_path / "benchmarks" / rule).mkdir(parents=True, exist_ok=True)
        pd.DataFrame({"s": [s], "max_rss": [1.0]}).to_csv(tmp_path / "benchmarks" / rule / f"{name}.tsv", sep="\t", index=False)
    (tmp_path / "runs").mkdir()
    for name, wall in (("iso_bunny_full", 250.0), ("iso_cow_full", 280.0)):
        with h5py.File(tmp_path / "runs" / f"{name}.h5", "w") as f:
            f.attrs["wall_time_s"] = wall
    assert page_meta.jobs_wall_time_s(tmp_path) == 250.0 + 300.0 + 5.0


def test_a_run_whose_silhouettes_closed_with_a_body_short_of_the_bar_is_named():
    from physmorph.reports.results_sections import BODY_VOLUME_IOU, body_section

    rows = [{"experiment": name, "closed_final_%": closed, "volume_iou_0": 0.5, "volume_iou_final": viou,
             "overfilled_mass_final": 0.0} for name, closed, viou in
            (("cow_S_full", 98.7, 0.79), ("iso_bunny_full", 99.0, 0.93), ("duck_C_full", 60.0, 0.5))]
    text = "\n".join(body_section(pd.DataFrame(rows)))
    assert BODY_VOLUME_IOU == 0.85
    assert "1 run(s) closed at least 90 % of their silhouettes' gap with a volume IoU below 0.85" in text
    assert "cow_S_full (98.7 % of the gap, volume IoU 0.79)" in text
    assert "iso_bunny_full (" not in text and "duck_C_full (" not in text  # above the bar; gap not closed
    assert "| cow_S_full | 0.5 -> 0.79 | 0.0 % |" in text  # not exported: the surface's columns empty
