"""What an export needs from a finished run file (physmorph.records.runfile) and its particle file.

A run file keeps the state of the frames it saved (every ``morph.save_every`` frames, the first
and the last) as ``/states/frame_XXXX/{x, F, Fp}`` (float32), and the Gaussians' rest size
``sigma0`` among its attributes. The particles' rest volumes V_p are not in the run file: they
are the particle file's ``/volume`` (physmorph.meshes.particles, constant over a run), which the run
names by its data identity (attribute ``input_checksums``, role "particles": physmorph.records.h5io's data
digest, or the content checksum of a file written before the digest existed); the grid spacing dx
is the particle file's too.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import h5py
import numpy as np

from physmorph.records.runfile import RunFileError

_FRAME_PREFIX = "frame_"


def _open_run(run_h5: str | os.PathLike) -> h5py.File:
    path = Path(run_h5)
    if path.is_dir():
        raise RunFileError(f"{path}: a partial run directory; export reads finished run files (wait for the run to "
                           "finish)")
    try:
        f = h5py.File(path, "r")
    except (OSError, FileNotFoundError) as exc:
        raise RunFileError(f"{path}: not a readable run file ({exc})") from exc
    if "states" not in f:
        f.close()
        raise RunFileError(f"{path}: no group 'states' (not a finished run file)")
    return f


def saved_frames(run_h5: str | os.PathLike) -> list[int]:
    """The frames whose state the run saved, ascending (frame 0 is the unmoved source)."""
    with _open_run(run_h5) as f:
        return sorted(int(name[len(_FRAME_PREFIX):]) for name in f["states"] if name.startswith(_FRAME_PREFIX))


def _rest_particles(particles_h5: str | os.PathLike, run_checksum: str | None, n: int, run_h5) -> dict:
    """volume [N], is_surface [N], dx of the particle file, checked to be the one the run was made from."""
    from physmorph.records.h5io import CHECKSUM_ATTR, data_identity, open_h5, read_attr, read_field

    with open_h5(particles_h5) as f:  # verifies its checksums
        known = {data_identity(f), str(f.attrs[CHECKSUM_ATTR])}  # a run made before the data digest names the latter
        if run_checksum is not None and run_checksum not in known:
            raise RunFileError(f"{particles_h5}: not the particle file {run_h5} was made from (data identity "
                               f"{data_identity(f)[:12]}..., the run's {run_checksum[:12]}...)")
        volume = read_field(f, "volume").astype(np.float64)
        is_surface = read_field(f, "is_surface").astype(bool)
        dx = float(read_attr(f, "dx"))
    if volume.shape != (n,):
        raise RunFileError(f"{particles_h5}: {len(volume)} particles, but {run_h5} has {n}")
    return {"volume": volume, "is_surface": is_surface, "dx": dx}


def rest_particles(run_h5: str | os.PathLike, particles_h5: str | os.PathLike) -> dict:
    """The particle file's volume [N], is_surface [N] and dx, checked to be the one ``run_h5`` was made from."""
    with _open_run(run_h5) as f:
        checksums = json.loads(str(f.attrs["input_checksums"])) if "input_checksums" in f.attrs else {}
        n = len(f["states"][sorted(f["states"])[0]]["x"])
    return _rest_particles(particles_h5, checksums.get("particles"), n, run_h5)


def frame_state(run_h5: str | os.PathLike, frame: int, particles_h5: str | os.PathLike | None = None) -> dict:
    """The saved state of ``frame`` of a finished run.

    Returns ``frame``; x [N, 3], F [N, 3, 3], Fp [N, 3, 3] (float64 from the stored float32);
    det_F [N]; ``sigma0`` (the run's, the Gaussians' rest std-dev: Sigma_p = sigma0^2 F_p F_p^T).
    With ``particles_h5`` (the particle file the run was made from: its content checksum must be
    the one the run records) also the rest volumes ``volume`` [N] (current volume V_p det F_p),
    ``is_surface`` [N] and the grid spacing ``dx``. RunFileError naming the file and the saved
    frames when ``frame`` was not saved.
    """
    with _open_run(run_h5) as f:
        name = f"{_FRAME_PREFIX}{int(frame):04d}"
        if name not in f["states"]:
            saved = sorted(int(k[len(_FRAME_PREFIX):]) for k in f["states"] if k.startswith(_FRAME_PREFIX))
            raise RunFileError(f"{run_h5}: frame {frame} was not saved (saved frames: {saved})")
        g = f["states"][name]
        out = {"frame": int(frame), **{k: np.asarray(g[k][()], dtype=np.float64) for k in ("x", "F", "Fp")}}
        out["sigma0"] = float(f.attrs["sigma0"]) if "sigma0" in f.attrs else float("nan")
        checksums = json.loads(str(f.attrs["input_checksums"])) if "input_checksums" in f.attrs else {}
    n = len(out["x"])
    if out["x"].shape != (n, 3) or out["F"].shape != (n, 3, 3) or out["Fp"].shape != (n, 3, 3):
        raise RunFileError(f"{run_h5}: frame {frame}: malformed state (x {out['x'].shape}, F {out['F'].shape})")
    out["det_F"] = np.linalg.det(out["F"])
    if particles_h5 is not None:
        out.update(_rest_particles(particles_h5, checksums.get("particles"), n, run_h5))
    return out
