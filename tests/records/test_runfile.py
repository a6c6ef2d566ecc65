"""The run-file module on hand-made frames (no solver): damaged or foreign checkpoints are refused
with their name, a changed key restarts, one writer at a time, disk full keeps the last frame,
and reading runs imports neither taichi nor torch."""

import errno
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

import physmorph.records.runfile as runfile
from physmorph.records.runfile import (SCALARS, ArrayBySlots, RunFileError, RunLockedError, RunWriter, describe_run,
                               read_checkpoint, read_metrics)
from physmorph.records.runkey import RunKey

REPO = Path(__file__).resolve().parents[2]
KEY = RunKey(json.dumps({"frames": 3}), (("particles", "aa" * 32), ("target", "bb" * 32)))
N, V = 5, 2


pytestmark = pytest.mark.usefixtures("checkpoint_every_frame")  # conftest


def _state(frame: int) -> dict:  # a recognisable loop state for each frame
    rng = np.random.default_rng(frame)
    return {"x": rng.normal(size=(N, 3)), "F": np.tile(np.eye(3), (N, 1, 1)) * (1 + frame),
            "Fp": np.tile(np.eye(3), (N, 1, 1)), "adam_step": frame, "injection_scale": 0.5 * frame}


def _write_frames(out: Path, frames: int, key: RunKey = KEY) -> None:
    with RunWriter(out, key) as w:
        assert w.resume(log=lambda m: None) is None
        w.set_meta({"experiment": "hand", "views": V})
        for k in range(frames):
            st = _state(k)
            w.commit(k, {"alpha_mse": 1.0 / (k + 1)}, np.full(V, 1.0 / (k + 1)), st, [f"w{k}"] if k == 1 else [],
                     {"x": st["x"], "F": st["F"], "adam_step": st["adam_step"], "injection_scale": st["injection_scale"]})


def test_frames_commit_read_and_finish(tmp_path):
    out = tmp_path / "run.h5"
    _write_frames(out, 3)
    d = runfile.partial_dir(out)
    ck = read_checkpoint(d / "checkpoint.h5")
    assert ck.frame == 2 and ck.data["adam_step"] == 2 and ck.key == KEY
    np.testing.assert_array_equal(ck.data["x"], _state(2)["x"])
    m = read_metrics(d)  # a partial run: its committed frames
    np.testing.assert_allclose(m["alpha_mse"], [1.0, 0.5, 1 / 3])
    assert np.isnan(m["loss_dt"]).all() and m["alpha_mse_views"].shape == (3, V)
    assert "frames 0..2 committed" in describe_run(d)
    with h5py.File(d / "frame_0001.h5") as f:  # the frame's arrays as stored: compressed chunks
        stored = {name: (f[f"state/{name}"].chunks, f[f"state/{name}"].id.read_direct_chunk((0,) * f[f"state/{name}"].ndim))
                  for name in f["state"]}
    log = []
    with RunWriter(out, KEY) as w:
        assert w.resume(log=log.append).frame == 2 and not log
        w.finish("complete", {"injection_scale": 1.0}, {"frames": 3})
    with h5py.File(out) as f:  # the finished file holds them byte for byte, chunked as they were
        assert {name: (f[f"states/frame_0001/{name}"].chunks,
                       f[f"states/frame_0001/{name}"].id.read_direct_chunk((0,) * f[f"states/frame_0001/{name}"].ndim))
                for name in f["states/frame_0001"]} == stored
    assert not d.exists()
    m = read_metrics(out)
    assert set(m) == set(SCALARS) | {"alpha_mse_views", "attrs"}
    np.testing.assert_allclose(m["alpha_mse"], [1.0, 0.5, 1 / 3])
    a = m["attrs"]
    assert a["status"] == "complete" and a["frames_completed"] == 2 and a["experiment"] == "hand"
    assert json.loads(a["warnings"]) == ["w1"] and a["run_key"] == KEY.digest
    segments = json.loads(a["wall_time_segments_s"])
    assert len(segments) == 2 and a["wall_time_s"] == pytest.approx(sum(segments))
    with h5py.File(out) as f:
        np.testing.assert_allclose(f["states/frame_0001/x"][()], _state(1)["x"].astype(np.float32))
        saved = f["states/frame_0001/F"]
        assert (saved.compression, saved.compression_opts, saved.shuffle) == ("gzip", 1, True)
    # The finished file's metrics are checked: zeroed bytes in them are refused with the file's name.
    with h5py.File(out, "a") as f:
        f["metrics/alpha_mse"][1] = 0.0
    with pytest.raises(RunFileError, match=r"run\.h5: its metrics do not match their checksum"):
        read_metrics(out)


def test_a_checkpoint_array_given_by_slots_is_stored_as_the_whole_array(tmp_path):
    """A checkpoint's ArrayBySlots (the control, written a slot at a time) reads back as the array
    its slots make, in its dtype and the whole array's layout, and the checkpoint verifies (its
    checksum hashed from the file where the whole array is hashed from memory)."""
    control = np.random.default_rng(4).normal(size=(4, N, 3, 3)).astype(np.float32)
    slots_asked = []

    def slot(s):
        slots_asked.append(s)
        return control[s].copy()

    layouts = {}
    for how, value in (("whole", control), ("slots", ArrayBySlots(control.shape, control.dtype, slot))):
        out = tmp_path / how / "run.h5"
        with RunWriter(out, KEY) as w:
            assert w.resume(log=lambda m: None) is None
            w.commit(0, {"alpha_mse": 1.0}, np.ones(V), _state(0), [], {"x": _state(0)["x"], "control": value})
        ck = read_checkpoint(runfile.partial_dir(out) / "checkpoint.h5")
        assert ck.data["control"].dtype == np.float32
        np.testing.assert_array_equal(ck.data["control"], control)
        with h5py.File(runfile.partial_dir(out) / "checkpoint.h5") as f:
            ds = f["control"]
            layouts[how] = (ds.shape, ds.dtype, ds.chunks, ds.compression)
    assert slots_asked == [0, 1, 2, 3] and layouts["whole"] == layouts["slots"]


def test_checkpoint_follows_at_its_wall_share_and_a_resume_recomputes_the_frames_after_it(tmp_path, monkeypatch):
    """With a checkpoint that takes 1 s to write and frames of 10 s, at a 2 % share the checkpoint
    follows frame 0, then the first frame at least 50 s after it ended, and the last frame; its
    state is gathered only then. Killed after frame 7, the run resumes after frame 6."""
    now = {"t": 0.0}
    monkeypatch.setattr(runfile, "CHECKPOINT_WALL_SHARE", 0.02)
    monkeypatch.setattr(runfile, "_clock", lambda: now["t"])
    real, written = runfile._write_aside, []

    def takes_a_second(tmp, fill):
        real(tmp, fill)
        if tmp.name == "checkpoint.h5.tmp":
            now["t"] += 1.0
            with h5py.File(tmp) as f:
                written.append(int(f.attrs["frame"]))

    monkeypatch.setattr(runfile, "_write_aside", takes_a_second)
    gathered = []

    def checkpoint_of(k):
        def gather():
            gathered.append(k)
            return {"x": _state(k)["x"], "adam_step": k}
        return gather

    out = tmp_path / "run.h5"
    with RunWriter(out, KEY) as w:
        w.resume(log=lambda m: None)
        w.set_meta({"experiment": "hand", "views": V})
        for k in range(9):
            now["t"] = 10.0 * k + (0.5 if k > 0 else 0.0)  # frame 0's checkpoint ends at 1 s
            w.commit(k, {"alpha_mse": 1.0 / (k + 1)}, np.ones(V), None, [], checkpoint_of(k), last=k == 8)
            if k == 7:
                break  # killed before frame 8
    assert written == [0, 6] and gathered == [0, 6]  # 0 -> due at 51 s: frame 6 (60.5 s) -> due at 111.5 s
    d = runfile.partial_dir(out)
    m = read_metrics(d)
    assert m["attrs"]["frames_completed"] == 7 and m["attrs"]["resumes_after"] == 6 and len(m["alpha_mse"]) == 8
    with RunWriter(out, KEY) as w:
        ck = w.resume(log=lambda msg: None)
        assert ck.frame == 6 and ck.data["adam_step"] == 6
        np.testing.assert_array_equal(ck.data["x"], _state(6)["x"])
        assert not (d / "frame_0007.h5").exists()  # computed again by the resumed run
        now["t"] = 200.0
        w.commit(7, {"alpha_mse": 0.125}, np.ones(V), None, [], checkpoint_of(7))  # a resumed writer checkpoints its first frame
        now["t"] = 205.0
        w.commit(8, {"alpha_mse": 1 / 9}, np.ones(V), None, [], checkpoint_of(8), last=True)  # the last frame
    assert written == [0, 6, 7, 8] and read_checkpoint(d / "checkpoint.h5").frame == 8


def test_checksums_hashed_from_memory_equal_the_stored_bytes(tmp_path):
    """Frame files, checkpoints and the finished file hash the arrays they were written from (no read
    back): each stamp equals the checksum recomputed from the file, for float64, float32, bool, int
    and non-contiguous arrays; an array whose dtype is not the dataset's is read back instead."""
    from physmorph.records.h5io import CHECKSUM_ATTR, content_checksum, stamp_checksum

    out = tmp_path / "run.h5"
    rng = np.random.default_rng(3)
    with RunWriter(out, KEY) as w:
        w.resume(log=lambda m: None)
        w.set_meta({"experiment": "hand", "views": V})
        for k in range(2):
            st = _state(k)
            w.commit(k, {"alpha_mse": 1.0}, np.ones(V), st, [],
                     {"x": st["x"], "F": np.transpose(rng.normal(size=(N, 3, 3)), (0, 2, 1)),
                      "mask": rng.random(N) < 0.5, "control": rng.normal(size=(1, N, 3, 3)).astype(np.float32),
                      "index": np.arange(N), "adam_step": k})
        d = runfile.partial_dir(out)
        files = sorted(d.glob("*.h5"))
        assert len(files) == 3
        for path in files:
            with h5py.File(path) as f:
                assert f.attrs[CHECKSUM_ATTR] == content_checksum(f), path.name
        w.finish("complete", {}, {"frames": 2})
    with h5py.File(out) as f:
        assert f.attrs[CHECKSUM_ATTR] == content_checksum(f)
    with h5py.File(tmp_path / "mixed.h5", "w") as f:
        a = rng.normal(size=(4, 3))
        f.create_dataset("a", data=a.astype(np.float32))
        stamp_checksum(f, written={"a": a})  # float64 given for a float32 dataset: read back
        assert f.attrs[CHECKSUM_ATTR] == content_checksum(f)


def test_the_data_digest_leaves_out_how_a_file_was_made_and_is_verified(tmp_path):
    """Two files with the same data written at other times, commits and package versions: other
    content checksums, one data digest; any other attribute or byte changes the digest, and a file
    whose stored digest was altered is refused like one whose content was."""
    from physmorph.records.h5io import (DATA_ATTR, EXECUTION_ATTRS, StageInputError, atomic_h5, open_h5, stamp_checksum,
                                stored_checksum, stored_identity)

    def write(name: str, made: dict, value: float = 1.0, dx: float = 0.5):
        with atomic_h5(tmp_path / name, {"stage": "t"}) as f:
            f.create_dataset("x", data=np.full((4, 3), value))
            f.attrs["dx"] = dx
        with h5py.File(tmp_path / name, "r+") as f:  # as another machine, commit and time would have made it
            for key, v in made.items():
                f.attrs[key] = v
            stamp_checksum(f)
        return tmp_path / name

    a = write("a.h5", {"wall_time_s": 1.0, "peak_rss_mb": 10.0, "git_commit": "aaaa", "git_dirty": "no"})
    b = write("b.h5", {"wall_time_s": 2.0, "peak_rss_mb": 20.0, "git_commit": "bbbb", "git_dirty": "yes",
                       "package_versions": "{}", "physmorph_version": "0"})
    assert {"wall_time_s", "peak_rss_mb", "git_commit", "git_dirty"} <= EXECUTION_ATTRS
    assert stored_checksum(a) != stored_checksum(b) and stored_identity(a) == stored_identity(b)
    assert stored_identity(write("c.h5", {}, value=2.0)) != stored_identity(a)
    assert stored_identity(write("d.h5", {}, dx=0.25)) != stored_identity(a)
    with h5py.File(a, "r+") as f:
        f.attrs[DATA_ATTR] = "0" * 64
    with pytest.raises(StageInputError, match=r"a\.h5: content does not match its data digest"):
        open_h5(a).close()


def test_frames_written_before_a_metric_existed_resume_with_it_as_nan(tmp_path, monkeypatch):
    """A run begun by a writer that did not know a scalar yet, finished by one that does: the
    finished file has the scalar, NaN for the older frames and its value for the newer."""
    out = tmp_path / "run.h5"
    old = tuple(name for name in SCALARS if name != "volume_iou")
    monkeypatch.setattr(runfile, "SCALARS", old)
    _write_frames(out, 2)
    monkeypatch.setattr(runfile, "SCALARS", SCALARS)
    with RunWriter(out, KEY) as w:
        assert w.resume(log=lambda m: None).frame == 1
        st = _state(2)
        w.commit(2, {"alpha_mse": 1 / 3, "volume_iou": 0.7}, np.full(V, 1 / 3), st, [], {"x": st["x"]})
        w.finish("complete", {}, {"frames": 3})
    m = read_metrics(out)
    np.testing.assert_allclose(m["volume_iou"], [np.nan, np.nan, 0.7])
    np.testing.assert_allclose(m["alpha_mse"], [1.0, 0.5, 1 / 3])


def _damage(path: Path, how: str) -> None:
    data = path.read_bytes()
    if how == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif how == "zero-filled":
        path.write_bytes(bytes(len(data)))
    elif how == "zeroed data":  # the stored particle positions zeroed, the file otherwise intact
        x = _state(1)["x"].tobytes()
        i = data.index(x)
        path.write_bytes(data[:i] + bytes(len(x)) + data[i + len(x):])
    else:
        raise ValueError(how)


@pytest.mark.parametrize("how", ["truncated", "zero-filled", "zeroed data"])
def test_damaged_checkpoint_is_refused_naming_file_reason_and_remedy(tmp_path, how):
    out = tmp_path / "run.h5"
    _write_frames(out, 2)
    ck = runfile.partial_dir(out) / "checkpoint.h5"
    _damage(ck, how)
    with RunWriter(out, KEY) as w:
        with pytest.raises(RunFileError) as err:
            w.resume(log=lambda m: None)
    msg = str(err.value)
    assert str(ck) in msg and "rm -r" in msg and "restart" in msg
    assert ("not a readable HDF5 file" in msg or "does not match its checksum" in msg or "unreadable" in msg), msg
    assert ck.exists()  # nothing is deleted behind the user's back


def _damage_frame(path: Path, how: str) -> None:
    """A committed frame file damaged: its stored alpha MSE (uncompressed, 1/2 in frame 1) changed to
    another float, or the whole file truncated or zero-filled."""
    if how == "a metric changed":
        data = path.read_bytes()
        i = data.index(np.float64(0.5).tobytes())
        path.write_bytes(data[:i] + np.float64(0.25).tobytes() + data[i + 8:])
    else:
        _damage(path, how)


@pytest.mark.parametrize("how", ["truncated", "zero-filled", "a metric changed"])
def test_a_damaged_frame_file_is_refused_at_resume_at_finish_and_in_the_partial_metrics(tmp_path, how):
    """Each committed frame file is verified whenever it is read (its datasets read once and hashed
    from memory): by a resume, by the finish that assembles the run, and by a partial run's metrics."""
    out = tmp_path / "run.h5"
    _write_frames(out, 3)
    frame1 = runfile.partial_dir(out) / "frame_0001.h5"
    _damage_frame(frame1, how)
    expected = ("not a readable HDF5 file", "does not match its checksum", "unreadable")

    def refused(err) -> None:
        msg = str(err.value)
        assert str(frame1) in msg and "rm -r" in msg and any(e in msg for e in expected), msg

    with RunWriter(out, KEY) as w, pytest.raises(RunFileError) as err:
        w.resume(log=lambda m: None)
    refused(err)
    with pytest.raises(RunFileError) as err:
        read_metrics(runfile.partial_dir(out))
    refused(err)
    # damaged after a resume, before the finish: the finish refuses it and writes no run file
    shutil.rmtree(runfile.partial_dir(out))
    _write_frames(out, 3)
    with RunWriter(out, KEY) as w:
        w.resume(log=lambda m: None)
        _damage_frame(frame1, how)
        with pytest.raises(RunFileError) as err:
            w.finish("complete", {}, {"frames": 3})
    refused(err)
    assert not out.exists() and frame1.exists()  # nothing deleted, nothing half written


def test_foreign_file_as_checkpoint_is_refused(tmp_path):
    out = tmp_path / "run.h5"
    _write_frames(out, 1)
    ck = runfile.partial_dir(out) / "checkpoint.h5"
    with h5py.File(ck, "w") as f:
        f["x"] = np.zeros(3)
    with RunWriter(out, KEY) as w, pytest.raises(RunFileError, match=r"checkpoint\.h5: not a physmorph-checkpoint/2 file"):
        w.resume(log=lambda m: None)


def test_a_checkpoint_of_the_earlier_format_is_refused_by_name(tmp_path):
    """The loop state's format changed (one FrameState, physmorph.morph.frame_state): a checkpoint an
    older version wrote is refused naming both formats and the way to restart, not half read."""
    out = tmp_path / "run.h5"
    _write_frames(out, 2)
    ck = runfile.partial_dir(out) / "checkpoint.h5"
    with h5py.File(ck, "r+") as f:
        f.attrs["format"] = "physmorph-checkpoint/1"
    with RunWriter(out, KEY) as w, pytest.raises(RunFileError) as err:
        w.resume(log=lambda m: None)
    msg = str(err.value)
    assert "checkpoint.h5: not a physmorph-checkpoint/2 file (format 'physmorph-checkpoint/1')" in msg, msg
    assert "rm -r" in msg and "restart the run from frame 0" in msg
    assert ck.exists()


def test_old_single_file_partial_is_refused(tmp_path):
    out = tmp_path / "run.h5"
    runfile.partial_dir(out).write_bytes(b"\x89HDF old format")
    with pytest.raises(RunFileError, match=r"run\.h5\.partial: a partial run in the older single-file format.*delete it"):
        RunWriter(out, KEY).acquire()


def test_changed_key_restarts_with_the_reason(tmp_path):
    out = tmp_path / "run.h5"
    _write_frames(out, 2)
    changed = RunKey(KEY.settings, (("particles", "aa" * 32), ("target", "cc" * 32)))
    log = []
    with RunWriter(out, changed) as w:
        assert w.resume(log=log.append) is None
    assert len(log) == 1 and "input 'target' changed (content checksum bbbbbbbbbbbb -> cccccccccccc)" in log[0]
    assert not list(runfile.partial_dir(out).glob("*.h5"))  # nothing of the old run is kept
    settings = RunKey(json.dumps({"frames": 4}), KEY.inputs)
    assert settings.changes_from(KEY) == ["settings changed (frames)"]


def test_interrupted_commit_leftovers_are_removed_on_resume(tmp_path):
    out = tmp_path / "run.h5"
    _write_frames(out, 2)
    d = runfile.partial_dir(out)
    (d / "checkpoint.h5.tmp").write_bytes(b"torn")
    (d / "frame_0002.h5.tmp").write_bytes(b"torn")
    (d / "frame_0002.h5").write_bytes((d / "frame_0001.h5").read_bytes())  # committed file, uncommitted frame
    with RunWriter(out, KEY) as w:
        assert w.resume(log=lambda m: None).frame == 1
    assert sorted(p.name for p in d.iterdir()) == ["LOCK", "checkpoint.h5", "frame_0000.h5", "frame_0001.h5"]


def test_disk_full_keeps_the_last_committed_frame(tmp_path, monkeypatch):
    out = tmp_path / "run.h5"
    _write_frames(out, 2)
    real = runfile._write_aside

    def full(tmp, fill):
        if tmp.name == "checkpoint.h5.tmp":
            tmp.write_bytes(b"\0" * 100)  # what got written before the disk filled up
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(tmp, fill)

    monkeypatch.setattr(runfile, "_write_aside", full)
    with RunWriter(out, KEY) as w:
        w.resume(log=lambda m: None)
        st = _state(2)
        with pytest.raises(RunFileError, match=r"checkpoint\.h5: disk full while writing the checkpoint of frame 2; "
                                               r"the last committed frame is kept"):
            w.commit(2, {"alpha_mse": 0.3}, np.zeros(V), None, [], {"x": st["x"]})
    monkeypatch.setattr(runfile, "_write_aside", real)
    assert not (runfile.partial_dir(out) / "checkpoint.h5.tmp").exists()
    with RunWriter(out, KEY) as w:
        ck = w.resume(log=lambda m: None)
    assert ck.frame == 1
    np.testing.assert_array_equal(ck.data["x"], _state(1)["x"])


_HOLDER = """
import sys, time
from physmorph.records.runfile import RunWriter
from physmorph.records.runkey import RunKey
w = RunWriter(sys.argv[1], RunKey('{"frames": 3}', (("particles", "aa" * 32), ("target", "bb" * 32))))
w.acquire()
print("locked", flush=True)
time.sleep(60)
"""


def test_second_writer_is_refused_with_the_holders_pid_and_the_first_run_survives(tmp_path):
    out = tmp_path / "run.h5"
    _write_frames(out, 2)
    d = runfile.partial_dir(out)
    before = {p.name: p.read_bytes() for p in d.glob("*.h5")}
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    holder = subprocess.Popen([sys.executable, "-c", _HOLDER, str(out)], stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(RunLockedError, match=rf"another process \(PID {holder.pid}\) is writing this run"):
            with RunWriter(out, KEY) as w:
                w.resume(log=lambda m: None)
        with pytest.raises(RunLockedError):  # a writer with another key does not clear it either
            RunWriter(out, RunKey("{}", ())).acquire()
    finally:
        holder.kill()
        holder.wait()
    assert {p.name: p.read_bytes() for p in d.glob("*.h5")} == before
    with RunWriter(out, KEY) as w:  # the lock went with its process: never stale
        assert w.resume(log=lambda m: None).frame == 1


def test_nothing_opens_a_run_file_in_a_mode_that_can_create_it():
    """Run files are only created fresh ("w-", aside) or read ("r"); no "a" or "w" on existing files."""
    src = (REPO / "physmorph" / "records" / "runfile.py").read_text() + (REPO / "physmorph" / "morph" / "loop.py").read_text()
    modes = [line for line in src.splitlines() if "h5py.File(" in line]
    assert modes and all(('"r")' in line or '"w-")' in line) for line in modes), modes


def test_reading_settings_and_runs_and_building_tables_imports_neither_taichi_nor_torch():
    # the workflow parses the config (every experiment's MorphConfig) on each snakemake call,
    # dry runs included: Taichi and torch would add ~3 s to each
    code = ("import sys, physmorph.records.runfile, physmorph.reports.tables, physmorph.studies.tradeoff, physmorph.reports.figures; "
            "from physmorph.settings.workflow import load_settings; "
            f"s = load_settings({str(REPO / 'config' / 'config.yaml')!r}); "
            "[s.experiment_config(e) for e in s.experiments]; "
            "print(sorted(m for m in ('taichi', 'torch') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "PYTHONPATH": str(REPO)})
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_every_frame_keeps_its_motion_for_the_video(tmp_path):
    """A frame without a saved state keeps x (float32) and F (float16) as its motion; the finished
    file holds both groups, and frame_motion reads any frame from either."""
    out = tmp_path / "run.h5"
    with RunWriter(out, KEY) as w:
        w.resume(log=lambda m: None)
        w.set_meta({"experiment": "hand", "views": V})
        for k in range(4):
            st = _state(k)
            saved = k in (0, 3)
            w.commit(k, {"alpha_mse": 1.0}, np.ones(V), st if saved else None, [], {"x": st["x"]}, last=k == 3,
                     motion={"x": st["x"], "F": st["F"] + 1e-3 * k})
        w.finish("complete", {}, {"frames": 3})
    with h5py.File(out) as f:
        assert sorted(f["states"]) == ["frame_0000", "frame_0003"]
        assert sorted(f["motion"]) == ["frame_0001", "frame_0002"]
        assert f["motion/frame_0002/F"].dtype == np.float16 and f["motion/frame_0002/x"].dtype == np.float32
        for k in range(4):
            x, F = runfile.frame_motion(f, k)
            np.testing.assert_allclose(x, _state(k)["x"], rtol=1e-6, atol=1e-6)
            want = _state(k)["F"] + (1e-3 * k if k in (1, 2) else 0.0)
            np.testing.assert_allclose(F, want, rtol=1e-3)
        with pytest.raises(RunFileError, match="frame 4 has no positions"):
            runfile.frame_motion(f, 4)
