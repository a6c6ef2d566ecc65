"""A run as a video: every frame of the morph, the body shaded as in the figures from a slowly
orbiting camera, beside the target from the same view, with the frame number, the share of the
reachable gap closed and the volume IoU.

The body is its closed surface at every frame or the run's own Gaussians (``export.body``:
physmorph.reports.export.video_body; x and F of every frame: physmorph.records.runfile.frame_motion),
shaded by ``physmorph.render.api.shade``; the target is its prepared mesh's surface, evenly sampled,
as small round Gaussians shaded the same way, so both sides are lit and seen alike. Frames are encoded with imageio-ffmpeg: H.264 in yuv420p (what browsers and players open)
and VP9 in WebM beside it.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from physmorph.base.cameras import Cameras, look_at
from physmorph.morph.quality import gap_closed
from physmorph.reports.export.runs import saved_frames
from physmorph.settings.export import ExportConfig
from physmorph.records.runfile import frame_motion
from physmorph.reports.export.video_body import SURFACE_GAUSSIANS, BodyDrawing, body_label, surface_gaussians


def orbit_camera(azimuth_deg: float, elevation_deg: float, fov_y_deg: float, distance: float, width: int,
                 height: int) -> Cameras:
    """One pinhole camera at ``azimuth_deg`` around +y (0: on +z, as ring_cameras' first view),
    ``elevation_deg`` above the xz plane, looking at the origin."""
    az, el = np.deg2rad(azimuth_deg), np.deg2rad(elevation_deg)
    eye = distance * np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
    fy = 0.5 * height / np.tan(0.5 * np.deg2rad(fov_y_deg))
    return Cameras(look_at(eye, np.zeros(3), np.array([0.0, 1.0, 0.0]))[None], np.array([[fy, fy, 0.5 * width,
                                                                                            0.5 * height]]),
                   width, height)


def target_gaussians(mesh_h5: Path, count: int = SURFACE_GAUSSIANS, seed: int = 0) -> tuple[np.ndarray, np.ndarray, float]:
    """The prepared target mesh as ``count`` round Gaussians evenly on its surface (surface_gaussians)."""
    import trimesh

    from physmorph.records.h5io import StageInputError

    if not Path(mesh_h5).exists():
        raise StageInputError(f"{mesh_h5}: missing (the target's prepared mesh)")
    with h5py.File(mesh_h5, "r") as f:
        mesh = trimesh.Trimesh(f["vertices"][()], f["faces"][()], process=False)
    return surface_gaussians(mesh, count, seed)


def _label(img: np.ndarray, text: str) -> np.ndarray:
    """``img`` [H, W, 3] uint8 with ``text`` in its top-left corner."""
    from PIL import Image, ImageDraw

    pil = Image.fromarray(img)
    ImageDraw.Draw(pil).text((6, 4), text, fill=(30, 30, 30))
    return np.array(pil)


def video_frames(run_h5: Path, target_mesh_h5: Path, target_cfg: dict, settings: ExportConfig, log=print,
                 particles_h5: Path | None = None):
    """Yield (k, the video's frame [H, 2W, 3] uint8) for every run frame k = 0..K (``particles_h5``:
    the run's particle file, which the body's surface needs: video_body.BodyDrawing)."""
    from physmorph.settings.render import RenderConfig
    from physmorph.render.api import shade
    from physmorph.reports.export.runs import rest_particles

    tx, tF, ts = target_gaussians(target_mesh_h5)
    rest = rest_particles(run_h5, particles_h5) if settings.body == "surface" and particles_h5 is not None else None
    with h5py.File(run_h5, "r") as f:
        frames = int(f.attrs["frames_completed"])
        drawing = BodyDrawing(settings, float(f.attrs["sigma0"]), rest)
        alpha = f["metrics/alpha_mse"][()]
        iou = f["metrics/volume_iou"][()] if "volume_iou" in f["metrics"] else np.full(len(alpha), np.nan)
        ceiling = float(f.attrs.get("ceiling_alpha_mse", np.nan))
        name = str(f.attrs.get("experiment", Path(run_h5).stem))
        last = None  # the frame before: its positions, F and the body's Gaussians
        for k in range(frames + 1):
            cam = orbit_camera(settings.orbit_deg * k / max(frames, 1), target_cfg["elevation_deg"],
                               target_cfg["fov_y_deg"], target_cfg["distance"], settings.width, settings.height)
            x, F = frame_motion(f, k)
            if last is not None and np.array_equal(x, last[0]) and np.array_equal(F, last[1]):
                body_gaussians = last[2]  # a held or undone frame: the body still, its surface the same
            else:
                body_gaussians = drawing.gaussians(x, F)
            last = (x, F, body_gaussians)
            bx, bF, bs = body_gaussians
            body = shade(bx, bF, bs, cam, 0, RenderConfig())
            target = shade(tx, tF, ts, cam, 0, RenderConfig(), color=(0.55, 0.62, 0.72))
            img = (255 * np.clip(np.concatenate([body, target], axis=1), 0, 1)).astype(np.uint8)
            closed = gap_closed(float(alpha[0]), float(alpha[k]), ceiling) if np.isfinite(ceiling) else np.nan
            img = _label(img, body_label(name, k, frames, closed, float(iou[k]) if k < len(iou) else np.nan))
            img[:, settings.width - 1: settings.width + 1] = 200  # the seam between body and target
            if k % 10 == 0:
                log(f"[video {name}] frame {k}/{frames}")
            yield k, img


def write_videos(run_h5: Path, target_mesh_h5: Path, target_cfg: dict, mp4: Path, webm: Path | None,
                 stills_dir: Path | None = None, settings: ExportConfig = ExportConfig(), log=print,
                 particles_h5: Path | None = None) -> int:
    """Encode the run's video as H.264 MP4 (yuv420p) and, with ``webm``, VP9 WebM; with
    ``stills_dir`` the saved frames' images as frame_{k:04d}.jpg (the viewer's slider). Returns
    the frame count (K + 1 for a run of K frames)."""
    from PIL import Image

    import imageio_ffmpeg

    size = (2 * settings.width, settings.height)
    outs = [(mp4, {"codec": "libx264", "output_params": ["-crf", str(settings.crf), "-preset", "veryfast",
                                                         "-movflags", "+faststart"]})]
    if webm is not None:
        outs.append((webm, {"codec": "libvpx-vp9", "output_params": ["-b:v", "0", "-crf", "36", "-deadline",
                                                                     "realtime", "-cpu-used", "8"]}))
    writers = []
    for path, opts in outs:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        w = imageio_ffmpeg.write_frames(str(path), size, fps=settings.fps, pix_fmt_out="yuv420p",
                                        macro_block_size=8, ffmpeg_log_level="error", **opts)
        w.send(None)
        writers.append(w)
    count = 0
    stills = set(saved_frames(run_h5)) if stills_dir is not None else set()
    if stills_dir is not None:
        Path(stills_dir).mkdir(parents=True, exist_ok=True)
    try:
        for k, img in video_frames(run_h5, target_mesh_h5, target_cfg, settings, log, particles_h5):
            for w in writers:
                w.send(np.ascontiguousarray(img))
            if k in stills:
                Image.fromarray(img).save(Path(stills_dir) / f"frame_{k:04d}.jpg", quality=85)
            count += 1
    finally:
        for w in writers:
            w.close()
    return count


def write_gif(mp4: Path, gif: Path, width: int = 640, max_bytes: int = 2_000_000) -> Path:
    """A GIF of ``mp4`` (the README's), shrunk until it is at most ``max_bytes``: every frame at
    ``width`` pixels, then every other frame, then narrower."""
    from PIL import Image

    frames = _read_mp4(mp4)
    step, w = 1, width
    while True:
        h = int(round(frames.shape[1] * w / frames.shape[2]))
        imgs = [Image.fromarray(fr).resize((w, h), Image.LANCZOS) for fr in frames[::step]]
        imgs = [im.convert("P", palette=Image.ADAPTIVE, colors=64) for im in imgs]
        gif.parent.mkdir(parents=True, exist_ok=True)
        imgs[0].save(gif, save_all=True, append_images=imgs[1:], duration=100 * step, loop=0, optimize=True)
        if gif.stat().st_size <= max_bytes or w < 160:
            return gif
        step, w = (2, w) if step == 1 else (step, int(w * 0.8))


def _read_mp4(mp4: Path) -> np.ndarray:  # [T, H, W, 3] uint8
    import imageio_ffmpeg

    reader = imageio_ffmpeg.read_frames(str(mp4))
    meta = reader.__next__()
    w, h = meta["size"]
    return np.stack([np.frombuffer(fr, np.uint8).reshape(h, w, 3) for fr in reader])


def video_record(mp4: Path) -> dict:
    """Frame count and duration of an encoded video (imageio_ffmpeg.count_frames_and_secs)."""
    import imageio_ffmpeg

    n, secs = imageio_ffmpeg.count_frames_and_secs(str(mp4))
    return {"frames": int(n), "seconds": float(secs), "bytes": Path(mp4).stat().st_size}
