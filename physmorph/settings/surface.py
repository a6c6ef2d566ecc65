"""The surface mask's settings (physmorph.morph.surface_mask, paper section 3.6)."""

from __future__ import annotations

from typing import Annotated

from physmorph.settings.base import Bool, Float, Int, setting, settings_dataclass


@settings_dataclass
class SurfaceMaskConfig:
    """The surface mask: which particles the render loss sees."""

    voxels: Annotated[Int, setting("voxels per axis of the density grid the mask is built on", ge=8)] = 64
    blur_sigma: Annotated[Float, setting("Gaussian blur of the density grid", "voxels", ge=0)] = 1.0
    level: Annotated[Float, setting("iso level, as a share of the 95th-percentile blurred density",
                                    gt=0, lt=1)] = 0.5
    band: Annotated[Float, setting("particles within this distance of the reconstructed surface are rendered",
                                   "voxels", gt=0)] = 1.5
    target_band: Annotated[Float, setting("and those within this distance of the target surface", "domain units",
                                          ge=0)] = 0.75
    enabled: Annotated[Bool, setting("false renders every particle")] = True
