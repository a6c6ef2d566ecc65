"""Runs under failure: a run killed in a frame, at any write step, between checkpoints, while
writing its finished file or on a full disk resumes to the uninterrupted run; divergence stops
loudly while keeping completed frames; a second writer is refused; the stability monitor's
warnings persist."""

import dataclasses
import errno
import json
import os
import shutil

import h5py
import numpy as np
import pytest

import physmorph.morph.loop as morph
import physmorph.records.runfile as runfile
from physmorph.morph.stability import MorphDivergenceError
from physmorph.morph.loop import morph_config, run_morph
from physmorph.records.runfile import read_metrics
from physmorph.records.h5io import stored_checksum, stored_identity
from physmorph.records.runfile import RunFileError, RunLockedError, RunWriter, read_checkpoint
from physmorph.records.runkey import RunKey
from physmorph.stages import rasterize_target_stage

pytestmark = pytest.mark.usefixtures("checkpoint_every_frame")

def _short(tiny):
    pl = dataclasses.replace(morph_config(tiny[0], "iso_bunny_full").plasticity, start_frame=2)
    return dict(frames=3, plasticity=pl)


def _run_logged(tiny, out_name, target="t_bunny.h5", **changes):
    cfg, d = tiny
    mc = dataclasses.replace(morph_config(cfg, "iso_bunny_full"), progress=False, **{"release_frames": 0, **changes})
    log = []
    run_morph(d / "p_iso.h5", d / target, d / out_name, mc, name=out_name, log=log.append)
    return d / out_name, log


class _Killed(Exception):
    pass


@pytest.mark.parametrize("correspondence", ["nearest", "transport"])
def test_resume_equals_uninterrupted_run(tiny, monkeypatch, correspondence):
    """Killed in frame 4, a run resumes to the uninterrupted one, with the transport plan's
    destinations (computed at the first update, not checkpointed) recomputed on resume. Slow (~11 s
    for the first case): two tiny morphs of 5 frames, and the first case compiles the solver's kernels."""
    plasticity = dataclasses.replace(morph_config(tiny[0], "iso_bunny_full").plasticity, start_frame=2,
                                     correspondence=correspondence)
    frames = dict(frames=5, plasticity=plasticity)
    full = _run_logged(tiny, f"uninterrupted_{correspondence}.h5", **frames)[0]
    real = morph.chamfer_plasticity_step
    calls = {"n": 0}

    def dies_at_frame_4(*args, **kwargs):  # killed in the middle of frame 4's plasticity stage
        calls["n"] += 1
        assert (kwargs.get("destination") is not None) == (correspondence == "transport")
        if calls["n"] == 3:
            raise _Killed()
        return real(*args, **kwargs)

    monkeypatch.setattr(morph, "chamfer_plasticity_step", dies_at_frame_4)
    with pytest.raises(_Killed):
        _run_logged(tiny, f"resumed_{correspondence}.h5", **frames)[0]
    partial = tiny[1] / f"resumed_{correspondence}.h5.partial"
    assert read_metrics(partial)["attrs"]["frames_completed"] == 3
    monkeypatch.setattr(morph, "chamfer_plasticity_step", real)
    resumed = _run_logged(tiny, f"resumed_{correspondence}.h5", **frames)[0]
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
    with pytest.raises(MorphDivergenceError, match=r"frame 3: Fp became non-finite \(particle 7\)") as stop:
        _run_logged(tiny, "diverged.h5", frames=5, plasticity=pl)
    # the stop's frame, quantity and particle are data too (the stability map reads them, not the text)
    assert (stop.value.frame, stop.value.quantity, stop.value.particle) == (3, "Fp", 7)
    kept = read_metrics(tiny[1] / "diverged.h5.partial")  # frames 0..2 stay readable
    assert len(kept["alpha_mse"]) == 3 and np.isfinite(kept["alpha_mse"]).all()
    assert not (tiny[1] / "diverged.h5").exists()


# ------------------------------------------------------------------- run files under failure
# The write steps of one frame's commit (physmorph.records.runfile): the frame file, then the checkpoint,
# each written aside, fsynced, renamed, and its directory fsynced.
COMMIT_STEPS = [("write", "frame_{k:04d}.h5.tmp"), ("fsync", "frame_{k:04d}.h5.tmp"), ("replace", "frame_{k:04d}.h5"),
                ("fsync", "{dir}"), ("write", "checkpoint.h5.tmp"), ("fsync", "checkpoint.h5.tmp"),
                ("replace", "checkpoint.h5"), ("fsync", "{dir}")]
KILL_FRAME = 2


class _SigKill(BaseException):
    """A kill: nothing below it cleans up (unlike an Exception, which a commit cleans after)."""


@pytest.fixture(scope="module")
def uninterrupted_short(tiny):
    return _run_logged(tiny, "short_uninterrupted.h5", **_short(tiny))[0]


def _kill_at(monkeypatch, call: int, steps: list):
    """Patch the commit steps to record (step, file name) and kill at the ``call``-th step call."""
    real = {"write": runfile._write_aside, "fsync": runfile._fsync, "replace": runfile._replace}

    def wrap(step):
        def f(*args):
            steps.append((step, args[-1].name if step == "replace" else args[0].name))
            if len(steps) - 1 == call:
                if step == "write":
                    args[0].write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(300))  # a torn file, left behind
                raise _SigKill()
            return real[step](*args)
        return f

    for step, attr in (("write", "_write_aside"), ("fsync", "_fsync"), ("replace", "_replace")):
        monkeypatch.setattr(runfile, attr, wrap(step))
    return real


def _assert_same_run(resumed, full):
    a, b = read_metrics(full), read_metrics(resumed)
    for key in ("alpha_mse", "physics_loss", "fp_det_max", "total_volume"):
        np.testing.assert_allclose(b[key], a[key], rtol=1e-4, err_msg=key)
    with h5py.File(full) as fa, h5py.File(resumed) as fb:
        assert sorted(fb["states"]) == sorted(fa["states"])
        for k in ("x", "F", "Fp"):
            np.testing.assert_allclose(fb["states/frame_0003"][k][()], fa["states/frame_0003"][k][()], rtol=1e-3, atol=1e-4)


STEP_IDS = ["write-frame", "fsync-frame", "replace-frame", "fsync-dir-frame", "write-checkpoint", "fsync-checkpoint",
            "replace-checkpoint", "fsync-dir-checkpoint"]


@pytest.mark.parametrize("step", range(len(COMMIT_STEPS)), ids=STEP_IDS)
def test_kill_at_every_write_step_of_a_frame_resumes_to_the_uninterrupted_run(tiny, uninterrupted_short, monkeypatch, step):
    out_name = f"killed_{step}.h5"
    partial = tiny[1] / f"{out_name}.partial"
    steps = []
    real = _kill_at(monkeypatch, KILL_FRAME * len(COMMIT_STEPS) + step, steps)
    with pytest.raises(_SigKill):
        _run_logged(tiny, out_name, **_short(tiny))
    # The kill hit frame 2's commit at the intended step, after frames 0 and 1 were committed.
    expected = [(s, f.format(k=k, dir=partial.name)) for k in range(KILL_FRAME + 1) for s, f in COMMIT_STEPS]
    assert steps == expected[:len(steps)] and len(steps) == KILL_FRAME * len(COMMIT_STEPS) + step + 1
    for attr, fn in (("_write_aside", real["write"]), ("_fsync", real["fsync"]), ("_replace", real["replace"])):
        monkeypatch.setattr(runfile, attr, fn)
    # Killed before a step: frame 2 is committed once the checkpoint's rename has happened.
    committed = KILL_FRAME if step > COMMIT_STEPS.index(("replace", "checkpoint.h5")) else KILL_FRAME - 1
    assert read_metrics(partial)["attrs"]["resumes_after"] == committed
    segment_1 = read_checkpoint(partial / "checkpoint.h5").wall_time_segments_s
    out, log = _run_logged(tiny, out_name, **_short(tiny))
    assert f"[{out_name}] resuming after frame {committed}/3" in log
    assert not any("restarting" in line for line in log) and not partial.exists()
    _assert_same_run(out, uninterrupted_short)
    # Elapsed wall time adds up over the two segments.
    attrs = read_metrics(out)["attrs"]
    segments = json.loads(attrs["wall_time_segments_s"])
    assert len(segments) == 2 and segments[0] == pytest.approx(segment_1[0])
    assert attrs["wall_time_s"] == pytest.approx(sum(segments))


def test_killed_between_checkpoints_resumes_after_the_last_one_to_the_uninterrupted_run(tiny, uninterrupted_short,
                                                                                         monkeypatch):
    """With checkpoints at their wall-time cadence (here a clock under which writing one takes
    1 s: due again 50 s later, never within this run), frames 1 and 2 commit only their frame
    files; killed after frame 2, the rerun resumes after frame 0 and computes them again."""
    monkeypatch.setattr(runfile, "CHECKPOINT_WALL_SHARE", 0.02)
    clock = {"t": 0.0}

    def ticks():  # one second a call
        clock["t"] += 1.0
        return clock["t"]

    monkeypatch.setattr(runfile, "_clock", ticks)
    steps = []
    frame_2_done = 8 + 4 + 4 - 1  # frame 0's eight steps, then the frame files of frames 1 and 2
    real = _kill_at(monkeypatch, frame_2_done + 1, steps)  # killed at frame 3's first write
    with pytest.raises(_SigKill):
        _run_logged(tiny, "killed_between.h5", **_short(tiny))
    assert [f for _, f in steps if f.startswith("checkpoint")] == ["checkpoint.h5.tmp"] * 2 + ["checkpoint.h5"]
    for attr, fn in (("_write_aside", real["write"]), ("_fsync", real["fsync"]), ("_replace", real["replace"])):
        monkeypatch.setattr(runfile, attr, fn)
    partial = tiny[1] / "killed_between.h5.partial"
    attrs = read_metrics(partial)["attrs"]
    assert attrs["frames_completed"] == 2 and attrs["resumes_after"] == 0
    out, log = _run_logged(tiny, "killed_between.h5", **_short(tiny))
    assert "[killed_between.h5] resuming after frame 0/3" in log
    _assert_same_run(out, uninterrupted_short)


def test_kill_while_writing_the_finished_file_resumes_to_the_uninterrupted_run(tiny, uninterrupted_short, monkeypatch):
    """Killed just before the finished file's rename: nothing is lost, the rerun only finishes."""
    steps = []
    real = _kill_at(monkeypatch, 4 * len(COMMIT_STEPS) + 2, steps)  # frames 0..3 committed, then write, fsync, rename
    with pytest.raises(_SigKill):
        _run_logged(tiny, "killed_finishing.h5", **_short(tiny))
    assert steps[-3:] == [("write", "killed_finishing.h5.tmp"), ("fsync", "killed_finishing.h5.tmp"),
                          ("replace", "killed_finishing.h5")]
    for attr, fn in (("_write_aside", real["write"]), ("_fsync", real["fsync"]), ("_replace", real["replace"])):
        monkeypatch.setattr(runfile, attr, fn)
    assert not (tiny[1] / "killed_finishing.h5").exists()
    rerun_steps = []
    _kill_at(monkeypatch, 10 ** 9, rerun_steps)  # records, never kills
    out, log = _run_logged(tiny, "killed_finishing.h5", **_short(tiny))
    assert "[killed_finishing.h5] resuming after frame 3/3" in log
    # No frame is committed again: the rerun only writes the finished file.
    assert [s for s, _ in rerun_steps] == ["write", "fsync", "replace", "fsync"]
    assert rerun_steps[0] == ("write", "killed_finishing.h5.tmp")
    _assert_same_run(out, uninterrupted_short)


def test_disk_full_during_a_frame_keeps_the_last_frame_and_resumes(tiny, uninterrupted_short, monkeypatch):
    real = runfile._write_aside
    calls = {"n": 0}

    def fills_up(tmp, fill):
        calls["n"] += 1
        if calls["n"] == 2 * KILL_FRAME + 2:  # frame 2's checkpoint
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(tmp, fill)

    monkeypatch.setattr(runfile, "_write_aside", fills_up)
    with pytest.raises(RunFileError, match=r"checkpoint\.h5: disk full while writing the checkpoint of frame 2"):
        _run_logged(tiny, "disk_full.h5", **_short(tiny))
    monkeypatch.setattr(runfile, "_write_aside", real)
    out, log = _run_logged(tiny, "disk_full.h5", **_short(tiny))
    assert "[disk_full.h5] resuming after frame 1/3" in log
    _assert_same_run(out, uninterrupted_short)


@pytest.mark.parametrize("size", ["half", "same"])
def test_changed_target_restarts_the_run_with_the_reason(tiny, uninterrupted_short, monkeypatch, size):
    """Ctrl-C at frame 2, the target re-rasterized at another image size, rerun: the run starts
    again from frame 0 (frames scored against two targets would otherwise mix). Re-rasterized at
    the same size (the same data, another content checksum) it resumes to the uninterrupted run."""
    cfg, d = tiny
    name = f"changing_{size}"
    shutil.copy(d / "t_bunny.h5", d / f"t_{name}.h5")
    _kill_at(monkeypatch, KILL_FRAME * len(COMMIT_STEPS), [])
    with pytest.raises(_SigKill):
        _run_logged(tiny, f"{name}.h5", target=f"t_{name}.h5", **_short(tiny))
    monkeypatch.undo()
    s = cfg.sampling
    k = 2 if size == "half" else 1
    again = dataclasses.replace(cfg.target, width=cfg.target.width // k, height=cfg.target.height // k)
    rasterize_target_stage(d / "bunny.h5", d / f"t_{name}.h5", d / f"t_{name}.png", s, again, 0)
    assert stored_checksum(d / f"t_{name}.h5") != stored_checksum(d / "t_bunny.h5")
    out, log = _run_logged(tiny, f"{name}.h5", target=f"t_{name}.h5", **_short(tiny))
    attrs = read_metrics(out)["attrs"]
    assert json.loads(attrs["input_checksums"])["target"] == stored_identity(d / f"t_{name}.h5")
    if size == "same":
        assert any("resuming" in line for line in log) and not any("restarting" in line for line in log), log
        _assert_same_run(out, uninterrupted_short)
        return
    assert any(f"restarting {name}.h5.partial from frame 0: input 'target' changed" in line for line in log), log
    assert not any("resuming" in line for line in log)
    assert len(json.loads(attrs["wall_time_segments_s"])) == 1


def test_second_writer_of_a_run_is_refused_and_the_first_keeps_its_frames(tiny, monkeypatch):
    cfg, d = tiny
    _kill_at(monkeypatch, KILL_FRAME * len(COMMIT_STEPS), [])
    with pytest.raises(_SigKill):
        _run_logged(tiny, "two_writers.h5", **_short(tiny))
    monkeypatch.undo()
    partial = d / "two_writers.h5.partial"
    before = {p.name: p.read_bytes() for p in partial.glob("*.h5")}
    key = RunKey.from_attrs(read_checkpoint(partial / "checkpoint.h5").key.attrs())
    with RunWriter(d / "two_writers.h5", key):  # the first writer, still running
        with pytest.raises(RunLockedError, match=rf"PID {os.getpid()}"):
            _run_logged(tiny, "two_writers.h5", **_short(tiny))
    assert {p.name: p.read_bytes() for p in partial.glob("*.h5")} == before
    out, log = _run_logged(tiny, "two_writers.h5", **_short(tiny))
    assert "[two_writers.h5] resuming after frame 1/3" in log and read_metrics(out)["attrs"]["status"] == "complete"


# ------------------------------------------------------------------------ stability warnings
def test_stability_monitor_warns_once_per_streak_and_survives_a_resume():
    from physmorph.settings.plasticity import PlasticityConfig

    pc = PlasticityConfig()
    lo, hi = pc.det_bounds
    logged = []
    mon = morph.StabilityMonitor(pc, log=logged.append, pinned_share=0.5, pinned_frames=3, rising_frames=2)
    free = np.tile(np.eye(3), (4, 1, 1))
    pinned = free * lo ** (1 / 3)  # det at the lower clamp bound, isotropic
    assert mon.update(1, pinned, 0.5) == [] and mon.update(2, pinned, 0.4) == []
    out = mon.update(3, pinned, 0.3)
    assert len(out) == 1 and "frame 3: 100.0 % of particles have Fp pinned at a clamp bound" in out[0]
    assert "plasticity.eta" in out[0] and logged == out
    assert mon.update(4, pinned, 0.2) == []  # once per streak
    # alpha MSE rising two frames in a row; the monitor's state goes through a checkpoint.
    assert mon.update(5, free, 0.25) == []
    resumed = morph.StabilityMonitor(pc, log=logged.append, pinned_share=0.5, pinned_frames=3, rising_frames=2)
    resumed.restore(mon.state())
    out = resumed.update(6, free, 0.3)
    assert out == ["frame 6: alpha MSE rose for 2 frames in a row (now 0.3)"]
    assert mon.update(6, free, 0.3) == out  # the uninterrupted monitor says the same
    assert resumed.update(7, free, 0.1) == [] and resumed.rising_streak == 0


def test_stability_warnings_are_recorded_in_the_run_file(tiny, monkeypatch):
    real = morph.StabilityMonitor.update

    def update(self, frame, Fp, alpha_mse, **measures):
        return real(self, frame, Fp, alpha_mse, **measures) + ([f"frame {frame}: test warning"] if frame == 2 else [])

    monkeypatch.setattr(morph.StabilityMonitor, "update", update)
    out, _ = _run_logged(tiny, "warned.h5", **_short(tiny))
    assert "frame 2: test warning" in json.loads(read_metrics(out)["attrs"]["warnings"])
