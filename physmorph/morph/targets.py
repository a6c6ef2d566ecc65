"""Stage rasterize_target: what the morph is compared against (paper sections 3.5 and 4.1).

For the ring cameras (V views, elevation 21 degrees by default) the target mesh gives, per view:
- ``alpha``: exact coverage, the fraction of s x s sub-pixel rays that hit the mesh;
- ``depth``: camera-space z of the first hit through the pixel centre, 0 where no hit;
- ``sdt``: signed distance (pixels) to the silhouette boundary (alpha >= 0.5), positive
  outside and negative inside, zero half-way between a covered and an uncovered pixel centre.
On the simulation grid it gives the target mass distribution (the target's own particle
sampling splatted with the MPM's B-spline, ``physmorph.base.grid.splat_mass``) for the mass loss,
and it gives target surface points for Chamfer correspondences. The cameras are stored in the
file so every later stage uses the same ones.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy import ndimage

from physmorph.base.cameras import Cameras, ring_cameras
from physmorph.settings.sections import SamplingConfig, TargetConfig
from physmorph.base.grid import Grid, splat_mass
from physmorph.settings.render import RenderConfig
from physmorph.records.h5io import StageInputError, atomic_h5, open_h5, read_attr, read_field


class TargetCropWarning(UserWarning):
    """The target's silhouette reaches the image border: the part beyond it is invisible to the
    render loss and to the alpha-MSE metric (only the mass loss sees it)."""


def cropped_views(alpha: np.ndarray) -> list[int]:  # alpha [V, H, W]
    """The views whose silhouette touches the image border (coverage >= 0.5 on an edge pixel)."""
    edge = np.concatenate([alpha[:, 0, :], alpha[:, -1, :], alpha[:, :, 0], alpha[:, :, -1]], axis=1)
    return [int(v) for v in np.flatnonzero((edge >= 0.5).any(axis=1))]


@dataclass(frozen=True)
class Target:
    """Everything a morph needs to know about its target."""

    cameras: Cameras
    alpha: np.ndarray  # [V, H, W]
    depth: np.ndarray  # [V, H, W]
    sdt: np.ndarray  # [V, H, W] pixels, >0 outside
    grid_mass: np.ndarray  # [res, res, res]
    surface_points: np.ndarray  # [M, 3]
    grid: Grid
    volume: float
    shape: str
    # The best reachable (physmorph.morph.quality): the target's own particle sampling rendered at rest
    # (F = I) with the same renderer, cameras and sigma0, against ``alpha``.
    ceiling_alpha_mse: float  # mean over views
    ceiling_iou: float  # mean silhouette IoU over views
    ceiling_alpha_mse_views: np.ndarray  # [V]
    ceiling_iou_views: np.ndarray  # [V]


def signed_distance_transform(mask: np.ndarray) -> np.ndarray:  # mask [H, W] bool -> [H, W]
    """Signed Euclidean distance (pixels) to the boundary of ``mask``: >0 outside, <0 inside.

    A pixel centre's distance to the nearest pixel centre of the other class, minus half a pixel,
    so the zero level sits on the boundary between the two. An empty (full) mask has no boundary:
    every pixel gets +(H + W) (-(H + W)), "far outside" ("far inside").
    """
    mask = np.asarray(mask, dtype=bool)
    far = float(mask.shape[0] + mask.shape[1])
    if not mask.any():
        return np.full(mask.shape, far)
    if mask.all():
        return np.full(mask.shape, -far)
    outside = ndimage.distance_transform_edt(~mask) - 0.5  # for outside pixels: distance to inside
    inside = ndimage.distance_transform_edt(mask) - 0.5  # for inside pixels: distance to outside
    return np.where(mask, -inside, outside)


def rasterize_mesh(mesh: trimesh.Trimesh, cameras: Cameras, supersample: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Coverage alpha [V, H, W] (s x s stratified rays per pixel) and centre-ray depth [V, H, W]."""
    intersector = mesh.ray  # Embree-backed when embreex is installed
    H, W, s = cameras.height, cameras.width, int(supersample)
    alpha = np.zeros((cameras.count, H, W))
    depth = np.zeros((cameras.count, H, W))
    offsets = (np.arange(s) + 0.5) / s  # sub-pixel sample positions within [0, 1)
    for v in range(cameras.count):
        fx, fy, cx, cy = cameras.intrinsics[v]
        R, t = cameras.rotation[v], cameras.translation[v]
        origin = cameras.centers[v]
        # Sub-pixel rays: (row j, col i, sub-row a, sub-col b).
        jj = (np.arange(H)[:, None] + offsets[None, :]).reshape(-1)  # [H*s]
        ii = (np.arange(W)[:, None] + offsets[None, :]).reshape(-1)  # [W*s]
        vv, uu = np.meshgrid(jj, ii, indexing="ij")
        d_cam = np.stack([(uu - cx) / fx, (vv - cy) / fy, np.ones_like(uu)], -1).reshape(-1, 3)
        d_world = d_cam @ R
        d_world /= np.linalg.norm(d_world, axis=1, keepdims=True)
        hit = intersector.intersects_any(np.broadcast_to(origin, d_world.shape), d_world)
        alpha[v] = hit.reshape(H, s, W, s).mean(axis=(1, 3))
        # Depth through the pixel centres.
        o, d = cameras.pixel_rays(v)
        loc, ray_idx, _ = intersector.intersects_location(o, d, multiple_hits=False)
        if len(ray_idx):
            z = (loc @ R.T + t)[:, 2]
            flat = np.zeros(H * W)
            # intersects_location may return more than one hit per ray on some backends: keep nearest
            order = np.argsort(-z)
            flat[ray_idx[order]] = z[order]
            depth[v] = flat.reshape(H, W)
    return alpha, depth


def rasterize_target(
    mesh_h5: str | Path,
    out_h5: str | Path,
    sampling: SamplingConfig,
    target_cfg: TargetConfig,
    seed: int = 0,
    preview_png: str | Path | None = None,
    config: dict | None = None,
    render: RenderConfig | None = None,
) -> dict:
    """Write the target HDF5 for one shape at one resolution; returns a summary dict."""
    from physmorph.meshes.prepare import load_mesh
    from physmorph.meshes.particles import mean_nn_distance, sample_volume
    from physmorph.morph.quality import ceiling_metrics

    mesh = load_mesh(mesh_h5)
    with open_h5(mesh_h5) as f:
        shape = str(f.attrs.get("shape", Path(mesh_h5).stem))
    grid = Grid(sampling.grid_res)
    cams = ring_cameras(target_cfg.cameras, target_cfg.elevation_deg, target_cfg.fov_y_deg,
                        target_cfg.width, target_cfg.height, target_cfg.distance, target_cfg.elevation_spread_deg)
    alpha, depth = rasterize_mesh(mesh, cams, target_cfg.supersample)
    cropped = cropped_views(alpha)
    if cropped:
        warnings.warn(f"{mesh_h5} (shape '{shape}'): the silhouette touches the image border in views "
                      f"{cropped} of {cams.count}; what lies beyond is invisible to the render loss and the alpha "
                      "MSE. Shrink the shape (python -m physmorph.meshes.fit prints a size that fits the views)",
                      TargetCropWarning, stacklevel=2)
    sdt = np.stack([signed_distance_transform(a >= 0.5) for a in alpha])
    x, vol, _ = sample_volume(mesh, grid, sampling.ppc_surface, sampling.ppc_interior, seed)
    grid_mass = splat_mass(x, sampling.density * vol, grid)
    # The ceiling: these same particles (the target's own sampling) rendered at rest with the
    # sigma0 sample_particles gives them, the same renderer settings and these cameras.
    ceiling_sigma0 = float(sampling.sigma_scale * mean_nn_distance(x))
    ceiling = ceiling_metrics(x, ceiling_sigma0, cams, alpha, render if render is not None else RenderConfig())
    surface_points, _ = trimesh.sample.sample_surface(mesh, target_cfg.surface_points, seed=seed)
    summary = dict(shape=shape, views=cams.count, width=cams.width, height=cams.height,
                   coverage=[float(a.mean()) for a in alpha], grid_mass_total=float(grid_mass.sum()),
                   surface_points=int(len(surface_points)), volume=float(mesh.volume), cropped_views=cropped,
                   ceiling_alpha_mse=ceiling["alpha_mse"], ceiling_iou=ceiling["iou"], ceiling_sigma0=float(ceiling_sigma0),
                   ceiling_alpha_mse_views=[float(v) for v in ceiling["alpha_mse_views"]],
                   ceiling_iou_views=[float(v) for v in ceiling["iou_views"]])
    with atomic_h5(out_h5, config=config) as f:
        cams.to_h5(f.create_group("cameras"))
        f.create_dataset("alpha", data=alpha.astype(np.float32), compression="gzip")
        f.create_dataset("depth", data=depth.astype(np.float32), compression="gzip")
        f.create_dataset("sdt", data=sdt.astype(np.float32), compression="gzip")
        f.create_dataset("grid_mass", data=grid_mass, compression="gzip")
        f.create_dataset("surface_points", data=np.asarray(surface_points, dtype=np.float64))
        f.create_dataset("ceiling_alpha_mse_views", data=ceiling["alpha_mse_views"])
        f.create_dataset("ceiling_iou_views", data=ceiling["iou_views"])
        f.attrs.update(ceiling_alpha_mse=ceiling["alpha_mse"], ceiling_iou=ceiling["iou"], ceiling_sigma0=ceiling_sigma0)
        f.attrs.update(shape=shape, grid_res=grid.res, lo=grid.lo, hi=grid.hi, dx=grid.dx,
                       sdt_units="pixels", depth_convention="z_cam of first hit at pixel centre, 0 = no hit",
                       volume=float(mesh.volume), density=sampling.density, seed=seed,
                       cropped_views=np.asarray(cropped, dtype=np.int64))
    if preview_png is not None:
        silhouette_preview(alpha, preview_png, title=f"target {shape}: {cams.count} views")
    return summary


def load_target(path: str | Path) -> Target:
    """Read a target HDF5; a missing or malformed field raises StageInputError naming it."""
    with open_h5(path) as f:
        if "cameras" not in f:
            raise StageInputError(f"{f.filename}: missing group 'cameras'")
        try:
            cams = Cameras.from_h5(f["cameras"])
        except (KeyError, ValueError) as exc:
            raise StageInputError(f"{f.filename}: malformed group 'cameras' ({exc})") from exc
        img = (cams.count, cams.height, cams.width)
        fields = {name: read_field(f, name) for name in ("alpha", "depth", "sdt")}
        for name, arr in fields.items():
            if arr.shape != img:
                raise StageInputError(f"{f.filename}: field '{name}' has shape {arr.shape}, expected {img}")
        res = int(read_attr(f, "grid_res"))
        grid = Grid(res, float(read_attr(f, "lo")), float(read_attr(f, "hi")))
        grid_mass = read_field(f, "grid_mass", (res, res, res))
        pts = read_field(f, "surface_points", (3,))
        try:
            ceiling = {name: float(read_attr(f, name)) for name in ("ceiling_alpha_mse", "ceiling_iou")}
            ceiling.update({name: read_field(f, name, (cams.count,)).astype(np.float64)
                            for name in ("ceiling_alpha_mse_views", "ceiling_iou_views")})
        except StageInputError as exc:
            raise StageInputError(f"{exc} (a target written before the ceiling was stored: "
                                  "rerun the rasterize_target stage)") from exc
        return Target(cams, fields["alpha"].astype(np.float64), fields["depth"].astype(np.float64),
                      fields["sdt"].astype(np.float64), grid_mass, pts, grid,
                      float(read_attr(f, "volume")), str(read_attr(f, "shape")), **ceiling)


def silhouette_preview(alpha: np.ndarray, png: str | Path, title: str = "") -> None:  # alpha [V, H, W]
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    V = alpha.shape[0]
    cols = min(4, V)
    rows = int(np.ceil(V / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(2.4 * cols, 1.6 * rows + 0.4), squeeze=False)
    for k, ax in enumerate(axes.flat):
        ax.axis("off")
        if k < V:
            ax.imshow(alpha[k], cmap="gray", vmin=0, vmax=1)
            ax.set_title(f"view {k}", fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    Path(png).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=80)
    plt.close(fig)
