"""The table/figure layout (config/paper_results.yaml, physmorph.reports.layout)."""

from pathlib import Path

import pytest
import yaml

from physmorph.settings.errors import ConfigError
from physmorph.settings.workflow import load_settings
from physmorph.reports.layout import load_layout
from physmorph.reports.metrics import CHOSEN_FIGURES, FIGURE_NAMES

REPO = Path(__file__).resolve().parents[2]
LAYOUT = REPO / "config" / "paper_results.yaml"


def test_layout_names_only_experiments_of_the_default_profile():
    layout = load_layout(LAYOUT)
    experiments = set(load_settings(REPO / "config" / "config.yaml").experiments)
    assert layout.experiments() <= experiments, sorted(layout.experiments() - experiments)
    assert set(layout.figures) == set(FIGURE_NAMES) - set(CHOSEN_FIGURES)
    # the paper's numbers as printed (tab:main, tab:ablation, source invariance)
    assert layout.tables.main["duck"].paper_improvement_percent == 49.9
    assert layout.paper_alpha_mse("iso_bunny_full") == (0.0546, "best (drag ablation)")
    assert layout.paper_alpha_mse("iso_cow_full") == (0.0694, "matched frame (main)")
    assert layout.paper_alpha_mse("iso_bunny_f_inject_d05") == (0.1043, "final (component ablation)")
    assert layout.tables.plasticity.with_ == "iso_bunny_full" and layout.tables.plasticity.paper_rebound == "< 8"


@pytest.mark.parametrize("edit, key", [
    (lambda d: d["tables"]["drag"]["iso_bunny_full"].update(best="a lot"), "tables.drag.iso_bunny_full.best"),
    (lambda d: d["tables"]["main"]["cow"].pop("full"), "tables.main.cow"),
    (lambda d: d["tables"]["plasticity"].update(whith="x"), "tables.plasticity.whith"),
    (lambda d: d["figures"].update(sequences_mian=["iso_bunny_full"]), "sequences_mian"),
    (lambda d: d["figures"].update(sequences_other=["iso_bunny_full"]), "sequences_other"),
])
def test_bad_layout_names_the_file_and_the_key(tmp_path, edit, key):
    data = yaml.safe_load(LAYOUT.read_text())
    edit(data)
    bad = tmp_path / "layout.yaml"
    bad.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError) as err:
        load_layout(bad)
    assert str(bad) in str(err.value) and key in str(err.value), str(err.value)
