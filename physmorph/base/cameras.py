"""Pinhole cameras shared by target rasterization, the Gaussian renderer and figures.

Conventions (OpenCV style, used everywhere in physmorph):
- world: +y is up; the ring cameras circle the y axis and look at the origin.
- camera: x_cam = R @ x_world + t, with +x right, +y down, +z forward (depth = z_cam > 0).
- pixel: u = fx * x_cam / z_cam + cx, v = fy * y_cam / z_cam + cy; pixel (row j, column i)
  covers [i, i+1) x [j, j+1) so its centre is (i + 0.5, j + 0.5). Images are [H, W].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Cameras:
    """V pinhole cameras of one image size."""

    world_to_cam: np.ndarray  # [V, 4, 4]
    intrinsics: np.ndarray  # [V, 4] fx, fy, cx, cy (pixels)
    width: int
    height: int
    near: float = 0.1

    def __post_init__(self) -> None:
        w2c = np.asarray(self.world_to_cam, dtype=np.float64)
        k = np.asarray(self.intrinsics, dtype=np.float64)
        if w2c.ndim != 3 or w2c.shape[1:] != (4, 4):
            raise ValueError(f"world_to_cam must be [V, 4, 4], got {w2c.shape}")
        if k.shape != (w2c.shape[0], 4):
            raise ValueError(f"intrinsics must be [V, 4] with V={w2c.shape[0]}, got {k.shape}")
        if self.width < 1 or self.height < 1:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "world_to_cam", w2c)
        object.__setattr__(self, "intrinsics", k)

    @property
    def count(self) -> int:
        return self.world_to_cam.shape[0]

    @property
    def rotation(self) -> np.ndarray:  # [V, 3, 3]
        return self.world_to_cam[:, :3, :3]

    @property
    def translation(self) -> np.ndarray:  # [V, 3]
        return self.world_to_cam[:, :3, 3]

    @property
    def centers(self) -> np.ndarray:  # [V, 3] camera centres in world space
        return -np.einsum("vji,vj->vi", self.rotation, self.translation)

    def subset(self, views: list[int] | np.ndarray) -> "Cameras":
        views = np.asarray(views, dtype=np.int64)
        return Cameras(self.world_to_cam[views], self.intrinsics[views], self.width, self.height, self.near)

    def project(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates [V, N, 2] and depths [V, N] of world points x: [N, 3]."""
        return self.project_camera(self.rotate(x) + self.translation[:, None, :])

    def rotate(self, x: np.ndarray) -> np.ndarray:  # [V, N, 3]
        """R_v x of world points x: [N, 3] in every view (the camera frame less its translation;
        a matrix product: einsum's loop took 25 ms for 8 views of 35K points, this 3 ms)."""
        return np.matmul(np.asarray(x, dtype=np.float64)[None], self.rotation.transpose(0, 2, 1))

    def project_camera(self, xc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates [V, N, 2] and depths [V, N] of points xc: [V, N, 3] in each view's camera frame."""
        z = xc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.intrinsics[:, None, 0] * xc[..., 0] / z + self.intrinsics[:, None, 2]
            v = self.intrinsics[:, None, 1] * xc[..., 1] / z + self.intrinsics[:, None, 3]
        return np.stack([u, v], axis=-1), z

    def pixel_rays(self, view: int) -> tuple[np.ndarray, np.ndarray]:
        """World-space ray origins [H*W, 3] and unit directions [H*W, 3] through pixel centres."""
        fx, fy, cx, cy = self.intrinsics[view]
        jj, ii = np.meshgrid(np.arange(self.height) + 0.5, np.arange(self.width) + 0.5, indexing="ij")
        d_cam = np.stack([(ii - cx) / fx, (jj - cy) / fy, np.ones_like(ii)], axis=-1).reshape(-1, 3)
        d_world = d_cam @ self.rotation[view]  # R^T d
        d_world /= np.linalg.norm(d_world, axis=1, keepdims=True)
        origins = np.broadcast_to(self.centers[view], d_world.shape).copy()
        return origins, d_world

    def to_h5(self, group) -> None:
        group.create_dataset("world_to_cam", data=self.world_to_cam)
        group.create_dataset("intrinsics", data=self.intrinsics)
        group.attrs["width"] = int(self.width)
        group.attrs["height"] = int(self.height)
        group.attrs["near"] = float(self.near)

    @classmethod
    def from_h5(cls, group) -> "Cameras":
        return cls(
            world_to_cam=group["world_to_cam"][()],
            intrinsics=group["intrinsics"][()],
            width=int(group.attrs["width"]),
            height=int(group.attrs["height"]),
            near=float(group.attrs["near"]),
        )


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """World-to-camera matrix [4, 4] for a camera at ``eye`` looking at ``target`` (+y image down)."""
    forward = np.asarray(target, float) - np.asarray(eye, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:
        raise ValueError("look_at: view direction is parallel to the up vector")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rot = np.stack([right, down, forward])
    m = np.eye(4)
    m[:3, :3] = rot
    m[:3, 3] = -rot @ np.asarray(eye, float)
    return m


def height_past_a_pole(elevation_deg: float, spread_deg: float = 0.0) -> float | None:
    """The first of a ring's two heights (elevation ± spread, degrees) at or past a pole, where
    look_at's up vector would be the view direction; None when both lie strictly between."""
    return next((h for h in (elevation_deg + spread_deg, elevation_deg - spread_deg) if not -90.0 < h < 90.0), None)


def ring_cameras(
    count: int = 8,
    elevation_deg: float = 21.0,
    fov_y_deg: float = 40.0,
    width: int = 320,
    height: int = 180,
    distance: float = 48.0,
    elevation_spread_deg: float = 0.0,
) -> Cameras:
    """``count`` cameras evenly spaced in azimuth around +y, ``elevation_deg`` above the xz plane
    (with ``elevation_spread_deg``, the even views that much higher and the odd ones that much
    lower: a ring at two heights), all looking at the origin from ``distance``; the vertical field
    of view is ``fov_y_deg``."""
    if count < 1:
        raise ValueError(f"camera count must be >= 1, got {count}")
    past = height_past_a_pole(elevation_deg, elevation_spread_deg)
    if past is not None:
        raise ValueError(f"camera elevation {past} degrees is not between -90 and 90 "
                         f"(elevation {elevation_deg}, spread {elevation_spread_deg})")
    fy = 0.5 * height / np.tan(0.5 * np.deg2rad(fov_y_deg))
    w2c, k = [], []
    for v in range(count):
        az = 2.0 * np.pi * v / count
        el = np.deg2rad(elevation_deg + (elevation_spread_deg if v % 2 == 0 else -elevation_spread_deg))
        eye = distance * np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
        w2c.append(look_at(eye, np.zeros(3), np.array([0.0, 1.0, 0.0])))
        k.append([fy, fy, 0.5 * width, 0.5 * height])
    return Cameras(np.stack(w2c), np.array(k), width, height)
