"""The morph loop on the tiny test profile: it improves, full beats physics-only, runs resume
exactly where they stopped, and divergence stops loudly while keeping completed frames."""

import dataclasses

import h5py
import numpy as np
import pytest

import physmorph.morph as morph
from physmorph.config import load_settings
from physmorph.morph import MorphDivergenceError, morph_config, read_metrics, run_morph
from physmorph.stages import prepare_mesh_stage, rasterize_target_stage, sample_particles_stage


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, mesh_dir):
    """iso particles and a bunny target at the test profile's resolution."""
    d = tmp_path_factory.mktemp("tiny")
    cfg = load_settings("config/config.yaml", "config/test.yaml")
    s = cfg.sampling
    prepare_mesh_stage("iso", cfg.shapes["iso"], None, d / "iso.h5")
    prepare_mesh_stage("bunny", cfg.shapes["bunny"], mesh_dir / "stanford-bunny.obj", d / "bunny.h5")
    sample_particles_stage(d / "iso.h5", d / "p_iso.h5", d / "p_iso.png", s, 0)
    rasterize_target_stage(d / "bunny.h5", d / "t_bunny.h5", d / "t_bunny.png", s, cfg.target, 0)
    return cfg, d


def _run(tiny, experiment, out_name, **changes):
    cfg, d = tiny
    mc = dataclasses.replace(morph_config(cfg, experiment), progress=False, **changes)
    out = d / out_name
    run_morph(d / "p_iso.h5", d / "t_bunny.h5", out, mc, name=out_name)
    return out


@pytest.fixture(scope="module")
def tiny_runs(tiny):
    return {m: read_metrics(_run(tiny, f"iso_bunny_{m}", f"{m}.h5")) for m in ("physics_only", "full")}


def test_tiny_morph_lowers_alpha_mse(tiny_runs):
    for method, m in tiny_runs.items():
        a = m["alpha_mse"]
        assert len(a) == 13 and np.isfinite(a).all()
        assert a[1:].min() < a[0], method
        assert m["physics_loss"][-1] < m["physics_loss_initial"][1], method  # the mass loss falls too
        assert m["attrs"]["status"] == "complete"


def test_full_method_runs_every_component_on_the_tiny_setup(tiny_runs):
    """Render injection and plasticity act in the full run and not in physics-only. (Whether full
    beats physics-only is a research result, measured in docs/convergence.md and the tables: with
    the log mass loss and normalised GD it does not at this profile, so no test asserts it.)"""
    # Plasticity (from frame 4) actually moved Fp; physics-only never touches it.
    assert tiny_runs["full"]["fp_det_max"][-1] > 1.0 + 1e-6
    assert np.all(tiny_runs["physics_only"]["fp_det_max"] == 1.0)
    # Render gradients were computed for the injecting method only.
    assert np.all(tiny_runs["full"]["grad_F_norm"][1:] > 0)
    assert np.isnan(tiny_runs["physics_only"]["grad_F_norm"][1:]).all()
    assert np.isnan(tiny_runs["physics_only"]["mask_size"]).all()  # no mask built where none is used


def test_run_records_metrics_and_provenance(tiny_runs):
    m = tiny_runs["full"]
    for key in ("alpha_mse_views", "elastic_energy", "total_volume", "mask_size", "t_physics", "t_render",
                "t_plasticity", "t_mask", "fp_anisotropy_max", "loss_dt", "loss_iou", "loss_depth"):
        assert key in m
    assert m["alpha_mse_views"].shape == (13, 8)
    assert np.allclose(m["alpha_mse_views"].mean(axis=1), m["alpha_mse"])
    for attr in ("git_commit", "package_versions", "peak_rss_mb", "config", "injection_scale"):
        assert attr in m["attrs"]
    assert 0 < m["mask_fraction"][1] < 1  # interior particles are not rendered


class _Killed(Exception):
    pass


def test_resume_equals_uninterrupted_run(tiny, monkeypatch):
    frames = dict(frames=5, plasticity=dataclasses.replace(morph_config(tiny[0], "iso_bunny_full").plasticity, start_frame=2))
    full = _run(tiny, "iso_bunny_full", "uninterrupted.h5", **frames)
    real = morph.chamfer_plasticity_step
    calls = {"n": 0}

    def dies_at_frame_4(*args, **kwargs):  # killed in the middle of frame 4's plasticity stage
        calls["n"] += 1
        if calls["n"] == 3:
            raise _Killed()
        return real(*args, **kwargs)

    monkeypatch.setattr(morph, "chamfer_plasticity_step", dies_at_frame_4)
    with pytest.raises(_Killed):
        _run(tiny, "iso_bunny_full", "resumed.h5", **frames)
    partial = tiny[1] / "resumed.h5.partial"
    with h5py.File(partial) as f:
        assert f.attrs["frames_completed"] == 3
    monkeypatch.setattr(morph, "chamfer_plasticity_step", real)
    resumed = _run(tiny, "iso_bunny_full", "resumed.h5", **frames)
    assert not partial.exists()
    a, b = read_metrics(full), read_metrics(resumed)
    # Same result: bit-identical with one thread; float32 atomics in a different order with more.
    for key in ("alpha_mse", "physics_loss", "fp_det_max", "total_volume"):
        np.testing.assert_allclose(b[key], a[key], rtol=1e-4, err_msg=key)
    with h5py.File(full) as fa, h5py.File(resumed) as fb:
        for k in ("x", "F", "Fp"):
            np.testing.assert_allclose(fb["states/frame_0005"][k][()], fa["states/frame_0005"][k][()], rtol=1e-3, atol=1e-4)


def test_divergence_names_frame_and_quantity_and_keeps_frames(tiny, monkeypatch):
    real = morph.chamfer_plasticity_step

    def poisons_fp(x, Fp, *args, **kwargs):
        res = real(x, Fp, *args, **kwargs)
        res.Fp[7] = np.nan
        return res

    monkeypatch.setattr(morph, "chamfer_plasticity_step", poisons_fp)
    pl = dataclasses.replace(morph_config(tiny[0], "iso_bunny_full").plasticity, start_frame=3)
    with pytest.raises(MorphDivergenceError, match=r"frame 3: Fp became non-finite \(particle 7\)"):
        _run(tiny, "iso_bunny_full", "diverged.h5", frames=5, plasticity=pl)
    kept = read_metrics(tiny[1] / "diverged.h5.partial")  # frames 0..2 stay readable
    assert len(kept["alpha_mse"]) == 3 and np.isfinite(kept["alpha_mse"]).all()
    assert not (tiny[1] / "diverged.h5").exists()


def test_position_injection_runs_and_records_its_outcome(tiny):
    out = _run(tiny, "iso_bunny_position_inject", "position.h5", frames=4)
    m = read_metrics(out)
    status = str(m["attrs"]["status"])
    assert status == "complete" or status.startswith("diverged: frame")
    assert np.all(m["grad_x_norm"][1:len(m["alpha_mse"])] > 0)


def test_camera_subset_for_the_loss_but_every_view_for_the_metric(tiny):
    out = _run(tiny, "iso_bunny_full", "two_cameras.h5", frames=1, cameras=2)
    m = read_metrics(out)
    assert list(m["attrs"]["loss_views"]) == [0, 4]  # evenly spaced on the ring of 8
    assert m["alpha_mse_views"].shape == (2, 8)
    assert np.allclose(m["alpha_mse_views"].mean(axis=1), m["alpha_mse"])


# ----------------------------------------------------------------------------- convergence
def test_tiny_physics_only_closes_most_of_its_reachable_gap(tiny_runs):
    """With the profile's log mass loss and normalised GD, the 12-frame tiny iso -> bunny run must
    close a real share of the gap to the ceiling (the target's own particles at rest)."""
    m = tiny_runs["physics_only"]
    ceiling = float(m["attrs"]["ceiling_alpha_mse"])
    assert 0 < ceiling < m["alpha_mse"][0]
    closed = m["gap_closed"]
    np.testing.assert_allclose(closed, (m["alpha_mse"][0] - m["alpha_mse"]) / (m["alpha_mse"][0] - ceiling), rtol=1e-9)
    assert closed[-1] >= TINY_CLOSED_FINAL
    assert m["iou"][-1] > m["iou"][0] + 0.05


# Measured on the tiny profile (12 frames, ~1.2K particles): see docs/convergence.md.
TINY_CLOSED_FINAL = 0.5


def test_source_equal_to_target_has_nothing_to_close(tiny, mesh_dir):
    """A run whose source is its target starts at the ceiling: the share closed stays finite and
    near 1 (the metric must not divide by a vanishing gap)."""
    cfg, d = tiny
    s = cfg.sampling
    sample_particles_stage(d / "bunny.h5", d / "p_bunny.h5", d / "p_bunny.png", s, 0)
    mc = dataclasses.replace(morph_config(cfg, "iso_bunny_physics_only"), progress=False, frames=3)
    out = d / "bunny_bunny.h5"
    run_morph(d / "p_bunny.h5", d / "t_bunny.h5", out, mc, name="bunny_bunny")
    m = read_metrics(out)
    assert abs(m["alpha_mse"][0] - float(m["attrs"]["ceiling_alpha_mse"])) < 2e-3
    assert np.isfinite(m["gap_closed"]).all()
    assert np.all(np.abs(m["gap_closed"]) < 50)
