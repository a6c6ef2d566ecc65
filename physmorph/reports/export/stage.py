"""The export stage's entry points (workflow/rules/export.smk): one function per rule.

* ``video_stage``: a run's MP4 (and WebM) of every frame, and its saved frames' stills;
* ``meshes_stage``: a closed surface of the body at every saved frame (PLY) and at the last (GLB),
  with the transform to the target's input frame recorded (and applied with ``export.frame:
  target``) and what each surface shows measured (measures.csv);
* ``splats_stage``: the Gaussians of every saved frame as 3DGS PLY files;
* ``viewer_stage``: results/{profile}/viewer/index.html over the exported runs, and a page per run;
* ``viewer_data_stage``, ``viewer_bundle_stage``: a run's 3D view data, and the 3D view's script.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

from physmorph.reports.export.runs import frame_state, saved_frames
from physmorph.settings.export import ExportConfig
from physmorph.records.h5io import StageInputError
from physmorph.meshes.errors import exit_on_refusal
from physmorph.records.runfile import RunFileError
from physmorph.stages import stage_log, typed

# a run or input file the export cannot use (made before every frame's motion was kept, damaged,
# not the run's own particles) ends the job in one line naming the file, not a traceback
USER_ERRORS = (RunFileError, StageInputError)


def video_stage(*args, log: str | None = None, **kwargs) -> None:
    """A run's videos and stills (see _video_stage); a file it cannot use ends the job in one line."""
    exit_on_refusal(lambda: _video_stage(*args, log=log, **kwargs), log=log, refusals=USER_ERRORS)


def meshes_stage(*args, log: str | None = None, **kwargs) -> None:
    """A run's surfaces and their measures (see _meshes_stage); one line for a file it cannot use."""
    exit_on_refusal(lambda: _meshes_stage(*args, log=log, **kwargs), log=log, refusals=USER_ERRORS)


def splats_stage(*args, log: str | None = None, **kwargs) -> None:
    """A run's splat files (see _splats_stage); one line for a file it cannot use."""
    exit_on_refusal(lambda: _splats_stage(*args, log=log, **kwargs), log=log, refusals=USER_ERRORS)


def _transforms(source_mesh_h5: Path, target_mesh_h5: Path) -> dict:
    from physmorph.reports.export.surface import domain_to_input

    return {"to_target_input": domain_to_input(target_mesh_h5).tolist(),
            "to_source_input": domain_to_input(source_mesh_h5).tolist()}


def _video_stage(run_h5: str, target_mesh_h5: str, target_cfg: str | dict, export: str | dict, mp4: str,
                 webm: str | None, stills_dir: str, log: str | None = None, particles_h5: str | None = None) -> None:
    from dataclasses import asdict

    from physmorph.settings.sections import TargetConfig
    from physmorph.reports.export.video import video_record, write_videos

    cfg = typed(ExportConfig, export, "export")
    target = asdict(typed(TargetConfig, target_cfg, "target"))
    with stage_log(log):
        count = write_videos(Path(run_h5), Path(target_mesh_h5), target, Path(mp4), Path(webm) if webm else None,
                             Path(stills_dir), cfg, particles_h5=Path(particles_h5) if particles_h5 else None)
        rec = video_record(Path(mp4))
        print(f"{mp4}: {count} frames encoded, {rec['frames']} read back, {rec['seconds']:.1f} s, "
              f"{rec['bytes'] / 1e6:.1f} MB")


def _meshes_stage(run_h5: str, particles_h5: str, source_mesh_h5: str, target_mesh_h5: str,
                 export: str | dict, out_dir: str, log: str | None = None) -> None:
    """Every saved frame's surface as frame_{k:04d}.ply and the last as final.glb, in the
    simulation domain (export.frame: domain) or the target mesh's input frame (target);
    transform.json holds both transforms, measures.csv what each surface shows."""
    from physmorph.reports.export.measures import frame_measures, write_measures
    from physmorph.reports.export.surface import particle_surface, write_glb, write_ply

    cfg = typed(ExportConfig, export, "export")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    transforms = _transforms(Path(source_mesh_h5), Path(target_mesh_h5))
    apply = np.asarray(transforms["to_target_input"]) if cfg.frame == "target" else None
    (out / "transform.json").write_text(json.dumps({"frame": cfg.frame, **transforms}, indent=1) + "\n")
    with stage_log(log):
        frames, rows = saved_frames(run_h5), []
        for k in frames:
            s = frame_state(run_h5, k, particles_h5=particles_h5)
            mesh = particle_surface(s["x"], s["volume"], s["det_F"], s["dx"], **cfg.surface())
            rows.append(frame_measures(k, s, mesh, target_mesh_h5))
            if apply is not None:
                mesh.apply_transform(apply)
            write_ply(mesh, out / f"frame_{k:04d}.ply")
            if k == frames[-1]:
                write_glb(mesh, out / "final.glb")
            print(f"frame {k}: {len(mesh.faces)} faces, closed {mesh.is_watertight}, stray "
                  f"{100 * rows[-1]['stray_share']:.2f} %, surface distance {rows[-1]['surface_distance_dx']:.2f} dx")
        write_measures(rows, out / "measures.csv")


def _splats_stage(run_h5: str, export: str | dict, target_mesh_h5: str, out_dir: str, log: str | None = None) -> None:
    """Every saved frame's Gaussians as splats/{experiment}/frame_{k:04d}.ply."""
    from physmorph.reports.export.splats import write_splats
    from physmorph.reports.export.surface import domain_to_input

    cfg = typed(ExportConfig, export, "export")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    apply = domain_to_input(target_mesh_h5) if cfg.frame == "target" else None
    with stage_log(log):
        for k in saved_frames(run_h5):
            s = frame_state(run_h5, k)
            write_splats(out / f"frame_{k:04d}.ply", s["x"], s["F"], s["sigma0"], transform=apply)
            print(f"frame {k}: {len(s['x'])} Gaussians")


def _numbers(run_h5: Path, measures_csv: Path | None) -> dict[str, str]:
    from physmorph.morph.quality import gap_closed

    with h5py.File(run_h5, "r") as f:
        a = f["metrics/alpha_mse"][()]
        ceiling = float(f.attrs.get("ceiling_alpha_mse", np.nan))
        iou = f["metrics/volume_iou"][()] if "volume_iou" in f["metrics"] else np.full(len(a), np.nan)
    closed = [gap_closed(float(a[0]), float(v), ceiling) for v in a]
    best = int(np.nanargmax(closed)) if np.isfinite(closed).any() else 0
    out = {"gap closed, best": f"{100 * closed[best]:.1f} % (frame {best})",
           "gap closed, last": f"{100 * closed[-1]:.1f} % (frame {len(a) - 1})",
           "volume IoU, last": f"{iou[-1]:.3f}"}
    if measures_csv is not None and Path(measures_csv).exists():
        import pandas as pd

        last = pd.read_csv(measures_csv).iloc[-1]
        out["stray share, last"] = f"{100 * last['stray_share']:.2f} %"
        out["surface distance, last"] = f"{last['surface_distance_dx']:.2f} dx"
    return out


def viewer_stage(names: list[str], runs: list[str], mp4s: list[str], webms: list[str] | None, stills: list[str],
                 measures: list[str] | None, out_html: str, profile: str, title: str | None = None,
                 data: list[str] | None = None, bundle: str | None = None, log: str | None = None) -> None:
    """The viewer page over the runs ``names`` (``title``: default the profile's page's; ``data``:
    each run's 3D data script, ``bundle`` the 3D view's script beside the page)."""
    from physmorph.reports.export.viewer import ViewerRun, write_viewer

    with stage_log(log):
        entries = []
        for i, name in enumerate(names):
            frames = sorted(Path(stills[i]).glob("frame_*.jpg"))
            entries.append(ViewerRun(name, Path(mp4s[i]), Path(webms[i]) if webms else None,
                                     [(int(p.stem.removeprefix("frame_")), p) for p in frames],
                                     _numbers(Path(runs[i]), Path(measures[i]) if measures else None),
                                     Path(data[i]) if data else None))
        write_viewer(entries, Path(out_html), title or f"physmorph: the {profile} profile's morphs",
                     Path(bundle) if bundle else None)
        print(f"{out_html}: {len(entries)} runs")


def viewer_data_stage(experiment: str, run_h5: str, meshes_dir: str, target_mesh_h5: str, out_js: str,
                      log: str | None = None) -> None:
    """A run's 3D view data, data/{experiment}.js (physmorph.reports.export.viewer_data)."""
    from physmorph.reports.export.viewer_data import write_viewer_data

    def run() -> None:
        with stage_log(log):
            path = write_viewer_data(experiment, Path(run_h5), Path(meshes_dir), Path(target_mesh_h5), Path(out_js))
            print(f"{path}: {path.stat().st_size / 1e6:.1f} MB")

    exit_on_refusal(run, log=log, refusals=USER_ERRORS)


def viewer_bundle_stage(out_js: str, log: str | None = None) -> None:
    """The 3D view's script beside the pages: the vendored bundle, copied (viewer_data.BUNDLE)."""
    import shutil

    from physmorph.reports.export.viewer import BUNDLE

    with stage_log(log):
        Path(out_js).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(BUNDLE, out_js)
        print(f"{out_js}: {BUNDLE.stat().st_size / 1e6:.1f} MB, from {BUNDLE.name}")
