"""What a video draws of the body at each frame (``export.body``): ``surface``, the closed surface
the export's meshes are (the particles' volume on a grid, marching cubes, Taubin smoothing, which
does not shrink it: physmorph.reports.export.surface), evenly sampled as small round Gaussians, as
the target is drawn; or ``particles``, the run's own Gaussians as the render loss sees them. The
paper shows its results as smoothed surfaces; the metrics are the raw run's either way."""

from __future__ import annotations

import numpy as np

from physmorph.settings.export import ExportConfig

# Gaussians on a surface, the body's or the target's: enough that the skin is closed at the video's size
SURFACE_GAUSSIANS = 40_000


def surface_gaussians(mesh, count: int = SURFACE_GAUSSIANS, seed: int = 0) -> tuple[np.ndarray, np.ndarray, float]:
    """``mesh`` (trimesh) as ``count`` round Gaussians (F = I) evenly on its surface, sigma the
    points' spacing sqrt(area / count): a closed, evenly lit skin. x [M, 3], F [M, 3, 3], sigma."""
    import trimesh

    pts = np.asarray(trimesh.sample.sample_surface_even(mesh, count, seed=seed)[0], dtype=np.float64)
    return pts, np.broadcast_to(np.eye(3), (len(pts), 3, 3)).copy(), float(np.sqrt(mesh.area / len(pts)))


def subsample(x: np.ndarray,  # [N, 3]
              F: np.ndarray,  # [N, 3, 3]
              sigma0: float, limit: int) -> tuple[np.ndarray, np.ndarray, float]:
    """At most ``limit`` particles, evenly strided, each Gaussian widened by (N / M)^(1/3) so the
    body stays closed (the same fill per volume)."""
    n = len(x)
    if n <= limit:
        return x, F, sigma0
    step = int(np.ceil(n / limit))
    return x[::step], F[::step], sigma0 * (n / len(x[::step])) ** (1.0 / 3.0)


class BodyDrawing:
    """The body's Gaussians of one frame for the video, as ``settings.body`` says; ``rest``: the
    particle file's ``volume`` [N] and ``dx`` (physmorph.reports.export.runs.rest_particles), which the
    surface needs."""

    def __init__(self, settings: ExportConfig, sigma0: float, rest: dict | None = None):
        if settings.body == "surface" and rest is None:
            raise ValueError("export.body 'surface' needs the run's particle file (its rest volumes)")
        self.settings, self.sigma0, self.rest = settings, float(sigma0), rest

    def gaussians(self, x: np.ndarray,  # [N, 3]
                  F: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:  # [N, 3, 3]
        s = self.settings
        if s.body == "particles":
            return subsample(x, F, self.sigma0, s.max_particles)
        from physmorph.reports.export.surface import particle_surface

        mesh = particle_surface(np.asarray(x, np.float64), self.rest["volume"], np.linalg.det(np.asarray(F, np.float64)),
                                self.rest["dx"], **s.surface())
        return surface_gaussians(mesh)


def body_label(name: str, k: int, frames: int, closed: float, volume_iou: float) -> str:
    """The video frame's label: the run, the frame, the share of the gap closed and the volume IoU."""
    text = f"{name}  frame {k}/{frames}"
    if np.isfinite(closed):
        text += f"  {100 * closed:.0f} % of the gap"
    if np.isfinite(volume_iou):
        text += f"  volume IoU {volume_iou:.2f}"
    return text
