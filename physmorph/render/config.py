"""Configuration and result containers of the Gaussian splatting renderer (paper sections 3.2, 3.5)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np


@dataclass(frozen=True)
class RenderConfig:
    """Settings of the differentiable splatting renderer and its losses.

    opacity: peak opacity of every Gaussian. Particles carry no learned opacity, so one constant
        is used. 0.9 makes a single layer of overlapping surface Gaussians (sigma0 = 0.7 d_nn)
        nearly opaque (alpha > 0.99 after a few layers) while the silhouette edge still falls
        off smoothly over about one sigma, which is what the silhouette losses need.
    low_pass: pixels^2 added to the diagonal of every 2D covariance (EWA low-pass / 3DGS's 0.3):
        keeps sub-pixel and degenerate Gaussians at least about a pixel wide and their 2D
        covariance invertible.
    tile_size: side of the square screen tiles Gaussians are binned into.
    cutoff_sigma: a Gaussian is evaluated only where its 2D Mahalanobis distance is below this
        (the exact axis-aligned box of that ellipse decides which tiles it touches).
    alpha_min: per-Gaussian alpha below this is skipped (3DGS: 1/255).
    alpha_max: per-Gaussian alpha is clamped to this (3DGS: 0.99) so 1 - alpha never reaches 0
        and the backward pass can divide by it.
    transmittance_min: compositing stops once the transmittance in front of the next Gaussian
        is below this (3DGS: 1e-4). Set 0 to composite every Gaussian.
    iou_fraction / depth_fraction: adaptive gradient matching (paper section 3.5): the soft-IoU
        and depth gradients are rescaled so their norm is this fraction of the DT gradient's
        norm before they are added (see :func:`physmorph.render.losses.match_gradients`).
        The paper gives no values; these defaults are ours.
    depth_min_alpha: the depth loss only uses pixels whose rendered alpha exceeds this (the
        expected depth D / alpha is meaningless where almost nothing is rendered).
    dtype: float type of the renderer ("float32" for speed, "float64" for gradient checks).
    kernel: "auto" | "tile" | "pixel": the rasterizer's loop order. "tile" (Gaussian-major, one
        thread per tile, only the pixels in each Gaussian's cutoff box) is faster on CPU;
        "pixel" (one thread per pixel, as 3DGS) suits CUDA; "auto" picks by device. Both give
        the same result.
    device: "auto" | "cpu" | "cuda" (torch tensors and Taichi kernels).
    """

    opacity: float = 0.9
    low_pass: float = 0.3
    tile_size: int = 16
    cutoff_sigma: float = 3.0
    alpha_min: float = 1.0 / 255.0
    alpha_max: float = 0.99
    transmittance_min: float = 1e-4
    iou_fraction: float = 0.5
    depth_fraction: float = 0.25
    depth_min_alpha: float = 0.1
    dtype: Literal["float32", "float64"] = "float32"
    kernel: Literal["auto", "tile", "pixel"] = "auto"
    device: Literal["auto", "cpu", "cuda"] = "cpu"

    def __post_init__(self) -> None:
        if not 0.0 < self.opacity <= 1.0:
            raise ValueError(f"opacity must be in (0, 1], got {self.opacity}")
        if self.low_pass < 0.0:
            raise ValueError(f"low_pass must be >= 0, got {self.low_pass}")
        if self.tile_size < 1:
            raise ValueError(f"tile_size must be >= 1, got {self.tile_size}")
        if self.cutoff_sigma <= 0.0:
            raise ValueError(f"cutoff_sigma must be > 0, got {self.cutoff_sigma}")
        if not 0.0 < self.alpha_max < 1.0:
            raise ValueError(f"alpha_max must be in (0, 1), got {self.alpha_max}")
        if not 0.0 <= self.alpha_min < self.alpha_max:
            raise ValueError(f"alpha_min must be in [0, alpha_max), got {self.alpha_min}")
        if not 0.0 <= self.transmittance_min < 1.0:
            raise ValueError(f"transmittance_min must be in [0, 1), got {self.transmittance_min}")
        if self.iou_fraction < 0.0 or self.depth_fraction < 0.0:
            raise ValueError("iou_fraction and depth_fraction must be >= 0")
        if self.dtype not in ("float32", "float64"):
            raise ValueError(f"dtype must be float32 or float64, got {self.dtype!r}")
        if self.kernel not in ("auto", "tile", "pixel"):
            raise ValueError(f"kernel must be auto, tile or pixel, got {self.kernel!r}")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ValueError(f"device must be auto, cpu or cuda, got {self.device!r}")


@dataclass
class RenderTarget:
    """Per-view target images, read from the target HDF5 (rasterize_target stage)."""

    alpha: np.ndarray  # [V, H, W] exact mesh coverage fraction per pixel, in [0, 1]
    depth: np.ndarray  # [V, H, W] z_cam of the first mesh hit at the pixel centre, 0 where not covered
    sdt: np.ndarray  # [V, H, W] signed distance to the silhouette boundary in pixels, > 0 outside

    def __post_init__(self) -> None:
        shapes = {np.shape(self.alpha), np.shape(self.depth), np.shape(self.sdt)}
        if len(shapes) != 1 or len(next(iter(shapes))) != 3:
            raise ValueError(f"target alpha, depth and sdt must share one [V, H, W] shape, got {shapes}")


@dataclass
class RenderResult:
    """What :func:`physmorph.render.render_and_grad` returns (numpy, float64)."""

    alpha: np.ndarray  # [V, H, W] rendered alpha = 1 - final transmittance
    depth: np.ndarray  # [V, H, W] expected depth (sum a T z) / alpha, 0 where alpha <= alpha_min
    losses: dict[str, float]  # dt, iou, depth, total (total = dt + w_iou iou + w_depth depth)
    alpha_mse_per_view: np.ndarray  # [V]
    alpha_mse: float
    grad_F: np.ndarray  # [N, 3, 3] dL_render/dF after adaptive gradient matching
    grad_x: np.ndarray | None  # [N, 3] or None
    weights: dict[str, float] = field(default_factory=dict)  # effective loss weights used for F (and x)
