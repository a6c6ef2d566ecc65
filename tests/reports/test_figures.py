"""Sequence figures (physmorph.reports.figures): the target beside the last frame, with the share closed."""

import json

import h5py
import numpy as np

from physmorph.reports.figures import run_target_shape, sequence_figure


def _write_run(path, target, alpha_mse, ceiling=None, frames=(0, 5, 10)):
    rng = np.random.default_rng(0)
    x = rng.normal(scale=3.0, size=(200, 3))
    with h5py.File(path, "w") as f:
        f.attrs["sigma0"] = 0.8
        f.attrs["config_record"] = json.dumps({"experiment": {"source": "iso", "target": target, "method": "full"}})
        if ceiling is not None:
            f.attrs["ceiling_alpha_mse"] = ceiling
        f.create_group("metrics")["alpha_mse"] = np.asarray(alpha_mse, dtype=float)
        for k in frames:
            g = f.create_group(f"states/frame_{k:04d}")
            g["x"] = x * (1.0 + 0.02 * k)
            g["F"] = np.tile(np.eye(3), (len(x), 1, 1))
    return path


def test_run_target_shape_from_record_else_name(tmp_path):
    with h5py.File(tmp_path / "a.h5", "w") as f:
        f.attrs["config_record"] = json.dumps({"experiment": {"target": "C"}})
        assert run_target_shape(f, "duck_S_full") == "C"
    with h5py.File(tmp_path / "b.h5", "w") as f:
        assert run_target_shape(f, "duck_S_full") == "S"


def test_sequence_figure_shows_the_target_and_the_share_closed(tmp_path):
    target_cfg = dict(cameras=2, width=16, height=12)
    # alpha MSE 0.06 -> 0.02 at the last frame (10), ceiling 0.01: 80 % of the gap closed.
    alpha = np.linspace(0.06, 0.02, 11)
    run = _write_run(tmp_path / "iso_bunny_full.h5", "bunny", alpha, ceiling=0.01)
    old = _write_run(tmp_path / "iso_cow_full.h5", "cow", alpha)  # no ceiling: no share shown
    t_h5 = tmp_path / "bunny_t.h5"
    with h5py.File(t_h5, "w") as f:
        f["alpha"] = np.zeros((2, 12, 16), np.float32)
    png = tmp_path / "seq.png"
    titles = sequence_figure({"iso_bunny_full": run, "iso_cow_full": old, "iso_duck_full": None}, target_cfg, png,
                             columns=3, targets={"bunny": t_h5})
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(titles) == 2 and all(len(row) == 4 for row in titles)  # 3 frames + the target
    assert titles[0][0].startswith("iso_bunny_full") and titles[0][2] == "k=10  80% of gap"
    assert titles[0][3] == "target (bunny)"
    assert titles[1][2] == "k=10" and titles[1][3] == "target (cow): not made"
    # Without targets (trajectory frames) the figure is as before: no extra column.
    titles = sequence_figure({"iso_bunny_full": run}, target_cfg, png, columns=3)
    assert titles == [["iso_bunny_full  k=0", "k=5", "k=10"]]


def test_build_figures_makes_the_figures_asked_for(tmp_path):
    """The main table's figures alone (workflow rule make_main_figures): only those files are
    written, and an unknown figure name is refused, naming the known ones."""
    import pytest

    from physmorph.reports.figures import build_figures
    from physmorph.reports.layout import load_layout

    alpha = np.linspace(0.06, 0.02, 11)
    runs = {"iso_bunny_full": _write_run(tmp_path / "iso_bunny_full.h5", "bunny", alpha, ceiling=0.01)}
    out = tmp_path / "figs"
    made = build_figures(runs, {}, dict(cameras=2, width=16, height=12), out, load_layout("config/paper_results.yaml"),
                         names=("sequences_main",))
    assert made == [out / "sequences_main.png"] and sorted(p.name for p in out.iterdir()) == ["sequences_main.png"]
    with pytest.raises(ValueError, match="unknown figures.*sequences_main"):
        build_figures(runs, {}, {}, out, load_layout("config/paper_results.yaml"), names=("sequence_main",))


def _write_method_run(path, target, method):
    _write_run(path, target, np.linspace(0.06, 0.02, 11), ceiling=0.01)
    with h5py.File(path, "a") as f:
        f.attrs["config_record"] = json.dumps({"experiment": {"source": "iso", "target": target, "method": method}})
    return path


def test_other_sequences_show_the_full_runs_of_targets_no_other_sequence_shows(tmp_path):
    """A profile's own targets (held-out shapes, a user's mesh) get a sequence figure; a target the
    paper's sequences already show does not appear twice, nor does a physics-only run; each figure
    records the runs it draws, and one with none records that (the results page leaves it out)."""
    from physmorph.reports.figures import build_figures, figure_runs
    from physmorph.reports.layout import load_layout

    runs = {n: _write_method_run(tmp_path / f"{n}.h5", t, m) for n, t, m in [
        ("iso_bunny_full", "bunny", "full"),          # sequences_main shows the bunny
        ("cow_bunny_full", "bunny", "full"),          # another source, the same target: shown there
        ("iso_torus_full", "torus", "full"),          # a profile's own target
        ("iso_torus_physics_only", "torus", "physics_only"),
        ("iso_mine_full", "mine", "full"),
    ]}
    out = tmp_path / "figs"
    build_figures(runs, {}, dict(cameras=2, width=16, height=12), out, load_layout("config/paper_results.yaml"),
                  names=("sequences_main", "sequences_other", "sequences_letters", "drag_ablation"))
    assert figure_runs(out / "sequences_other.png") == ["iso_torus_full", "iso_mine_full"]
    assert figure_runs(out / "sequences_main.png") == ["iso_bunny_full"]
    assert figure_runs(out / "sequences_letters.png") == []
    assert figure_runs(out / "drag_ablation.png") == ["iso_bunny_full"]
    (tmp_path / "plain.png").write_bytes(b"not a png")
    assert figure_runs(tmp_path / "plain.png") is None
