"""Pinhole and rectified-stereo camera models.

Image convention: pixel (u, v) = (column, row), origin at the top-left pixel's centre.
Camera frame: optical (z forward, x right, y down), metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics of an undistorted (rectified) pinhole camera.

    Attributes:
        width, height: image size [px].
        fx, fy: focal lengths [px].
        cx, cy: principal point [px].
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f'camera size must be positive, got {self.width}x{self.height}')
        if not (np.isfinite(self.fx) and np.isfinite(self.fy)) or self.fx <= 0 or self.fy <= 0:
            raise ValueError(f'focal lengths must be positive, got fx={self.fx} fy={self.fy}')

    @classmethod
    def from_fov(cls, width: int, height: int, vertical_fov_deg: float) -> 'PinholeCamera':
        """Square-pixel camera with the principal point at the image centre."""
        f = 0.5 * height / np.tan(np.radians(vertical_fov_deg) / 2.0)
        return cls(width, height, f, f, (width - 1) / 2.0, (height - 1) / 2.0)

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def project(self, pts_cam: np.ndarray) -> np.ndarray:
        """Pixel (u, v) ``(..., 2)`` of camera-frame points ``(..., 3)`` [m]."""
        pts = np.asarray(pts_cam, dtype=np.float64)
        z = pts[..., 2]
        return np.stack([self.fx * pts[..., 0] / z + self.cx,
                         self.fy * pts[..., 1] / z + self.cy], axis=-1)

    def rays(self) -> np.ndarray:
        """Per-pixel ray directions ``(H, W, 3)`` with z = 1."""
        u = (np.arange(self.width) - self.cx) / self.fx
        v = (np.arange(self.height) - self.cy) / self.fy
        uu, vv = np.meshgrid(u, v)
        return np.stack([uu, vv, np.ones_like(uu)], axis=-1)

    def depth_to_points(self, depth: np.ndarray) -> np.ndarray:
        """Organized cloud ``(H, W, 3)`` float32 [m] from a z-depth image [m]; NaN where invalid."""
        depth = np.asarray(depth, dtype=np.float32)
        if depth.shape != (self.height, self.width):
            raise ValueError(f'depth image is {depth.shape}, camera is {self.height}x{self.width}')
        z = np.where(np.isfinite(depth) & (depth > 0), depth, np.nan).astype(np.float32)
        return (self.rays().astype(np.float32) * z[..., None]).astype(np.float32)


@dataclass(frozen=True)
class StereoCamera:
    """A rectified stereo pair: the left camera's intrinsics and the baseline.

    The right camera sits at +baseline_m along the left camera's x axis, same intrinsics,
    so disparity d = u_left - u_right = fx * baseline_m / Z.
    """

    left: PinholeCamera
    baseline_m: float

    def __post_init__(self) -> None:
        if not np.isfinite(self.baseline_m) or self.baseline_m <= 0:
            raise ValueError(f'stereo baseline must be positive, got {self.baseline_m} m')

    def depth_to_disparity(self, depth: np.ndarray) -> np.ndarray:
        """Disparity [px] from z-depth [m]; NaN where depth is invalid."""
        depth = np.asarray(depth, dtype=np.float32)
        with np.errstate(divide='ignore', invalid='ignore'):
            d = self.left.fx * self.baseline_m / depth
        return np.where(np.isfinite(d) & (depth > 0), d, np.nan).astype(np.float32)

    def disparity_to_depth(self, disparity: np.ndarray) -> np.ndarray:
        """z-depth [m] from disparity [px]; NaN where disparity <= 0 or NaN."""
        d = np.asarray(disparity, dtype=np.float32)
        with np.errstate(divide='ignore', invalid='ignore'):
            z = self.left.fx * self.baseline_m / d
        return np.where(np.isfinite(z) & (d > 0), z, np.nan).astype(np.float32)
