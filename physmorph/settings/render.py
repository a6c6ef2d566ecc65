"""The renderer's settings (physmorph.render, paper sections 3.2, 3.5): image, Gaussians, compositing and losses."""

from __future__ import annotations

from typing import Annotated, Literal

from physmorph.settings.base import Float, Int, Refused, setting, settings_dataclass

# The render loss's terms (paper section 3.5: distance transform, soft IoU, depth) and the run
# file's scalar each is recorded as, "total" being their weighted sum: declared once, for the
# renderer that computes them, the run file that stores them and the pages and phases that read them.
LOSS_TERMS = ("dt", "iou", "depth")
LOSS_SCALARS = {**{term: f"loss_{term}" for term in LOSS_TERMS}, "total": "loss_render"}

@settings_dataclass
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

    opacity: Annotated[Float, setting("peak opacity of every Gaussian (particles carry no learned opacity)",
                                      gt=0, le=1)] = 0.9
    low_pass: Annotated[Float, setting("added to the diagonal of every 2D covariance (EWA low-pass)", "pixels^2",
                                       ge=0)] = 0.3
    tile_size: Annotated[Int, setting("side of the screen tiles Gaussians are binned into", "pixels", ge=1)] = 16
    cutoff_sigma: Annotated[Float, setting("a Gaussian is evaluated within this 2D Mahalanobis distance", "sigma",
                                           gt=0)] = 3.0
    alpha_min: Annotated[Float, setting("per-Gaussian alpha below this is skipped", "", "[0, alpha_max)",
                                        ge=0)] = 1.0 / 255.0
    alpha_max: Annotated[Float, setting("per-Gaussian alpha is clamped to this", gt=0, lt=1)] = 0.99
    transmittance_min: Annotated[Float, setting("compositing stops below this transmittance; 0 composites all",
                                                ge=0, lt=1)] = 1e-4
    iou_fraction: Annotated[Float, setting(
        "soft-IoU gradient scaled to this share of the distance-transform gradient's norm", ge=0)] = 0.5
    depth_fraction: Annotated[Float, setting(
        "depth gradient scaled to this share of the distance-transform gradient's norm", ge=0)] = 0.25
    depth_min_alpha: Annotated[Float, setting("the depth loss uses pixels whose rendered alpha exceeds this",
                                              ge=0, le=1)] = 0.1
    dtype: Annotated[Literal["float32", "float64"], setting(
        "floating-point type of the renderer (float64 for gradient checks)")] = "float32"
    kernel: Annotated[Literal["auto", "tile", "pixel"], setting(
        "rasterizer loop order: tile (faster on CPU), pixel (CUDA), auto by device")] = "auto"
    device: Annotated[Literal["auto", "cpu", "cuda"], setting(
        "where torch and Taichi run (set by device)")] = "cpu"

    def __post_init__(self) -> None:
        """The check across fields (each field's own range is its declaration's)."""
        if not self.alpha_min < self.alpha_max:
            raise Refused("alpha_min", f"alpha_min must be in [0, alpha_max), got {self.alpha_min}")
