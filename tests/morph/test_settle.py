"""The morph comes to rest (MorphConfig.settle, physmorph.morph.settle): at the shipped method settings
its last frames are still and as good as its best; a target of another volume than its source is
named in the log and the run file, and still settles; a run killed while settling resumes exactly."""

import dataclasses

import h5py
import numpy as np
import pytest

import physmorph.morph.loop as morph
from physmorph.settings.workflow import load_settings
from physmorph.meshes.fit import VOLUME_MISMATCH, volume_mismatch
from physmorph.reports.metrics import REST_SWING_PERCENT, at_rest, sign_changes, swing_percent
from physmorph.settings.morph import MorphConfig
from physmorph.morph.judge import FrameJudge
from physmorph.morph.loop import morph_config, run_morph
from physmorph.records.runfile import frame_motion, read_metrics
from physmorph.mpm.state import ParticleState
from physmorph.morph.settle import AcceptedFrame, SettleGate, settle_gate
from physmorph.stages import prepare_mesh_stage, rasterize_target_stage, sample_particles_stage

# config/test.yaml's resolution, and nothing of its method: the shipped method settings at a tiny scale
TEST_RESOLUTION = {"sampling": {"ppc_surface": 1}, "target": {"width": 48, "height": 32, "supersample": 2,
                                                              "surface_points": 2000},
                   "surface": {"voxels": 32}}


def shipped(frames: int, **changes) -> MorphConfig:
    """iso -> bunny full at the shipped method settings, the test profile's resolution."""
    cfg = load_settings("config/config.yaml", overrides=TEST_RESOLUTION)
    return dataclasses.replace(morph_config(cfg, "iso_bunny_full"), frames=frames, progress=False, release_frames=0,
                               **changes)


def _share(m: dict) -> np.ndarray:  # [K + 1] the share of the gap closed, in %
    return 100.0 * np.asarray(m["gap_closed"], dtype=float)


def _run(particles, target, out, mc, target_size=None) -> tuple[dict, list[str]]:
    lines = []
    run_morph(particles, target, out, mc, name=out.stem, log=lines.append, target_size=target_size)
    return read_metrics(out), lines


def test_the_tiny_scale_matches_the_test_profile(tiny):
    """The shipped settings here differ from config/test.yaml's in the method only."""
    mine = load_settings("config/config.yaml", overrides=TEST_RESOLUTION)
    test = tiny[0]
    assert (mine.sampling, mine.target, mine.surface) == (test.sampling, test.target, test.surface)
    assert shipped(5).settle == MorphConfig().settle == "after_first_rise"


SHIPPED_FRAMES = 39


@pytest.fixture(scope="module")
def shipped_run(tiny):
    """The tiny iso -> bunny full at the shipped method settings: (its metrics, its log lines).
    Slow: one whole tiny full morph of SHIPPED_FRAMES (39) frames."""
    _, d = tiny
    return _run(d / "p_iso.h5", d / "t_bunny.h5", d / "settle_shipped.h5", shipped(SHIPPED_FRAMES))


def test_shipped_morph_comes_to_rest_as_good_as_its_best(shipped_run):
    """At the shipped method settings the tiny iso -> bunny arrives by frame ~30 and then holds
    still. Measured over 50 frames: with the gate, sign changes 0, swing 0 %, best 108.9 % at
    frame 34 = last; without it (settle off, the loop before), best 112.0 % at frame 31 and 110 %
    from frame 36 on (drop 2 points at frame 39), 5 sign changes and a swing of 1.15 % by frame 50."""
    m, lines = shipped_run
    a, g = m["alpha_mse"], _share(m)
    drop = np.nanmax(g) - g[-1]
    print(f"shipped: best {np.nanmax(g):.1f} last {g[-1]:.1f} sign changes {sign_changes(a)} "
          f"swing {swing_percent(a):.2f} %")
    assert g[-1] > 95.0  # it arrives
    assert at_rest(a), (sign_changes(a), swing_percent(a))
    assert drop <= 1.0
    # the phase starts at the first rise and the record says which frames were undone
    assert any("every frame starts at rest" in line for line in lines)
    settling = np.asarray(m["settling"], dtype=float)
    assert np.nansum(settling == 2.0) > 0 and np.all(np.isnan(settling[:5]))
    # an undone frame holds the body: the same alpha MSE as the frame before it
    undone = np.flatnonzero(settling == 2.0)
    np.testing.assert_array_equal(a[undone], a[undone - 1])
    # the step: mpm's at frame 1, times settle_backoff after each undone frame
    mc = shipped(SHIPPED_FRAMES)
    expect = [mc.mpm.step_size]
    for k in range(1, len(settling) - 1):  # frame k + 1's step follows frame k
        expect.append(expect[-1] * mc.settle_backoff if settling[k] == 2.0 else expect[-1])
    np.testing.assert_array_equal(m["step_size"][1:], expect)
    # the shipped gate judges the physics loss with the alpha MSE until the physics loss stalls, then
    # the alpha MSE alone: before the hand-over no committed frame raised both, after it none raised alpha
    assert mc.settle_objective == "physics_then_alpha"
    handed = [line for line in lines if "the physics loss fell by less than" in line]
    assert len(handed) == 1, lines
    h = int(handed[0].split("from frame ")[1].split()[0])
    gated = np.flatnonzero(~np.isnan(settling))
    phys = np.asarray(m["physics_loss"], dtype=float)
    before, after = gated[gated < h], gated[gated >= h]
    assert before.size and after.size, (gated, h)
    assert not np.any((phys[before] > phys[before - 1]) & (a[before] > a[before - 1]))
    assert np.all(a[after] <= a[after - 1])


@pytest.fixture(scope="module")
def other_volumes(tiny, tmp_path_factory, mesh_dir):
    """A bunny at size 15 (57 % of the iso's volume) and an iso at size 12.4 (the bunny then holds 135 %)."""
    cfg = load_settings("config/config.yaml", overrides={**TEST_RESOLUTION, "shapes": {
        "bunny": {"size": 15.0}, "iso": {"size": 12.4}}})
    d = tmp_path_factory.mktemp("volumes")
    prepare_mesh_stage("bunny", cfg.shapes["bunny"], mesh_dir / "stanford-bunny.obj", d / "bunny15.h5")
    prepare_mesh_stage("iso", cfg.shapes["iso"], None, d / "iso124.h5")
    rasterize_target_stage(d / "bunny15.h5", d / "t_bunny15.h5", d / "t_bunny15.png", cfg.sampling, cfg.target, 0)
    sample_particles_stage(d / "iso124.h5", d / "p_iso124.h5", d / "p_iso124.png", cfg.sampling, 0)
    return d


@pytest.mark.parametrize("case, ratio", [("small_target", 0.57), ("small_source", 1.34)])
def test_a_target_of_another_volume_warns_and_settles(tiny, other_volumes, case, ratio):
    """The morph names the experiment, the volume ratio, the volume setting and the size that would
    match in its log and the run file, reaches the target's volume and the target, and comes to
    rest (at most two sign changes or a swing of 2 %, a drop of at most 2 points). Measured without the gate at the default scale: the bunny at 15.0 swings
    by 90 % of its alpha MSE every frame. Slow: a whole tiny full morph of 30 frames for each case."""
    _, d = tiny
    particles, target, size = ((d / "p_iso.h5", other_volumes / "t_bunny15.h5", 15.0) if case == "small_target"
                               else (other_volumes / "p_iso124.h5", d / "t_bunny.h5", 18.0))
    m, lines = _run(particles, target, other_volumes / f"{case}.h5", shipped(30), target_size=size)
    warning = [line for line in lines if "of the source's volume" in line]
    assert len(warning) == 1 and f"{case}:" in warning[0] and f"{100 * ratio:.0f} %" in warning[0], lines
    assert f"(now {size:g})" in warning[0]
    assert "plasticity.volume: target moves the body's rest volume there" in warning[0]
    assert warning[0].split("] warning: ", 1)[1] in m["attrs"]["warnings"]
    assert m["attrs"]["target_volume_ratio"] == pytest.approx(ratio, abs=0.02)
    a, g = m["alpha_mse"], _share(m)
    v = m["total_volume"]
    print(f"{case}: best {np.nanmax(g):.1f} last {g[-1]:.1f} sign changes {sign_changes(a)} "
          f"swing {swing_percent(a):.2f} % rest volume {m['rest_volume'][-1]:.3f} body {v[-1] / v[0]:.3f} "
          f"volume IoU {m['volume_iou'][-1]:.3f}")
    # the shipped plasticity.volume (target) moves the rest volume to the target's and the body
    # follows; measured here: best / last 105.0 / 105.0 % (small target), 102.8 / 102.8 % (small source),
    # and with volume keep at the default scale 67 % and 105 % (docs/study/log.md finding 242)
    wanted = m["attrs"]["target_volume_ratio"]
    assert m["rest_volume"][-1] == pytest.approx(wanted, rel=0.03)
    assert v[-1] / v[0] == pytest.approx(wanted, rel=0.10)
    assert g[-1] >= 95.0
    assert at_rest(a, max_swing=2 * REST_SWING_PERCENT), (sign_changes(a), swing_percent(a))
    assert np.nanmax(g) - g[-1] <= 2.0


def test_volume_mismatch_line_names_ratio_and_matching_size():
    assert VOLUME_MISMATCH == 0.10
    assert volume_mismatch("e", 1000.0, 1099.0) is None and volume_mismatch("e", 1000.0, 901.0) is None
    assert volume_mismatch("e", 1000.0, 1101.0) and volume_mismatch("e", 1000.0, 899.0)
    line = volume_mismatch("iso_bunny", 1170.0, 675.0, 15.0)
    assert line.startswith("iso_bunny: the target holds 58 % of the source's volume")
    # volume scales with size^3: 15 (1170 / 675)^(1/3) = 18.0
    assert "a target size of 18.0 (now 15)" in line
    assert "size of" not in volume_mismatch("e", 1000.0, 1400.0)


def test_gate_starts_at_the_first_rise_or_the_cycle_and_judges_against_the_accepted_frame():
    gate = SettleGate("after_first_rise", "alpha_mse", 0.5)
    assert not gate.note_restart(5, False) and gate.start is None
    assert gate.note_restart(7, True) and gate.start == 8 and gate.at_rest_after(7) and not gate.at_rest_after(6)
    cycle = SettleGate("after_cycle", "alpha_mse", 0.5)
    assert not cycle.note_restart(7, True) and not cycle.note_restart(8, False) and not cycle.note_restart(10, True)
    assert cycle.note_restart(12, True) and cycle.start == 13  # restarts at 10 and 12: the period-two cycle
    off = SettleGate("off", "alpha_mse", 0.5)
    assert not off.note_restart(7, True) and not off.note_restart(9, True) and off.start is None
    gate.accepted = AcceptedFrame(None, None, None, None, 0.0, {}, None, objective=1.0)
    assert not gate.rejects(7, {"alpha_mse": 2.0})  # before the phase
    assert gate.rejects(8, {"alpha_mse": 1.5}) and not gate.rejects(8, {"alpha_mse": 1.0})
    assert not gate.rejects(9, {"alpha_mse": 0.5})
    restored = SettleGate("after_first_rise", "alpha_mse", 0.5)
    restored.restore(gate.checkpoint())
    assert (restored.start, restored.last_restart) == (8, 7)
    # a method that does not render is never gated on the images
    assert settle_gate("after_first_rise", "alpha_mse", False, 0.5).onset == "off"
    assert settle_gate("after_first_rise", "physics", False, 0.5).objective_key == "physics_loss"



def test_physics_then_alpha_hands_the_gate_over_when_the_physics_loss_stops_falling():
    """settle_objective physics_then_alpha: the gate judges the physics loss while each accepted frame
    lowers it by at least settle_handover, then the alpha MSE; the hand-over survives a resume."""
    gate = settle_gate("after_first_rise", "physics_then_alpha", True, 0.5, handover=0.02)
    assert gate.objective_key == "physics_loss" and gate.handover_key == "alpha_mse"
    assert gate.note_restart(4, True) and gate.start == 5
    gate.accepted = AcceptedFrame(None, None, None, None, 0.0, {"alpha_mse": 0.1}, None, objective=100.0)
    assert not gate.after_accepted(4, 99.9)  # before the phase: no hand-over
    assert not gate.after_accepted(5, 97.0)  # fell by 3 %: the physics loss goes on judging
    gate.accepted = AcceptedFrame(None, None, None, None, 0.0, {"alpha_mse": 0.1}, None, objective=97.0)
    # before the hand-over a frame is undone where its physics loss and its alpha MSE both rose
    assert gate.rejects(6, {"physics_loss": 97.5, "alpha_mse": 0.11})
    assert not gate.rejects(6, {"physics_loss": 97.5, "alpha_mse": 0.09})
    assert not gate.rejects(6, {"physics_loss": 96.0, "alpha_mse": 0.11})
    assert gate.after_accepted(6, 97.5) and gate.handed_over == 7  # rose: hand over
    assert gate.objective_key == "alpha_mse"
    gate.accepted = AcceptedFrame(None, None, None, None, 0.0, {"alpha_mse": 0.09}, None, objective=0.09)
    assert gate.rejects(7, {"physics_loss": 90.0, "alpha_mse": 0.095})  # then the alpha MSE alone
    other = settle_gate("after_first_rise", "physics_then_alpha", True, 0.5, handover=0.02)
    other.note_restart(4, True)
    other.accepted = AcceptedFrame(None, None, None, None, 0.0, {}, None, objective=97.0)
    assert other.after_accepted(5, 96.0) and other.handed_over == 6  # fell by 1 %: hand over
    assert not gate.after_accepted(7, 10.0)  # once
    restored = settle_gate("after_first_rise", "physics_then_alpha", True, 0.5, handover=0.02)
    restored.restore(gate.checkpoint())
    assert (restored.handed_over, restored.objective_key) == (7, "alpha_mse")
    fresh = settle_gate("after_first_rise", "physics_then_alpha", True, 0.5, handover=0.02)
    fresh.restore(settle_gate("after_first_rise", "physics_then_alpha", True, 0.5).checkpoint())
    assert fresh.handed_over is None and fresh.objective_key == "physics_loss"
    # the other objectives never hand over
    plain = settle_gate("after_first_rise", "physics", True, 0.5, handover=0.02)
    plain.note_restart(4, True)
    plain.accepted = AcceptedFrame(None, None, None, None, 0.0, {}, None, objective=100.0)
    assert not plain.after_accepted(5, 100.0) and plain.objective_key == "physics_loss"


class _Killed(Exception):
    pass


@pytest.mark.usefixtures("checkpoint_every_frame")  # conftest: it kills a run
def test_a_run_killed_while_settling_resumes_to_the_uninterrupted_run(tiny, shipped_run, monkeypatch):
    """Killed in frame 38, after the gate has undone frames (from frame 15 in this run), the run
    resumes from its checkpoint (the accepted state) to the uninterrupted run. Every frame runs here
    (none held, so frame 38 is the 37th plasticity update); shipped_run holds its last frames, which
    changes none of its numbers. Slow: a 39-frame tiny morph run to its kill in frame 38, then
    resumed from its checkpoint to the end."""
    _, d = tiny
    mc = shipped(SHIPPED_FRAMES, settle_hold_below=0.0)
    full = shipped_run[0]
    assert np.nansum(np.asarray(full["settling"])[:38] == 2.0) > 0  # frames were undone before the kill
    real, calls = morph.chamfer_plasticity_step, {"n": 0}

    def dies_in_frame_38(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 37:  # plasticity from frame 2: its 37th update is frame 38's
            raise _Killed()
        return real(*args, **kwargs)

    monkeypatch.setattr(morph, "chamfer_plasticity_step", dies_in_frame_38)
    with pytest.raises(_Killed):
        run_morph(d / "p_iso.h5", d / "t_bunny.h5", d / "settle_resumed.h5", mc, name="resumed")
    assert read_metrics(d / "settle_resumed.h5.partial")["attrs"]["frames_completed"] == 37
    monkeypatch.setattr(morph, "chamfer_plasticity_step", real)
    resumed, _ = _run(d / "p_iso.h5", d / "t_bunny.h5", d / "settle_resumed.h5", mc)
    for key in ("alpha_mse", "physics_loss", "settling"):
        np.testing.assert_allclose(resumed[key], full[key], rtol=1e-4, err_msg=key)


def test_frames_held_under_the_step_share_are_the_undone_frames_without_their_work(tiny, shipped_run, monkeypatch):
    """settle_hold_below: a settling frame whose step has backed off under that share of mpm's is
    committed as the undone frame it would have been (shipped_run undoes every frame once its gate
    starts, so at 0.3 each one from the second back-off on is held) without its phases: no
    physics, NaN stage times; the record and the bodies are shipped_run's. Killed in the
    frame before the first held one, the run resumes into the held frames. Slow: a 39-frame tiny full
    morph to its kill, then resumed."""
    _, d = tiny
    mc = shipped(SHIPPED_FRAMES, settle_hold_below=0.3)
    full = shipped_run[0]
    settling, step = np.asarray(full["settling"]), np.asarray(full["step_size"])
    expect = np.flatnonzero((settling == 2.0) & (step < 0.3 * mc.mpm.step_size))
    assert len(expect) >= 3 and np.all(np.diff(expect) == 1) and expect[-1] == SHIPPED_FRAMES
    killed_in = int(expect[0]) - 1
    real, physics_at = morph.MorphRun.physics, []

    def recorded(self, k):
        physics_at.append(k)
        if k == killed_in and physics_at.count(k) == 1:
            raise _Killed()
        return real(self, k)

    monkeypatch.setattr(morph.MorphRun, "physics", recorded)
    with pytest.raises(_Killed):
        run_morph(d / "p_iso.h5", d / "t_bunny.h5", d / "settle_held.h5", mc, name="held")
    held, lines = _run(d / "p_iso.h5", d / "t_bunny.h5", d / "settle_held.h5", mc)
    for key in ("alpha_mse", "physics_loss", "settling", "step_size", "volume_iou", "gap_closed"):
        np.testing.assert_allclose(held[key], full[key], rtol=1e-9, err_msg=key)
    np.testing.assert_array_equal(np.flatnonzero(np.isnan(held["t_frame"][1:])) + 1, expect)
    assert killed_in in physics_at and not set(physics_at) & set(expect)  # the held frames' physics never ran
    said = [line for line in lines if "from here on the frames are held" in line]
    assert len(said) == 1 and f"frame {expect[0]}:" in said[0], said
    with h5py.File(d / "settle_held.h5") as a, h5py.File(d / "settle_shipped.h5") as b:
        for k in (killed_in, SHIPPED_FRAMES):
            np.testing.assert_allclose(frame_motion(a, k)[0], frame_motion(b, k)[0], rtol=0, atol=1e-12)


def test_the_accepted_frame_kept_in_files_is_the_one_kept_in_memory(tiny, shipped_run, monkeypatch):
    """On the CPU the accepted frame and its control are written to the partial run and read back
    when a frame is undone (FrameJudge.keep_accepted, as in shipped_run); kept in memory instead (the
    GPU's way), the run is the same: on the CPU the physics' sums are the same on every run
    (physmorph.mpm.lanes) and the tiny images' render runs on one thread, so what remains is the
    order in which the threads' float64 partial sums of the loss meet (~1e-15 of it).
    Slow: a whole 39-frame tiny full morph of its own, compared with shipped_run's."""
    _, d = tiny

    def in_memory(self, frame):
        self.solver.keep_control()
        return frame

    monkeypatch.setattr(FrameJudge, "keep_accepted", in_memory)
    held = _run(d / "p_iso.h5", d / "t_bunny.h5", d / "settle_in_memory.h5", shipped(SHIPPED_FRAMES))[0]
    on_disk = shipped_run[0]
    assert np.nansum(np.asarray(held["settling"]) == 2.0) > 0
    for key in ("alpha_mse", "physics_loss", "settling", "step_size", "volume_iou"):
        np.testing.assert_allclose(held[key], on_disk[key], rtol=1e-9, err_msg=key)


def test_a_spilled_accepted_frame_reads_back_exactly(tmp_path):
    rng = np.random.default_rng(0)
    n = 50
    st = ParticleState(x=rng.normal(size=(n, 3)), v=rng.normal(size=(n, 3)), F=rng.normal(size=(n, 3, 3)),
                       C=rng.normal(size=(n, 3, 3)), Fp=rng.normal(size=(n, 3, 3)), mass=rng.random(n),
                       volume=rng.random(n))
    mask = rng.random(n) > 0.5
    frame = AcceptedFrame(st, mask, rng.normal(size=(n, 3, 3)), None, 0.7, {"alpha_mse": 0.1}, np.ones(4), 0.1)
    spilled = frame.spill(tmp_path / "settle")
    assert spilled.state is None and spilled.g_F is None and spilled.objective == 0.1
    back, back_mask, g_F, g_x = spilled.arrays()
    for name in ("x", "v", "F", "C", "Fp", "mass", "volume"):
        np.testing.assert_array_equal(getattr(back, name), getattr(st, name), err_msg=name)
    np.testing.assert_array_equal(back_mask, mask)
    np.testing.assert_array_equal(g_F, frame.g_F)
    assert g_x is None and back_mask.dtype == bool
    # a later accepted frame replaces the files, one without g_F leaves none behind
    AcceptedFrame(st, mask, None, None, 0.7, {}, np.ones(4), 0.1).spill(tmp_path / "settle")
    assert not (tmp_path / "settle" / "g_F.npy").exists()


class _StubSolver:
    """What FrameJudge.steer asks of the solver, recorded."""

    overfill_weight = 0.0

    def __init__(self):
        self.calls = []

    def __getattr__(self, name):
        return lambda *a, **k: self.calls.append(name)


@pytest.mark.parametrize("regrow", [False, True])
def test_the_settle_step_backs_off_on_an_undone_frame_and_regrows_on_an_accepted_one(regrow):
    """settle_backoff after each undone frame; with settle_regrow the step grows back by its
    inverse after each accepted one, never above mpm's step_size."""
    from types import SimpleNamespace

    from physmorph.morph.frame_state import FrameState
    from physmorph.morph.steering import StepSchedule

    cfg = dataclasses.replace(MorphConfig(), settle_regrow=regrow, momentum_restart="off", settle_objective="alpha_mse")
    base = cfg.mpm.step_size
    inputs = SimpleNamespace(want_grad=True, device="cuda")  # not the CPU: the accepted frame stays in memory
    judge = FrameJudge(cfg, _StubSolver(), inputs, run=None, log=lambda line: None)
    n = 2
    eye = np.tile(np.eye(3), (n, 1, 1))
    st = ParticleState(x=np.zeros((n, 3)), v=np.zeros((n, 3)), F=eye, C=0 * eye, Fp=eye, mass=np.ones(n), volume=np.ones(n))
    fs = FrameState.at_start(st, np.zeros(n, bool), base, 0.0)
    judge.restart = SimpleNamespace(on=None, rise_on="alpha_mse", observe=lambda now: (False, False))
    judge.schedule = StepSchedule(base)
    judge.gate.start = 3
    judge.gate.accepted = AcceptedFrame(st, fs.mask, fs.g_F, fs.g_x, 0.0, {"alpha_mse": 1.0}, np.zeros(1), objective=1.0)
    steps = []
    # frames 3 and 4 rise (undone), 5 and 6 fall (accepted), 7 rises, 8-10 fall
    for k, alpha in zip(range(3, 11), [2.0, 2.0, 0.9, 0.8, 5.0, 0.7, 0.6, 0.5]):
        judge.steer(k, fs, {"alpha_mse": alpha, "step_size": judge.schedule.step}, np.zeros(1), {}, judge.schedule.step)
        steps.append(fs.next_step / base)
    if regrow:
        assert steps == [0.5, 0.25, 0.5, 1.0, 0.5, 1.0, 1.0, 1.0]
    else:
        assert steps == [0.5, 0.25, 0.25, 0.25, 0.125, 0.125, 0.125, 0.125]
