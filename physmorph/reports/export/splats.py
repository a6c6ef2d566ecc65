"""Particles as 3D Gaussians in the PLY layout of the original 3D Gaussian splatting viewers.

Each particle p is the renderer's Gaussian (physmorph.render.projection.covariance_from_F, paper
eq. 1): mean x_p, covariance Sigma_p = F_p Sigma0 F_p^T with Sigma0 = sigma0^2 I, i.e.
Sigma_p = sigma0^2 F_p F_p^T (F the total deformation gradient the run saves; sigma0 the particle
file's, recorded in the run's attributes). Its peak opacity is the renderer's constant
RenderConfig.opacity and it is drawn in one flat colour (the renderer draws coverage, not colour;
the default is the colour of physmorph.render.api.shade). Every particle given is written: the morph's
loss draws only its surface mask, which the run does not save (``is_surface`` of
physmorph.reports.export.runs.frame_state selects the sampled surface shell instead). Positions are in domain
units with +y up (physmorph.base.cameras); viewers made for COLMAP scenes (y down) show it upside down.

File layout (binary little-endian PLY, one ``vertex`` element of 62 float32 properties in this
order, the full vertex Kerbl et al. 2023's training code writes (SH degree 3): the reference SIBR
viewer fails on a file without the ``f_rest`` properties and Unity's importer expects all 62):
  x, y, z               mean
  nx, ny, nz            0 (unused by viewers)
  f_dc_0, f_dc_1, f_dc_2  degree-0 SH coefficient of the colour: (rgb - 0.5) / SH_C0
  f_rest_0..44          0: the degree-1..3 SH coefficients (15 per colour channel); the colour is flat
  opacity               logit of the peak opacity (a viewer applies the sigmoid)
  scale_0..2            log of the standard deviations along the Gaussian's axes
  rot_0..3              unit quaternion (w, x, y, z) of the rotation R whose columns are the axes
so that Sigma = R diag(exp(scale))^2 R^T. The factorisation is a symmetric eigendecomposition
(numpy.linalg.eigh) of Sigma in float64; float32 storage then keeps Sigma to ~1e-7 relative.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from physmorph.settings.render import RenderConfig  # light: the renderer's torch modules load lazily

SH_C0 = 0.28209479177387814  # the degree-0 real spherical harmonic, 1 / (2 sqrt(pi))
DEFAULT_RGB = (0.80, 0.62, 0.45)  # physmorph.render.api.shade's default colour
RENDER_OPACITY = RenderConfig().opacity  # the renderer's peak opacity of every Gaussian
_OPACITY_CLIP = 1e-6  # opacity 1 (or 0) has an infinite logit: clipped this far into (0, 1)
SH_REST = 45  # f_rest_*: the SH coefficients of degrees 1..3, 15 per colour channel (all 0 here)
_PROPERTIES = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(SH_REST)]
               + ["opacity"] + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)])


def covariances_from_F(F: np.ndarray,  # [N, 3, 3] deformation gradients
                       sigma0: float | np.ndarray) -> np.ndarray:  # [N, 3, 3]
    """Sigma_p = F_p Sigma0 F_p^T with Sigma0 = sigma0^2 I (the renderer's; sigma0 scalar or [N])."""
    F = np.asarray(F, dtype=np.float64)
    s2 = np.asarray(sigma0, dtype=np.float64) ** 2
    s2 = s2.reshape(-1, 1, 1) if s2.ndim > 0 else s2
    return s2 * (F @ np.swapaxes(F, -1, -2))


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:  # R: [N, 3, 3] proper rotations -> [N, 4]
    """Unit quaternions (w, x, y, z), w >= 0, of rotation matrices (Shepperd's method).

    Each rotation takes the branch whose square root argument is largest (4w^2 = 1 + tr R, or
    4x^2 = 1 + R00 - R11 - R22, ...), so no division is by a number near zero.
    """
    R = np.asarray(R, dtype=np.float64)
    r00, r11, r22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    d21, d02, d10 = R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]
    s01, s02, s12 = R[:, 0, 1] + R[:, 1, 0], R[:, 0, 2] + R[:, 2, 0], R[:, 1, 2] + R[:, 2, 1]
    diag = np.stack([r00 + r11 + r22, r00 - r11 - r22, r11 - r00 - r22, r22 - r00 - r11], axis=1)
    branch = np.argmax(diag, axis=1)
    big = 0.5 * np.sqrt(np.maximum(1.0 + diag[np.arange(len(R)), branch], 1e-300))  # the largest |component|
    inv = 0.25 / big
    q = np.empty((len(R), 4))
    rows = {  # branch -> (w, x, y, z) given the largest component ``big``
        0: (big, d21 * inv, d02 * inv, d10 * inv),
        1: (d21 * inv, big, s01 * inv, s02 * inv),
        2: (d02 * inv, s01 * inv, big, s12 * inv),
        3: (d10 * inv, s02 * inv, s12 * inv, big),
    }
    for b, comps in rows.items():
        sel = branch == b
        q[sel] = np.stack([c[sel] for c in comps], axis=1)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)  # q and -q are the same rotation: w >= 0
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:  # q: [N, 4] (w, x, y, z) -> [N, 3, 3]
    """Rotation matrices of quaternions (w, x, y, z), normalised first (as the 3DGS viewers do)."""
    q = np.asarray(q, dtype=np.float64)
    w, x, y, z = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=1)


def _factor_covariances(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # cov: [N, 3, 3]
    """Sigma = R diag(s^2) R^T by eigh: log std-devs [N, 3] and quaternions (w first) [N, 4]."""
    cov = 0.5 * (cov + np.swapaxes(cov, -1, -2))  # exactly symmetric for eigh
    eigenvalues, R = np.linalg.eigh(cov)  # columns of R: the axes
    R[np.linalg.det(R) < 0, :, 2] *= -1.0  # a proper rotation: flipping an axis leaves Sigma unchanged
    # rounding can leave a flat Gaussian's least eigenvalue at or below 0: keep its log finite
    floor = 1e-24 * np.maximum(eigenvalues[:, 2:], 1e-300)
    log_scale = 0.5 * np.log(np.maximum(eigenvalues, floor))
    return log_scale, rotation_to_quaternion(R)


def write_splats(path: str | os.PathLike,
                 x: np.ndarray,  # [N, 3] means, domain units
                 F: np.ndarray,  # [N, 3, 3] deformation gradients
                 sigma0: float | np.ndarray,  # rest std-dev, scalar or [N]
                 rgb: tuple[float, float, float] | np.ndarray = DEFAULT_RGB,  # [3] or [N, 3] in [0, 1]
                 opacity: float = RENDER_OPACITY,
                 transform: np.ndarray | None = None) -> Path:
    """Write the Gaussians x_p, Sigma_p = sigma0^2 F_p F_p^T as a 3DGS PLY (layout: module docstring).

    ``transform``: a 4x4 affine matrix [[A, t], [0, 1]] applied first (x -> A x + t,
    Sigma -> A Sigma A^T), e.g. physmorph.reports.export.surface.domain_to_input. Written aside and renamed into
    place. Returns the path.
    """
    from plyfile import PlyData, PlyElement

    x = np.asarray(x, dtype=np.float64)
    n = len(x)
    if x.shape != (n, 3) or np.shape(F) != (n, 3, 3):
        raise ValueError(f"need x [N, 3] and F [N, 3, 3], got {x.shape} and {np.shape(F)}")
    cov = covariances_from_F(F, sigma0)
    if transform is not None:
        transform = np.asarray(transform, dtype=np.float64)
        A = transform[:3, :3]
        x = x @ A.T + transform[:3, 3]
        cov = A @ cov @ A.T
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(cov))):
        raise ValueError("positions and covariances must be finite")
    log_scale, quat = _factor_covariances(cov)
    colour = np.broadcast_to(np.asarray(rgb, dtype=np.float64), (n, 3))
    p = float(np.clip(opacity, _OPACITY_CLIP, 1.0 - _OPACITY_CLIP))
    vertex = np.zeros(n, dtype=[(name, "<f4") for name in _PROPERTIES])  # nx, ny, nz and f_rest_* stay 0
    for names, block in ((["x", "y", "z"], x), ([f"f_dc_{i}" for i in range(3)], (colour - 0.5) / SH_C0),
                         ([f"scale_{i}" for i in range(3)], log_scale), ([f"rot_{i}" for i in range(4)], quat)):
        for name, values in zip(names, block.T):  # block: [N, len(names)]
            vertex[name] = values
    vertex["opacity"] = np.log(p / (1.0 - p))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".partial")
    try:
        PlyData([PlyElement.describe(vertex, "vertex")], byte_order="<").write(str(tmp))
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def read_splats(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """A 3DGS PLY's Gaussians: x [N, 3], rgb [N, 3] (SH degree 0), opacity [N] (after the
    sigmoid), scale [N, 3] (std-devs), rotation [N, 4] (unit quaternion, w first), cov [N, 3, 3]."""
    from plyfile import PlyData

    v = PlyData.read(str(path))["vertex"].data

    def col(names: list[str]) -> np.ndarray:  # [N, len(names)] float64
        return np.stack([np.asarray(v[k], dtype=np.float64) for k in names], axis=1)

    q = col([f"rot_{i}" for i in range(4)])
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    scale = np.exp(col([f"scale_{i}" for i in range(3)]))
    R = quaternion_to_rotation(q)
    return {"x": col(["x", "y", "z"]), "rgb": 0.5 + SH_C0 * col([f"f_dc_{i}" for i in range(3)]),
            "opacity": 1.0 / (1.0 + np.exp(-np.asarray(v["opacity"], dtype=np.float64))),
            "scale": scale, "rotation": q, "cov": (R * scale[:, None, :] ** 2) @ np.swapaxes(R, -1, -2)}


def read_splat_covariances(path: str | os.PathLike) -> np.ndarray:  # [N, 3, 3]
    """The covariances R diag(exp(scale))^2 R^T a 3DGS PLY stores (what a viewer draws)."""
    return read_splats(path)["cov"]
