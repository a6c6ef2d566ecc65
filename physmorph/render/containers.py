"""The renderer's data containers: the target images it is compared against and what a render returns (paper sections 3.2, 3.5); its settings are physmorph.settings.render."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np



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

    def in_float(self, render_dtype: str) -> "RenderTarget":
        """The images in the renderer's float type (RenderConfig.dtype), contiguous: a renderer of
        that type reads them without converting them at each call."""
        dtype = np.float64 if render_dtype == "float64" else np.float32
        return RenderTarget(*(np.ascontiguousarray(a, dtype=dtype) for a in (self.alpha, self.depth, self.sdt)))


@dataclass
class RenderResult:
    """What :func:`physmorph.render.api.render_and_grad` returns (numpy, float64)."""

    alpha: np.ndarray  # [V, H, W] rendered alpha = 1 - final transmittance
    depth: np.ndarray  # [V, H, W] expected depth (sum a T z) / alpha, 0 where alpha <= alpha_min
    losses: dict[str, float]  # dt, iou, depth, total (total = dt + w_iou iou + w_depth depth)
    alpha_mse_per_view: np.ndarray  # [V]
    alpha_mse: float
    grad_F: np.ndarray  # [N, 3, 3] dL_render/dF after adaptive gradient matching
    grad_x: np.ndarray | None  # [N, 3] or None
    weights: dict[str, float] = field(default_factory=dict)  # effective loss weights used for F (and x)
