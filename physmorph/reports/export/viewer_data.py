"""results/{profile}/viewer/data/{experiment}.js: what the viewer page's 3D view shows of one run,
as a script the page loads (a page opened as a file may load scripts, not fetch files): the body's
closed surface at every saved frame and the target's surface as GLB, and the last frame's Gaussians
as a 3D Gaussian splatting PLY, each base64 in ``PHYSMORPH_RUNS[experiment]``. The 3D view itself
is the vendored bundle assets/viewer3d.js (three.js and Spark; its sources and licenses beside it).

Everything is in the simulation's domain frame (y up), whatever ``export.frame`` put the exported
files in: the body beside the target as the morph saw them.
"""

from __future__ import annotations

import base64
import json
import tempfile
from pathlib import Path

import numpy as np
import trimesh

# at most this many Gaussians in the page's splat view: an even subsample, each widened to keep the
# body closed (as the video draws it), so a page of the paper's 0.5M particles stays a few MB a run
VIEWER_SPLATS = 50_000


def _glb_b64(mesh: trimesh.Trimesh) -> str:
    return base64.b64encode(mesh.export(file_type="glb")).decode("ascii")


def _to_domain(meshes_dir: Path) -> np.ndarray | None:
    """The 4x4 matrix taking the exported surfaces back to the domain frame (None: they are in it)."""
    transform = json.loads((meshes_dir / "transform.json").read_text()) if (meshes_dir / "transform.json").exists() else {}
    if transform.get("frame") != "target":
        return None
    return np.linalg.inv(np.asarray(transform["to_target_input"], np.float64))


def body_frames(meshes_dir: Path) -> list[dict]:
    """[{frame, glb}] of every saved frame's exported surface, in the domain frame."""
    back = _to_domain(meshes_dir)
    out = []
    for ply in sorted(meshes_dir.glob("frame_*.ply")):
        mesh = trimesh.load(ply, force="mesh", process=False)
        if back is not None:
            mesh.apply_transform(back)
        out.append({"frame": int(ply.stem.removeprefix("frame_")), "glb": _glb_b64(mesh)})
    return out


def last_frame_splats(run_h5: Path) -> str:
    """The last saved frame's Gaussians (at most VIEWER_SPLATS) as a base64 3DGS PLY, in the domain frame."""
    from physmorph.reports.export.runs import frame_state, saved_frames
    from physmorph.reports.export.splats import write_splats
    from physmorph.reports.export.video_body import subsample

    s = frame_state(run_h5, saved_frames(run_h5)[-1])
    x, F, sigma = subsample(np.asarray(s["x"]), np.asarray(s["F"]), float(s["sigma0"]), VIEWER_SPLATS)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "last.ply"
        write_splats(path, x, F, sigma)
        return base64.b64encode(path.read_bytes()).decode("ascii")


def write_viewer_data(experiment: str, run_h5: Path, meshes_dir: Path, target_mesh_h5: Path, out_js: Path) -> Path:
    """Write ``out_js``: ``PHYSMORPH_RUNS[experiment] = {frames, target, splats, label}``."""
    from physmorph.meshes.prepare import load_mesh

    data = {"frames": body_frames(Path(meshes_dir)), "target": _glb_b64(load_mesh(target_mesh_h5)),
            "splats": last_frame_splats(Path(run_h5)), "label": experiment}
    return write_data_script(experiment, data, out_js)


def write_data_script(experiment: str, data: dict, out_js: Path) -> Path:
    """``data`` (the bundle's mount argument: frames, target, splats, label) as the script ``out_js``."""
    out_js = Path(out_js)
    out_js.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_js.with_suffix(".partial")
    tmp.write_text("window.PHYSMORPH_RUNS = window.PHYSMORPH_RUNS || {};\n"
                   f"window.PHYSMORPH_RUNS[{json.dumps(experiment)}] = {json.dumps(data)};\n")
    tmp.replace(out_js)
    return out_js
