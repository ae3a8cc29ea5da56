"""Stereo benchmark: raw StereoBM vs Shao's post-processing vs StereoSGBM, time, ground plane.

``terrain-bench stereo [--quick]`` renders stereo pairs of several terrains from both robot
cameras (``config/robots/littledog.yaml``, ``frog.yaml``) with exact ground-truth disparity from
the depth buffer, and scores, for each method:

* ``bad2``: share of evaluable pixels whose disparity is missing or off by more than 2 px
  (holes count as bad); ``bad2_est``: the same among estimated pixels only; ``coverage``;
* ``height_rmse_m``: RMSE of the height of the method's 3-D points (in the world) against the
  true terrain height at the same x-y.

Evaluable pixels are those with a finite ground truth inside the searched disparity range whose
match lies inside the right image (``u - d >= 0``); no method can do better elsewhere.

It also times the full core pipeline (normalisation + matching + post-processing +
reprojection) against raw ``StereoBM.compute`` on a 640x480 pair with 64 disparities,
single-threaded, in the same run, and scores the RANSAC ground plane's camera pitch against the
simulator's true pitch on scenes with obstacles.

``terrain-bench stereo --left L --right R [--gt D]`` scores any rectified pair from disk
(PNG / PFM / NPY; a PNG ground truth is read as KITTI's uint16 disparity x 256, 0 = none).

Rendering: the synthetic renderer here (:func:`render_pair_raycast`) ray-casts a height map
(``terrain_perception.raycast``) from both cameras and shades every hit by a world-fixed
procedural texture and a Lambertian term, so the two views of a surface point agree exactly and
the ground truth is exact.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import cv2
import numpy as np

from terrain_perception.camera import PinholeCamera, StereoCamera
from terrain_perception.grid import ELEVATION, GridMap
from terrain_perception.ground_plane import (GroundPlaneConfig, camera_pitch_from_pose,
                                             fit_ground_plane)
from terrain_perception.stereo import (StereoConfig, StereoMatcher, StereoPipeline,
                                       disparity_to_points, fixed_to_float, normalise,
                                       postprocess, to_gray)
from terrain_perception.transforms import make_T, rot_y, rot_z, rot_x, transform_points

# ------------------------------------------------------------------------------ scenes


def synthetic_course(kind: str, seed: int = 0, size_xy: Tuple[float, float] = (6.0, 4.0),
                     resolution_m: float = 0.01) -> GridMap:
    """A height map with its flat ground at z = 0 and the region x >= 0 ahead of a robot at
    the origin looking along +x.

    kinds: ``'flat'``, ``'boxes'`` (random 3-20 cm blocks, paper 002's stones), ``'steps'``
    (a staircase of 5-10 cm steps with gaps), ``'rocks'`` (smooth random bumps up to 8 cm).
    """
    rng = np.random.default_rng(seed)
    nx, ny = int(round(size_xy[0] / resolution_m)), int(round(size_xy[1] / resolution_m))
    origin = (-0.5, -size_xy[1] / 2)
    grid = GridMap(resolution_m, origin, (nx, ny), frame_id='map')
    xs, ys = grid.cell_centers()
    X, Y = np.meshgrid(xs, ys, indexing='ij')
    h = np.zeros((nx, ny), np.float32)
    if kind == 'boxes':
        for _ in range(18):
            cx, cy = rng.uniform(0.3, 2.5), rng.uniform(-1.0, 1.0)
            a, b = rng.uniform(0.05, 0.18, 2)
            yaw = rng.uniform(0, np.pi)
            u = (X - cx) * np.cos(yaw) + (Y - cy) * np.sin(yaw)
            v = -(X - cx) * np.sin(yaw) + (Y - cy) * np.cos(yaw)
            box = (np.abs(u) < a / 2) & (np.abs(v) < b / 2)
            h = np.where(box, np.maximum(h, rng.uniform(0.03, 0.20)), h)
    elif kind == 'steps':
        x = 0.6
        level = 0.0
        while x < 3.0:
            run = rng.uniform(0.25, 0.45)
            level += rng.choice([-1, 1]) * rng.uniform(0.05, 0.10) if level > 0.05 \
                else rng.uniform(0.05, 0.10)
            h[(X >= x) & (X < x + run) & (np.abs(Y) < 0.8)] = level
            x += run
    elif kind == 'rocks':
        noise = rng.normal(0, 1, (nx // 10 + 2, ny // 10 + 2)).astype(np.float32)
        bumps = cv2.resize(noise, (ny, nx), interpolation=cv2.INTER_CUBIC)
        bumps = cv2.GaussianBlur(bumps, (0, 0), 4)
        bumps = np.clip(bumps / (np.abs(bumps).max() + 1e-9), 0, None) * 0.08
        h = np.where((X > 0.4) & (X < 2.5) & (np.abs(Y) < 1.0), bumps, 0).astype(np.float32)
    elif kind != 'flat':
        raise ValueError(f'unknown course kind {kind!r} (flat, boxes, steps, rocks)')
    grid[ELEVATION] = h
    grid.metadata['kind'] = kind
    grid.metadata['seed'] = seed
    return grid


class WorldTexture:
    """A world-fixed procedural grey texture: value noise on the xy, xz and yz planes (a fine
    4 mm and a coarse 3 cm octave), so floors and vertical faces are both textured."""

    def __init__(self, seed: int, lo: np.ndarray, hi: np.ndarray,
                 cells_m: Tuple[float, float] = (0.004, 0.03)) -> None:
        rng = np.random.default_rng(seed)
        self.lo = np.asarray(lo, dtype=np.float64)
        self.cells = cells_m
        self.planes = []
        span = np.asarray(hi, dtype=np.float64) - self.lo
        for axes in ((0, 1), (0, 2), (1, 2)):
            octaves = []
            for cell in cells_m:
                shape = tuple(int(np.ceil(span[a] / cell)) + 2 for a in axes)
                tex = cv2.GaussianBlur(rng.normal(0, 1, shape).astype(np.float32), (0, 0), 0.7)
                octaves.append(tex / tex.std())
            self.planes.append((axes, octaves))

    def __call__(self, pts: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Texture value (about zero-mean, unit-scale) at world points ``(H, W, 3)`` with unit
        surface normals ``(H, W, 3)``: each plane's texture is weighted by how squarely the
        surface faces it (triplanar mapping), so a floor shows no stripes from the wall maps."""
        out = np.zeros(pts.shape[:2], np.float32)
        rel = (pts - self.lo).astype(np.float32)
        w = np.abs(normals[..., ::-1]).astype(np.float32) ** 4   # xy <- n_z, xz <- n_y, yz <- n_x
        w /= w.sum(axis=-1, keepdims=True)
        for k, (axes, octaves) in enumerate(self.planes):
            for cell, tex, weight in zip(self.cells, octaves, (1.0, 0.6)):
                # cv2.remap maps (x = column, y = row) = (axes[1], axes[0]).
                mx = np.ascontiguousarray(rel[..., axes[1]] / cell)
                my = np.ascontiguousarray(rel[..., axes[0]] / cell)
                out += w[..., k] * weight * cv2.remap(tex, mx, my, cv2.INTER_LINEAR,
                                                      borderMode=cv2.BORDER_REFLECT)
        return out / 1.17


def _normals(grid: GridMap) -> np.ndarray:
    gx, gy = np.gradient(np.nan_to_num(grid[ELEVATION]).astype(np.float64), grid.resolution_m)
    n = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def render_pair_raycast(grid: GridMap, stereo: StereoCamera, T_world_cam: np.ndarray,
                        seed: int = 0, noise_std: float = 2.0, supersample: int = 2,
                        scene=None, texture: Optional[WorldTexture] = None):
    """Render a rectified grey stereo pair of a height map and its exact left depth.

    Args:
        grid: terrain (``elevation`` layer, z up).
        stereo: the pair; the right camera sits at ``+baseline_m`` along the left camera's x.
        T_world_cam: left camera optical frame in the grid frame.
        seed: texture and noise seed.
        noise_std: sensor noise added to each image [grey levels].
        supersample: rays per pixel side (anti-aliasing of the texture).
        scene, texture: a prebuilt ``HeightFieldScene`` / :class:`WorldTexture` to reuse.

    Returns:
        ``(left, right, depth)``: uint8 ``(H, W)`` images and z-depth [m] (NaN = sky).
    """
    from terrain_perception.raycast import HeightFieldScene
    cam = stereo.left
    s = int(supersample)
    hi_cam = PinholeCamera(cam.width * s, cam.height * s, cam.fx * s, cam.fy * s,
                           (cam.cx + 0.5) * s - 0.5, (cam.cy + 0.5) * s - 0.5)
    if scene is None:
        scene = HeightFieldScene(grid)
    if texture is None:
        h = grid[ELEVATION]
        lo = np.array([*grid.origin_xy, float(np.nanmin(h)) - 0.1])
        hi = np.array([*(np.asarray(grid.origin_xy) + grid.length_xy), float(np.nanmax(h)) + 0.1])
        texture = WorldTexture(seed, lo, hi)
    normals = _normals(grid)
    light = np.array([0.4, 0.3, 1.0]) / np.linalg.norm([0.4, 0.3, 1.0])
    rng = np.random.default_rng(seed + 1)
    images = []
    depth_left = None
    for T in (T_world_cam, T_world_cam @ make_T(t=[stereo.baseline_m, 0.0, 0.0])):
        depth = scene.depth_image(hi_cam, T)
        pts = transform_points(T, hi_cam.depth_to_points(depth).astype(np.float64))
        hit = np.isfinite(depth)
        ij = np.clip(np.floor((pts[..., :2] - np.asarray(grid.origin_xy)) / grid.resolution_m),
                     0, np.array(grid.shape) - 1)
        ij = np.where(hit[..., None], ij, 0).astype(np.int64)
        n = normals[ij[..., 0], ij[..., 1]]
        tex = texture(np.where(hit[..., None], pts, 0.0), n)
        shade = 0.35 + 0.65 * np.clip(n @ light, 0, 1)
        img = np.where(hit, (110.0 + 45.0 * tex) * shade + 20.0, 215.0).astype(np.float32)
        img = cv2.resize(img, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
        img += rng.normal(0, noise_std, img.shape).astype(np.float32)
        images.append(np.clip(np.rint(img), 0, 255).astype(np.uint8))
        if depth_left is None:
            # Exact z-depth of the centre ray of each pixel (not the supersampled average).
            depth_left = scene.depth_image(cam, T)
    return images[0], images[1], depth_left
