"""Run files of the morph stage: write (one frame at a time, all or nothing), read, describe.

This module imports neither the solver nor the renderer (no taichi, no torch): tables, figures and
the speed/accuracy study read runs through it.

A finished run is one HDF5 file ``<out>``:
  attrs     the run's description (experiment, method, n_particles, views, ...), its settings
            (``config_record``), the content checksums of its inputs (``input_checksums``) and the
            ``run_key`` made of both, ``status``, ``frames_completed``, ``wall_time_s`` (summed over
            resumed segments, one entry each in ``wall_time_segments_s``), ``warnings`` (a JSON
            list), provenance, and ``metrics_sha256`` / ``content_sha256`` (written last)
  /metrics  one dataset per SCALARS name, [frames + 1] (index 0 = the initial state), and
            ``alpha_mse_views`` [frames + 1, V]
  /states   frame_XXXX/{x, F, Fp} float32, the frames the run chose to save
  /motion   frame_XXXX/{x float32, F float16} for every other frame: what a video of every frame
            needs (x and F shade the Gaussians; F at half precision, ~5e-4 relative, keeps a
            paper-scale run's file near 0.6 GB where full states every frame would take 1.3 GB)

While it runs, a run lives in the directory ``<out>.partial/``:
  LOCK              held (fcntl.flock) by the one process writing the run; holds that PID
  frame_XXXX.h5     one per committed frame: its metrics, saved state and warnings (frame 0 also
                    holds the run's description)
  checkpoint.h5     the loop state after a committed frame: what a resume continues from
Every file there is written aside (``*.tmp``), flushed to disk (fsync) and renamed into place
(os.replace), and carries a format tag, its frame number, the run key and a content checksum
written last: a file is either absent or complete. Each frame commits its frame file; the
checkpoint follows at the first frame, the last, and between them once the frames since the
previous one took ``1 / CHECKPOINT_WALL_SHARE`` times what writing it took (at the paper's scale
it is ~0.2 GB: written every frame it cost ~8 % of the run). A resume continues after the
checkpoint's frame: the frame files beyond it are removed and computed again (the same frames: a
run is deterministic given its checkpoint).
A run resumes only when its key (settings and input checksums) equals the checkpoint's; otherwise
it restarts and says what changed. A damaged or foreign file of a run is refused with its name, the
reason and what to delete; a path that is no run (physmorph.records.runfile_cli) is named as such.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import h5py
import numpy as np

from physmorph.settings.render import LOSS_SCALARS
from physmorph.records.h5io import (StageInputError, code_state, content_checksum, fsync_path, peak_rss_mb, stamp_checksum, verify_checksum,
                            write_provenance)
from physmorph.records.runkey import RunKey
from physmorph.records.runfile_cli import CHECKPOINT_NAME, LOCK_NAME, METRICS_CHECKSUM_ATTR, not_a_run  # the names a run leaves on disk

# Per-frame scalar metrics, in the order they appear in the run file's /metrics group: the one
# declaration of their names (RunWriter.commit refuses any other; the render loss's from its terms).
# physics_loss: the loss the frame's control minimised, at its end (the mass loss with the packing
# term, plus mpm.volume_weight's volume term, for the full method plus the stray pull's term);
# mass_loss: the same without the pull's and the volume term;
# physics_loss_to_target: with morph.waypoint_cells, the end state's physics loss against the target
# itself (the frames' aims differ), and mass_loss then against the target too; plan_distance: the
# full method's mass-weighted mean distance to the transport destinations, in cells.
# each frame's seconds by stage (physmorph.morph.loop), and its whole wall time
STAGE_TIMES = ("t_physics", "t_render", "t_plasticity", "t_mask", "t_frame")
SCALARS = (
    "alpha_mse", "iou", "gap_closed", "physics_loss_initial", "physics_loss", "mass_loss", "delta_E_percent", *LOSS_SCALARS.values(),
    "injection_scale", "grad_F_norm", "grad_x_norm", "mpm_grad_norm", "fp_det_min",
    "fp_det_max", "fp_anisotropy_max", "elastic_energy", "total_volume", "rest_volume", "mask_size",
    "mask_fraction", "chamfer", "volume_iou", "overfilled_mass", "kinetic_energy", "momentum_restart", "settling", "step_size", "step_accepted", "frame_strain", "reabsorbed", "physics_loss_to_target", "plan_distance", *STAGE_TIMES,
)
SAVED_STATE = ("x", "F", "Fp")  # what a saved frame keeps (float32)
MOTION = {"x": np.float32, "F": np.float16}  # what every other frame keeps (the module docstring)
# How saved states are stored: gzip at level 1 on byte-shuffled floats. A paper-scale state
# (471K particles, 40 MB): 30 MB in 0.9 s, against 35 MB in 1.6 s at gzip's default level unshuffled.
STATE_COMPRESSION = {"compression": "gzip", "compression_opts": 1, "shuffle": True}

FRAME_FORMAT = "physmorph-run-frame/1"
CHECKPOINT_FORMAT = "physmorph-checkpoint/2"
# The most of a run's wall time its checkpoints take: a checkpoint that took c seconds to write is
# followed by the next once c / CHECKPOINT_WALL_SHARE seconds have passed, so a kill loses at most
# that much computing (None: a checkpoint every frame).
CHECKPOINT_WALL_SHARE: float | None = 0.02


class RunFileError(RuntimeError):
    """A path is no run, or a run's file is damaged, foreign or unwritable; the message names the
    file, the reason and, for a run's own file only, what to delete or rerun."""


class RunLockedError(RunFileError):
    """Another process is writing this run."""


def partial_dir(out: str | os.PathLike) -> Path:
    """The directory a run ``out`` lives in until it finishes."""
    return Path(out).with_name(Path(out).name + ".partial")


def frame_name(frame: int) -> str:
    return f"frame_{frame:04d}.h5"


# ------------------------------------------------------------------------- atomic file writes
# Each step of a commit is a module-level function, so tests can kill a commit at any of them.
def _write_aside(tmp: Path, fill: Callable[[h5py.File], dict | None]) -> None:
    """Create ``tmp`` (it must not exist), fill it, stamp its content checksum last (``fill`` may
    return the arrays it wrote by dataset name: they are hashed from memory)."""
    with h5py.File(tmp, "w-") as f:
        written = fill(f)
        stamp_checksum(f, written=written, data=False)  # no run takes a run's files as its input


def _fsync(path: Path) -> None:
    fsync_path(path)


def _replace(src: Path, dst: Path) -> None:
    os.replace(src, dst)


def _clock() -> float:  # the checkpoints' cadence (a function, so tests can set the time)
    return time.monotonic()


def _commit_h5(path: Path, fill: Callable[[h5py.File], dict | None], what: str) -> None:
    """Write ``path`` all or nothing: aside, fsync, rename, fsync the directory."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.unlink(missing_ok=True)
    try:
        _write_aside(tmp, fill)
        _fsync(tmp)
    except Exception as exc:  # a kill leaves the .tmp behind; resume removes it
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError) and exc.errno == errno.ENOSPC:
            raise RunFileError(f"{path}: disk full while writing {what}; the last committed frame is kept in "
                               f"{path.parent}: free space and rerun to resume") from exc
        raise
    _replace(tmp, path)
    _fsync(path.parent)


# ----------------------------------------------------------------------------- checkpoints
@dataclass(frozen=True)
class ArrayBySlots:
    """A checkpoint's array [S, ...] given a slot at a time, so that its whole is never in memory
    (the solver's control: 0.37 GB at 511K particles x 20 slots, which set a run's peak memory at
    each checkpoint): its shape, dtype and ``slot(s)``, the array of slot s. A checkpoint stores it
    as the dataset the whole array would make; reading the checkpoint gives that array."""

    shape: tuple[int, ...]
    dtype: np.dtype
    slot: Callable[[int], np.ndarray]


@dataclass(frozen=True)
class Checkpoint:
    """The loop state after a committed frame."""

    frame: int
    data: dict  # name -> np.ndarray (loop state arrays) or float/int/str (scalars)
    wall_time_segments_s: tuple[float, ...]  # wall time of each run segment up to this frame
    key: RunKey


def _open_run_h5(path: Path, remedy: str) -> h5py.File:
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise RunFileError(f"{path}: not a readable HDF5 file ({exc}): it is truncated, zero-filled or "
                           f"overwritten; {remedy}") from exc


def _check_format(f: h5py.File, path: Path, fmt: str, remedy: str, read: dict | None = None) -> None:
    """The format tag and the content checksum of ``f``; ``read``: dataset name -> the array just
    read from it, hashed in its place (each dataset is read once)."""
    try:
        found = f.attrs.get("format")
    except (OSError, RuntimeError, KeyError) as exc:
        raise RunFileError(f"{path}: unreadable attributes ({exc}); {remedy}") from exc
    if found is None or str(found) != fmt:
        raise RunFileError(f"{path}: not a {fmt} file (format {found!r}): a foreign or older file; {remedy}")
    try:
        verify_checksum(f, remedy=remedy, written=read)
    except StageInputError as exc:
        raise RunFileError(str(exc)) from exc


def read_checkpoint(path: str | os.PathLike) -> Checkpoint:
    """Read and verify a checkpoint; RunFileError naming the file when torn, foreign or damaged."""
    path = Path(path)
    remedy = (f"the run cannot resume from it: delete {path.parent} (rm -r '{path.parent}') and rerun to "
              "restart the run from frame 0")
    with _open_run_h5(path, remedy) as f:
        _check_format(f, path, CHECKPOINT_FORMAT, remedy)
        try:
            data = {k: f[k][()] for k in f if isinstance(f[k], h5py.Dataset)}
            data.update({k: f["scalars"].attrs[k] for k in f["scalars"].attrs})
            segments = tuple(float(s) for s in json.loads(str(f.attrs["wall_time_segments_s"])))
            return Checkpoint(int(f.attrs["frame"]), data, segments, RunKey.from_attrs(f.attrs))
        except (OSError, KeyError, ValueError, RuntimeError) as exc:
            raise RunFileError(f"{path}: malformed checkpoint ({exc}); {remedy}") from exc


# ----------------------------------------------------------------------------------- writer
class RunWriter:
    """Writes one run: lock, resume or start, commit frames, finish into ``out``.

    Use as a context manager: entering takes the run's lock (RunLockedError naming the holder's
    PID when another process has it), leaving releases it.
    """

    def __init__(self, out: str | os.PathLike, key: RunKey, started: float | None = None):
        self.out = Path(out)
        self.dir = partial_dir(self.out)
        self.key = key
        self.started = time.time() if started is None else started
        code_state()  # the code this run starts with is the code its file will name
        self.previous_segments: tuple[float, ...] = ()
        self.meta: dict = {}
        self.last_frame = -1  # the last committed frame
        self._checkpoint_due = -np.inf  # _clock() time from which the next frame writes the checkpoint
        self._lock_fd: int | None = None

    # -- lock
    def __enter__(self) -> "RunWriter":
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def acquire(self) -> None:
        if self.dir.exists() and not self.dir.is_dir():
            raise RunFileError(f"{self.dir}: a partial run in the older single-file format, which cannot be resumed "
                               f"safely; delete it (rm '{self.dir}') and rerun to restart the run")
        for attempt in range(3):  # the directory may vanish under us when another writer finishes
            self.dir.mkdir(parents=True, exist_ok=True)
            try:
                fd = os.open(self.dir / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
                break
            except FileNotFoundError:
                if attempt == 2:
                    raise
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 64).decode("ascii", "replace").strip() or "unknown"
            os.close(fd)
            raise RunLockedError(f"{self.dir}: another process (PID {holder}) is writing this run; wait for it to "
                                 f"finish or stop it (kill {holder}). The lock goes when its process ends, so it "
                                 "is never stale.") from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._lock_fd = fd

    def release(self) -> None:
        if self._lock_fd is not None:
            fcntl.flock(self._lock_fd, fcntl.LOCK_UN)
            os.close(self._lock_fd)
            self._lock_fd = None

    def _require_lock(self) -> None:
        if self._lock_fd is None:
            raise RuntimeError(f"{self.dir}: the run's lock is not held (use RunWriter as a context manager)")

    # -- resume
    def _frame_files(self) -> dict[int, Path]:
        out = {}
        for p in self.dir.glob("frame_*.h5"):
            try:
                out[int(p.stem.split("_")[1])] = p
            except ValueError:
                pass
        return out

    def clear(self) -> None:
        """Remove every frame and checkpoint of the partial run (the lock stays)."""
        self._require_lock()
        for p in self.dir.iterdir():
            if p.name != LOCK_NAME:
                shutil.rmtree(p) if p.is_dir() else p.unlink()

    def resume(self, log: Callable[[str], None]) -> Checkpoint | None:
        """The checkpoint to continue from, or None (the partial run is cleared: start at frame 0).

        Leftovers of an interrupted commit and the frame files after the checkpoint are removed. A checkpoint of another key restarts the run
        with the reason logged; a damaged checkpoint or committed frame raises RunFileError.
        """
        self._require_lock()
        for tmp in self.dir.glob("*.tmp"):
            tmp.unlink()
        ck_path = self.dir / CHECKPOINT_NAME
        frames = self._frame_files()
        if not ck_path.exists():
            if frames:
                log(f"restarting {self.dir.name}: no committed frame (the first frame was interrupted)")
            self.clear()
            return None
        ck = read_checkpoint(ck_path)
        reasons = self.key.changes_from(ck.key)
        if reasons:
            log(f"restarting {self.dir.name} from frame 0: " + "; ".join(reasons))
            self.clear()
            return None
        for k in range(ck.frame + 1):
            if k not in frames:
                raise RunFileError(f"{self.dir / frame_name(k)}: missing, but the checkpoint says frame {ck.frame} was "
                                   f"committed; delete {self.dir} (rm -r '{self.dir}') and rerun to restart the run")
            self._read_frame(frames[k], k)  # verifies
        for k, p in frames.items():
            if k > ck.frame:  # a frame after the checkpoint (or an interrupted commit's): computed again
                p.unlink()
        self.previous_segments = ck.wall_time_segments_s
        self.last_frame = ck.frame
        with h5py.File(frames[0], "r") as f:
            self.meta = dict(f["meta"].attrs)
        return ck

    def _read_frame(self, path: Path, frame: int) -> dict:
        """A committed frame file's content, verified (_read_frame_file), of this run and frame."""
        remedy = f"delete {self.dir} (rm -r '{self.dir}') and rerun to restart the run"
        content = _read_frame_file(path, remedy)
        if content["frame"] != frame or content["run_key"] != self.key.digest:
            raise RunFileError(f"{path}: belongs to another run or frame (frame {content['frame']}); {remedy}")
        return content

    def frame_metrics(self, frame: int) -> tuple[dict, np.ndarray]:  # {name: value}, [V]
        """A committed frame's scalars and its alpha MSE per view."""
        with h5py.File(self.dir / frame_name(frame), "r") as f:
            g = f["metrics"]
            return {k: float(g[k][()]) for k in SCALARS if k in g}, np.asarray(g["alpha_mse_views"][()])

    def frame_metric(self, frame: int, name: str) -> float:
        with h5py.File(self.dir / frame_name(frame), "r") as f:
            return float(f["metrics"][name][()])

    # -- write
    def segments_now(self) -> tuple[float, ...]:
        return self.previous_segments + (time.time() - self.started,)

    def commit(self, frame: int, scalars: dict, views: np.ndarray,  # views [V] alpha MSE per view
               state: dict | None, warnings: list[str], checkpoint: dict | Callable[[], dict],
               last: bool = False, motion: dict | None = None) -> None:
        """Commit frame ``frame``: its frame file, then, when due (see the module docstring) or
        ``last``, the checkpoint.

        state: None or {x [N,3], F [N,3,3], Fp [N,3,3]} to save (else, where ``state`` holds x and F
        anyway, the frame's motion: MOTION); checkpoint: name -> array or scalar, or a function
        returning it (called only when the checkpoint is written).
        """
        self._require_lock()
        unknown = sorted(set(scalars) - set(SCALARS))
        if unknown:  # a misspelt name would be written nowhere: SCALARS declares every one
            raise ValueError(f"frame {frame}: scalars not declared in physmorph.records.runfile.SCALARS: {unknown}")
        segments = self.segments_now()

        def fill_frame(f: h5py.File) -> dict:
            f.attrs.update(format=FRAME_FORMAT, frame=frame, run_key=self.key.digest,
                           warnings=json.dumps(list(warnings)), peak_rss_mb=peak_rss_mb())
            if frame == 0:
                f.create_group("meta").attrs.update(self.meta)
            g = f.create_group("metrics")
            for name in SCALARS:
                g[name] = float(scalars.get(name, np.nan))
            g["alpha_mse_views"] = np.asarray(views, dtype=np.float64).ravel()
            written = {}
            if state is not None:
                s = f.create_group("state")
                for k in SAVED_STATE:
                    written[f"state/{k}"] = np.asarray(state[k]).astype(np.float32)
                    s.create_dataset(k, data=written[f"state/{k}"], **STATE_COMPRESSION)
            elif motion is not None:
                s = f.create_group("motion")
                for k, dtype in MOTION.items():
                    written[f"motion/{k}"] = np.asarray(motion[k]).astype(dtype)
                    s.create_dataset(k, data=written[f"motion/{k}"], **STATE_COMPRESSION)
            return written

        def fill_checkpoint(f: h5py.File) -> dict:
            f.attrs.update(format=CHECKPOINT_FORMAT, frame=frame, wall_time_segments_s=json.dumps(list(segments)),
                           **self.key.attrs())
            sc = f.create_group("scalars")
            written = {}
            for k, v in checkpoint.items():
                if isinstance(v, np.ndarray):
                    written[k] = v
                    f.create_dataset(k, data=v)
                elif isinstance(v, ArrayBySlots):  # hashed by reading it back, a block at a time
                    ds = f.create_dataset(k, shape=v.shape, dtype=v.dtype)
                    for s in range(v.shape[0]):
                        ds[s] = v.slot(s)
                else:
                    sc.attrs[k] = v
            return written

        _commit_h5(self.dir / frame_name(frame), fill_frame, f"frame {frame}")
        self.last_frame = frame
        if not (last or CHECKPOINT_WALL_SHARE is None or _clock() >= self._checkpoint_due):
            return
        if callable(checkpoint):
            checkpoint = checkpoint()
        began = _clock()
        _commit_h5(self.dir / CHECKPOINT_NAME, fill_checkpoint, f"the checkpoint of frame {frame}")
        if CHECKPOINT_WALL_SHARE is not None:
            ended = _clock()
            self._checkpoint_due = ended + (ended - began) / CHECKPOINT_WALL_SHARE

    def set_meta(self, meta: dict) -> None:
        """The run's description (stored with frame 0, copied to the finished file's attributes)."""
        self.meta = dict(meta)

    def finish(self, status: str, attrs: dict, config: dict | None) -> Path:
        """Assemble ``out`` from the committed frames (aside, fsync, rename) and remove the partial run."""
        self._require_lock()
        last = self.last_frame
        if last < 0:
            raise RuntimeError(f"{self.dir}: no committed frame to finish the run with")
        segments = self.segments_now()

        def fill(f: h5py.File) -> dict:
            f.attrs.update(self.meta)
            f.attrs.update(self.key.attrs())
            f.create_group("states")
            # each frame file is verified, then its arrays are copied as stored (their compressed
            # chunks: no encoding again, which took 0.3-0.7 s a frame at the paper's scale), one
            # frame at a time (all of them together are ~0.7 GB there); metrics and warnings are kept
            frames = []
            for k in range(last + 1):
                path = self.dir / frame_name(k)
                frame = self._read_frame(path, k)
                del frame["arrays"]
                with h5py.File(path, "r") as src:
                    for group, stored in FRAME_GROUPS.items():
                        if stored in src:
                            f.copy(src[stored], f.require_group(group), name=f"frame_{k:04d}")
                frames.append(frame)
            g = f.create_group("metrics")
            for name in SCALARS + ("alpha_mse_views",):
                g.create_dataset(name, data=np.stack([_frame_metric(fr, name) for fr in frames]))
            written = {}
            write_provenance(f, config, self.started)
            f.attrs.update(attrs)
            f.attrs.update(status=status, frames_completed=last,
                           warnings=json.dumps([w for fr in frames for w in fr["warnings"]]),
                           wall_time_s=float(sum(segments)), wall_time_segments_s=json.dumps(list(segments)),
                           peak_rss_mb=max([peak_rss_mb()] + [fr["peak_rss_mb"] for fr in frames]))
            f.attrs[METRICS_CHECKSUM_ATTR] = content_checksum(f, only="metrics")
            return written

        _commit_h5(self.out, fill, "the finished run")
        shutil.rmtree(self.dir)  # the lock file goes with it; the lock itself until release()
        return self.out


# the finished file's array groups -> the frame file's groups that hold them
FRAME_GROUPS = {"states": "state", "motion": "motion"}


def _read_frame_file(path: Path, remedy: str) -> dict:
    """A frame file's content (_frame_content), verified against its checksum: each dataset is read
    once and its arrays hashed from memory. A file too damaged to read is named by its format tag's
    or checksum's failure, with ``remedy``."""
    with _open_run_h5(path, remedy) as f:
        try:
            content = _frame_content(f)
        except (OSError, KeyError, ValueError, RuntimeError, TypeError):
            content = None  # damaged or foreign: _check_format says which
        read = None if content is None else {f"{FRAME_GROUPS[out]}/{name}": a
                                             for out, arrays in content["arrays"].items() for name, a in arrays.items()}
        _check_format(f, path, FRAME_FORMAT, remedy, read=read)
        if content is None:
            raise RunFileError(f"{path}: malformed frame file (its checksum holds, its groups do not); {remedy}")
        return content


def _frame_content(f: h5py.File) -> dict:
    """A frame file's metrics, warnings and meta, and its saved state or motion
    ({"states": {...}} or {"motion": {...}}, stored as they were written)."""
    return {"metrics": {k: f["metrics"][k][()] for k in f["metrics"]},
            "arrays": {out: {k: f[g][k][()] for k in f[g]} for out, g in FRAME_GROUPS.items() if g in f},
            "warnings": json.loads(str(f.attrs["warnings"])), "peak_rss_mb": float(f.attrs["peak_rss_mb"]),
            "frame": int(f.attrs["frame"]), "run_key": str(f.attrs["run_key"]),
            "meta": dict(f["meta"].attrs) if "meta" in f else None}


# ------------------------------------------------------------------------------------ read
def _partial_metrics(d: Path) -> dict[str, np.ndarray]:
    """Metrics of the committed frames of a partial run directory (read-only, no lock): frame 0 on
    to the last frame file (``frames_completed``); ``resumes_after``: the checkpoint's frame."""
    remedy = f"delete {d} (rm -r '{d}') and rerun to restart the run"
    ck_path = d / CHECKPOINT_NAME
    if not ck_path.exists():
        return {"attrs": {}, **{name: np.zeros(0) for name in SCALARS}}
    with _open_run_h5(ck_path, remedy) as f:
        resumes_after = int(f.attrs["frame"])
    frames = []
    while True:
        k = len(frames)
        path = d / frame_name(k)
        if not path.exists():
            if k <= resumes_after:
                raise RunFileError(f"{path}: missing, but the checkpoint says frame {resumes_after} was committed; "
                                   f"{remedy}")
            break
        frames.append(_read_frame_file(path, remedy))
    out = {name: np.stack([_frame_metric(fr, name) for fr in frames]) for name in SCALARS + ("alpha_mse_views",)}
    out["attrs"] = {**(frames[0]["meta"] or {}), "status": "running", "frames_completed": len(frames) - 1,
                    "resumes_after": resumes_after, "warnings": json.dumps([w for fr in frames for w in fr["warnings"]])}
    return out


def _frame_metric(frame: dict, name: str):
    """One metric of a committed frame; NaN for a scalar the frame's writer did not know yet (a run
    begun before that metric existed and resumed after)."""
    if name in frame["metrics"] or name not in SCALARS:
        return frame["metrics"][name]
    return np.float64(np.nan)


def read_metrics(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Per-frame metrics of a run (index 0 = initial state), plus its attributes under 'attrs'.

    ``path`` is a finished run file (its metrics checksum verified when it has one) or a partial
    run directory ``<out>.partial`` (its committed frames).
    """
    path = Path(path)
    foreign = not_a_run(path)  # a mesh, another HDF5 file, a directory, a missing path: no remedy
    if foreign:
        raise RunFileError(foreign)
    if path.is_dir():
        return _partial_metrics(path)
    remedy = "it is a physmorph run file (it carries a run file's metrics or attribute names): delete it and rerun the morph that writes it"
    with _open_run_h5(path, remedy) as f:
        try:
            stored = f.attrs.get(METRICS_CHECKSUM_ATTR)
            if stored is not None and content_checksum(f, only="metrics") != str(stored):
                raise RunFileError(f"{path}: its metrics do not match their checksum: the file changed after it "
                                   f"was written (zero-filled, torn or edited); {remedy}")
            if "metrics" not in f:
                raise RunFileError(f"{path}: a run file's attributes but no group 'metrics' (torn or edited); {remedy}")
            out = {k: f["metrics"][k][()] for k in f["metrics"]}
            out["attrs"] = dict(f.attrs)
        except (OSError, KeyError, ValueError) as exc:
            raise RunFileError(f"{path}: unreadable run file ({exc}); {remedy}") from exc
    return out


def summarize_run(path: str | os.PathLike) -> dict:
    m = read_metrics(path)
    a = m["alpha_mse"]
    return {"frames": int(len(a) - 1), "alpha_mse_initial": float(a[0]), "alpha_mse_final": float(a[-1]),
            "alpha_mse_best": float(np.nanmin(a)), "best_frame": int(np.nanargmin(a)),
            "status": str(m["attrs"].get("status", "")), "peak_rss_mb": float(m["attrs"].get("peak_rss_mb", 0.0)),
            "wall_time_s": float(m["attrs"].get("wall_time_s", np.nan))}


def describe_run(path: str | os.PathLike) -> str:
    """One paragraph about a run file or a partial run: status, frames, alpha MSE, wall time."""
    path = Path(path)
    if path.is_dir():
        m = read_metrics(path)
        n = len(m["alpha_mse"])
        if n == 0:
            return f"{path}: a partial run with no committed frame"
        lock = path / LOCK_NAME
        holder = lock.read_text().strip() if lock.exists() else ""
        return (f"{path}: a partial run, frames 0..{n - 1} committed, alpha MSE {m['alpha_mse'][0]:.4g} -> "
                f"{m['alpha_mse'][-1]:.4g}" + (f"; last writer PID {holder}" if holder else ""))
    s = summarize_run(path)
    return (f"{path}: {s['status']}, {s['frames']} frames, alpha MSE {s['alpha_mse_initial']:.4g} -> "
            f"{s['alpha_mse_final']:.4g} (best {s['alpha_mse_best']:.4g} at frame {s['best_frame']}), "
            f"wall time {s['wall_time_s']:.1f} s, peak RSS {s['peak_rss_mb']:.0f} MB")


def frame_motion(f: h5py.File, frame: int) -> tuple[np.ndarray, np.ndarray]:  # x [N, 3], F [N, 3, 3]
    """Positions and deformation gradients of any frame of a finished run (float64): the saved
    state where the frame has one, else its motion (F at half precision: MOTION)."""
    name = f"frame_{frame:04d}"
    for group in ("states", "motion"):
        if group in f and name in f[group]:
            g = f[group][name]
            return g["x"][()].astype(np.float64), g["F"][()].astype(np.float64)
    raise RunFileError(f"{f.filename}: frame {frame} has no positions (a run made before every frame's "
                       f"motion was kept has them every save_every frames only: rerun it)")


if __name__ == "__main__":  # python -m physmorph.records.runfile RUN [RUN ...] (--help: the command line)
    from physmorph.records.runfile_cli import main
    sys.exit(main(describe_run))
