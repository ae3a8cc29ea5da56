"""Stereo benchmark: raw StereoBM vs Shao's post-processing vs StereoSGBM, time, ground plane.

``terrain-bench stereo [--quick]`` renders stereo pairs of several terrains from both robot
cameras (``config/robots/littledog.yaml``, ``frog.yaml``) with exact ground-truth disparity from
the depth buffer, and scores, for each method:

* ``bad2``: share of evaluable pixels whose disparity is missing or off by more than 2 px
  (holes count as bad); ``bad2_est``: the same among estimated pixels only; ``coverage``;
* ``height_rmse_m``: RMSE of the height of the method's 3-D points (in the world) against the
  true terrain height at the same x-y;
* ``too_near_est``: share of estimates more than 2 px too large (nearer than the surface: the
  SAD window's foreground fattening at depth edges), ``above_2cm``: share of 3-D points more
  than 2 cm above the true terrain (what a height map fuses as ledges that are not there).

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
import os
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
                                       disparity_to_points, fixed_to_float, floor_disparity_range,
                                       normalise, postprocess, to_gray)
from terrain_perception.transforms import make_T, transform_points

#: Default rays per pixel side of the renderers (``--supersample``). TinyRenderer samples the
#: ground texture without mip-mapping; rendering at 2x and averaging is what a lens and a pixel
#: do. The simulator sizes its texels to the camera (``sim.session.auto_texel_m``), which
#: removes most of the aliasing at 1x, as sim_bridge renders (``--supersample 1``).
SUPERSAMPLE = 2


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


# ------------------------------------------------------------------------------ scoring


def evaluable_mask(gt: np.ndarray, min_disparity: int, num_disparities: int) -> np.ndarray:
    """Pixels a matcher can get right: finite ground truth inside the searched range whose
    match lies inside the right image (``u - d >= 0``)."""
    u = np.arange(gt.shape[1], dtype=np.float32)[None, :]
    with np.errstate(invalid='ignore'):
        return (np.isfinite(gt) & (gt >= min_disparity)
                & (gt < min_disparity + num_disparities) & (u - gt >= 0))


def score_disparity(est: np.ndarray, gt: np.ndarray, mask: np.ndarray,
                    threshold_px: float = 2.0) -> Dict[str, float]:
    """bad-pixel rate with holes counted as bad, bad rate among estimates, and coverage."""
    have = np.isfinite(est) & mask
    with np.errstate(invalid='ignore'):
        wrong = np.abs(est - gt) > threshold_px
    n = max(int(mask.sum()), 1)
    bad_est = int((wrong & have).sum())
    with np.errstate(invalid='ignore'):
        near = int(((est - gt > threshold_px) & have).sum())
    return {'bad2': float((n - have.sum() + bad_est) / n),
            'bad2_est': float(bad_est / max(int(have.sum()), 1)),
            'coverage': float(have.sum() / n),
            # estimates too large: points nearer than the surface, above it in a downward view
            'too_near_est': float(near / max(int(have.sum()), 1))}


def height_errors(points_cam: np.ndarray, T_world_cam: np.ndarray, grid: GridMap) -> np.ndarray:
    """Height [m] of every valid camera-frame point in the world minus the true terrain height
    at the same x-y (points over no terrain are left out)."""
    from terrain_perception.raycast import interpolate_height
    pts = points_cam.reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)].astype(np.float64)
    world = transform_points(T_world_cam, pts)
    err = world[:, 2] - interpolate_height(grid, world[:, :2])
    return err[np.isfinite(err)]


def make_sgbm(num_disparities: int, min_disparity: int = 0, block_size: int = 5):
    """StereoSGBM as a user would configure it (OpenCV's documented P1/P2 rule of thumb)."""
    return cv2.StereoSGBM.create(minDisparity=min_disparity, numDisparities=num_disparities,
                                 blockSize=block_size, P1=8 * block_size ** 2,
                                 P2=32 * block_size ** 2, disp12MaxDiff=1, preFilterCap=63,
                                 uniquenessRatio=10, speckleWindowSize=100, speckleRange=2)


METHODS = ('stereobm_opencv_defaults', 'raw', 'outliers_only', 'filling_only', 'post_shao',
           'post', 'post_fill4', 'sgbm')
METHOD_LABELS = {
    'stereobm_opencv_defaults': 'StereoBM, OpenCV defaults',
    'raw': 'raw StereoBM (our matcher)',
    'outliers_only': '+ row outlier removal',
    'filling_only': '+ area filling',
    'post_shao': '+ both (Shao II-B)',
    'post': '+ both + fattening guard (default)',
    'post_fill4': '+ both + guard, 4 fill passes',
    'sgbm': 'StereoSGBM (reference)',
}


def disparities_of_all_methods(left: np.ndarray, right: np.ndarray,
                               cfg: StereoConfig) -> Dict[str, np.ndarray]:
    """Float disparity [px] (NaN = none) of every method on one grey pair."""
    matcher = StereoMatcher(cfg)
    nl, nr = normalise(left, cfg.normalisation), normalise(right, cfg.normalisation)
    raw = matcher.match(nl, nr)
    plain = cv2.StereoBM.create(cfg.num_disparities, cfg.block_size_px)
    plain.setMinDisparity(cfg.min_disparity)
    shao = replace(cfg, fattening_radius_px=0)      # the paper's steps alone
    out = {
        'stereobm_opencv_defaults': fixed_to_float(plain.compute(left, right), cfg.min_disparity),
        'raw': raw,
        'outliers_only': postprocess(raw, replace(shao, outlier_removal=True,
                                                  area_filling=False)),
        'filling_only': postprocess(raw, replace(shao, outlier_removal=False,
                                                 area_filling=True)),
        'post_shao': postprocess(raw, replace(shao, outlier_removal=True, area_filling=True)),
        'post': postprocess(raw, replace(cfg, outlier_removal=True, area_filling=True)),
        'post_fill4': postprocess(raw, replace(cfg, outlier_removal=True, area_filling=True,
                                               fill_passes=4)),
        'sgbm': fixed_to_float(make_sgbm(cfg.num_disparities, cfg.min_disparity)
                               .compute(left, right), cfg.min_disparity),
    }
    return out


# ------------------------------------------------------------------------------ simulated set


@dataclass
class SceneResult:
    robot: str
    course: str
    seed: int
    scores: Dict[str, Dict[str, float]]
    pitch_err_deg: float
    height_err_m: float
    pitch_err_plain_deg: float


def _course_scene(course: str, seed: int, resolution_m: float) -> Tuple[GridMap, GridMap]:
    """A course from ``terrain_perception.terrain`` and the same course on a 6 m x 4 m floor
    (what the camera sees around the 1-2 m wide course; the simulator draws that floor)."""
    from terrain_perception.grid import crop_or_pad
    from terrain_perception.terrain import make_course
    g = make_course(course, seed, resolution_m=resolution_m)
    ny = int(round(4.0 / resolution_m))
    j0 = int(round((g.origin_xy[1] + 2.0) / resolution_m))
    origin = (g.origin_xy[0] - 1.0, g.origin_xy[1] - j0 * resolution_m)
    out = crop_or_pad(g, origin, (int(round(6.0 / resolution_m)), ny), fill=0.0)
    out.metadata.update(g.metadata)
    return g, out


def _body_pose(rng: np.random.Generator, x: float, height: float) -> np.ndarray:
    from terrain_perception.transforms import rpy_to_R
    rpy = np.radians([rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(-8, 8)])
    return make_T(rpy_to_R(*rpy), [x + rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), height])


ROBOT_VIEWS = {
    # robot: (courses, distance from the body to the rough section's start [m])
    'littledog': (('rocks-6cm', 'rocks-12cm', 'stones-15cm'), 0.25),
    'frog': (('stones-15cm', 'rocks-12cm'), 0.7),
}


#: The --quick subset (one view each; under 2 minutes on a shared 2-core machine).
QUICK_VIEWS = {('littledog', 'rocks-12cm'), ('frog', 'stones-15cm'), ('frog', 'rocks-12cm')}


def run_simulated(quick: bool, renderer: str = 'raycast', views: int = 3,
                  supersample: int = SUPERSAMPLE) -> Tuple[List[SceneResult], tuple]:
    """Render and score every (robot, course, view); seeds 100, 101, ... (the defaults were
    chosen on seeds 1-8). The simulator's ground texel follows its per-robot rule."""
    from terrain_perception.robot_model import load_robot_model
    from terrain_perception.sim.session import auto_texel_m
    results: List[SceneResult] = []
    timing_pair = None
    print(f'rendering with the {renderer} renderer ({supersample}x supersampled)')
    for robot, (courses, lead_m) in ROBOT_VIEWS.items():
        rm = load_robot_model(robot)
        stereo = rm.stereo
        texel = auto_texel_m(rm)
        for course in courses:
            if quick and (robot, course) not in QUICK_VIEWS:
                continue
            for k in range(1 if quick else views):
                seed = 100 + k
                course_grid, grid = _course_scene(course, seed, 0.005)
                rng = np.random.default_rng(seed)
                x0 = float(grid.metadata['rough_extent_xy'][0]) - lead_m
                T = _body_pose(rng, x0, rm.standing_height_m) @ rm.T_base_camera
                nd = floor_disparity_range(stereo, T)
                cfg = StereoConfig(num_disparities=nd)
                left, right, depth = render_pair(renderer, course_grid, grid, stereo, T, seed,
                                                 supersample, texel)
                if timing_pair is None and robot == 'frog':
                    timing_pair = (left, right, stereo)
                gt = stereo.depth_to_disparity(depth)
                mask = evaluable_mask(gt, cfg.min_disparity, nd)
                scores = {}
                for name, d in disparities_of_all_methods(left, right, cfg).items():
                    s = score_disparity(d, gt, mask)
                    pts = disparity_to_points(d, stereo, cfg.max_depth_m)
                    err = height_errors(pts, T, grid)
                    s['height_rmse_m'] = float(np.sqrt(np.mean(err ** 2))) if len(err) else \
                        float('nan')
                    # points floating > 2 cm above the terrain (a height map's phantom ledges)
                    s['above_2cm'] = float(np.mean(err > 0.02)) if len(err) else float('nan')
                    scores[name] = s
                frame = StereoPipeline(cfg, stereo).process(left, right)
                true_pitch = camera_pitch_from_pose(T)
                plane = fit_ground_plane(frame.points, GroundPlaneConfig())
                p_err = np.degrees(plane.pitch_rad - true_pitch)
                h_err = plane.height_m - T[2, 3]
                # The paper's plain RANSAC (no below-penalty), for comparison.
                plain = fit_ground_plane(frame.points, GroundPlaneConfig(below_penalty=0.0))
                p_plain = np.degrees(plain.pitch_rad - true_pitch)
                results.append(SceneResult(robot, course, seed, scores, float(p_err),
                                           float(h_err), float(p_plain)))
                print(f'  {robot:9s} {course:11s} seed {seed}: {nd} disparities, bad2 raw '
                      f'{scores["raw"]["bad2"]:.3f} post {scores["post"]["bad2"]:.3f} sgbm '
                      f'{scores["sgbm"]["bad2"]:.3f}, pitch error {p_err:+.2f} deg')
    return results, timing_pair


def render_pair(renderer: str, course: GridMap, padded: GridMap, stereo: StereoCamera,
                T: np.ndarray, seed: int, supersample: int = SUPERSAMPLE,
                texel_m: Optional[float] = None):
    """``(left, right, depth)`` grey uint8 images and left z-depth [m] of the course seen from
    the left optical frame ``T``: ``'pybullet'`` = the simulator (``terrain_perception.sim.
    world``: textured heightfield + floor, TinyRenderer), ``'raycast'`` = the ray-cast
    renderer of this module over ``padded`` (the course on a flat floor). Both render at
    ``supersample`` x the resolution and average down (anti-aliasing). ``texel_m``: the
    simulator's ground texel [m] (default: its WorldConfig)."""
    if renderer == 'raycast':
        return render_pair_raycast(padded, stereo, T, seed=seed, supersample=supersample)
    if renderer == 'pybullet':
        import pybullet
        from pybullet_utils.bullet_client import BulletClient
        from terrain_perception.sim.world import (SimWorld, WorldConfig, render_camera,
                                                  render_stereo)
        cam, s = stereo.left, int(supersample)
        world_cfg = WorldConfig()
        if texel_m is not None:
            world_cfg = replace(world_cfg, texture_tile_m=texel_m * world_cfg.texture_size_px)
        hi = StereoCamera(PinholeCamera(cam.width * s, cam.height * s, cam.fx * s, cam.fy * s,
                                        (cam.cx + 0.5) * s - 0.5, (cam.cy + 0.5) * s - 0.5),
                          stereo.baseline_m)
        client = BulletClient(connection_mode=pybullet.DIRECT)
        try:
            SimWorld(client, course, world_cfg, texture_seed=seed)
            left, right, _ = render_stereo(client, T, hi)
            # The exact depth of each native pixel's centre ray.
            _, depth = render_camera(client, T, cam, 0.05, 10.0)
        finally:
            client.disconnect()
        left, right = to_gray(left, 'rgb'), to_gray(right, 'rgb')
        if s > 1:
            size = (cam.width, cam.height)
            left = cv2.resize(left, size, interpolation=cv2.INTER_AREA)
            right = cv2.resize(right, size, interpolation=cv2.INTER_AREA)
        return left, right, depth
    raise ValueError(f'unknown renderer {renderer!r}')


# ------------------------------------------------------------------------------ timing


def time_pipeline(left: np.ndarray, right: np.ndarray, stereo: StereoCamera, reps: int,
                  num_disparities: int = 64) -> Dict[str, float]:
    """Single-threaded cost of raw StereoBM and of the full core pipeline [s].

    Times are CPU time of the calling thread (``time.thread_time``; OpenCV runs in it with
    ``cv2.setNumThreads(1)``), medians of interleaved runs: on a machine shared with other jobs
    wall-clock time measures the queue for the cores, not the code. Wall-clock medians are
    reported alongside. ``raw`` is the bare ``StereoBM.compute`` with the pipeline's settings
    (no padding).
    """
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        cfg = StereoConfig(num_disparities=num_disparities)
        pipe = StereoPipeline(cfg, stereo)
        runs = {
            'raw': lambda m=StereoMatcher(replace(cfg, pad_left=False)): m.match_fixed(left,
                                                                                       right),
            'pipeline': lambda: pipe.process(left, right),
        }
        sgbm = make_sgbm(num_disparities)
        cpu: Dict[str, list] = {k: [] for k in list(runs) + ['sgbm']}
        wall: Dict[str, list] = {k: [] for k in cpu}
        for i in range(reps + 2):
            items = list(runs.items()) + ([('sgbm', lambda: sgbm.compute(left, right))]
                                          if i % 4 == 0 else [])
            for name, fn in items:
                w0, c0 = time.perf_counter(), time.thread_time()
                fn()
                c1, w1 = time.thread_time(), time.perf_counter()
                if i >= 2:                   # two warm-up rounds
                    cpu[name].append(c1 - c0)
                    wall[name].append(w1 - w0)
        med = {k: float(np.median(v)) for k, v in cpu.items() if v}
        out = {f'{k}_cpu_s': v for k, v in med.items()}
        out.update({f'{k}_wall_s': float(np.median(v)) for k, v in wall.items() if v})
        out['ratio'] = med['pipeline'] / med['raw']
        out['ratio_wall'] = out['pipeline_wall_s'] / out['raw_wall_s']
        return out
    finally:
        cv2.setNumThreads(threads)


# ------------------------------------------------------------------------------ files


def read_pfm(path: Path) -> np.ndarray:
    """A PFM image (Middlebury disparities) as float32, top row first."""
    with open(path, 'rb') as f:
        kind = f.readline().strip()
        if kind not in (b'Pf', b'PF'):
            raise ValueError(f'{path} is not a PFM file (header {kind!r})')
        dims = f.readline().split()
        while not dims:
            dims = f.readline().split()
        w, h = int(dims[0]), int(dims[1])
        scale = float(f.readline().strip())
        dtype = '<f4' if scale < 0 else '>f4'
        ch = 3 if kind == b'PF' else 1
        data = np.frombuffer(f.read(w * h * ch * 4), dtype=dtype)
    if data.size != w * h * ch:
        raise ValueError(f'{path}: truncated PFM ({data.size} of {w * h * ch} values)')
    img = data.reshape(h, w, ch)[::-1, :, 0] if ch == 3 else data.reshape(h, w)[::-1]
    return np.ascontiguousarray(img, dtype=np.float32)


def read_image(path: Path) -> np.ndarray:
    """A rectified grey image (PNG/any OpenCV format, or NPY) as uint8 ``(H, W)``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f'no such image: {path}')
    if path.suffix.lower() == '.npy':
        img = np.load(path)
    else:
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError(f'OpenCV cannot read {path}')
        if img.ndim == 3:
            img = cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2GRAY)
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    return to_gray(img)


def read_disparity(path: Path) -> np.ndarray:
    """Ground-truth disparity [px], NaN = none: PFM (inf = none), NPY (float; <= 0 or NaN =
    none) or PNG (KITTI: uint16 = disparity x 256, 0 = none)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f'no such ground truth: {path}')
    suffix = path.suffix.lower()
    if suffix == '.pfm':
        d = read_pfm(path)
    elif suffix == '.npy':
        d = np.load(path).astype(np.float32)
    else:
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None or raw.dtype != np.uint16 or raw.ndim != 2:
            raise ValueError(f'{path}: a PNG ground truth must be 16-bit single channel '
                             '(KITTI: disparity x 256, 0 = none)')
        d = raw.astype(np.float32) / 256.0
    return np.where(np.isfinite(d) & (d > 0), d, np.nan).astype(np.float32)


def run_files(args) -> dict:
    left, right = read_image(args.left), read_image(args.right)
    if left.shape != right.shape:
        raise ValueError(f'left is {left.shape}, right is {right.shape}')
    cfg = StereoConfig(num_disparities=args.num_disparities, block_size_px=args.block_size)
    disps = disparities_of_all_methods(left, right, cfg)
    figures: dict = {'pair': {'left': str(args.left), 'right': str(args.right),
                              'size': list(left.shape), 'num_disparities': cfg.num_disparities}}
    if args.gt is not None:
        gt = read_disparity(args.gt)
        if gt.shape != left.shape:
            raise ValueError(f'ground truth is {gt.shape}, images are {left.shape}')
        mask = evaluable_mask(gt, cfg.min_disparity, cfg.num_disparities)
        scores = {m: score_disparity(d, gt, mask) for m, d in disps.items()}
        print(f'{"method":34s} {"bad2":>7s} {"bad2_est":>8s} {"coverage":>8s}')
        for m in METHODS:
            s = scores[m]
            print(f'{METHOD_LABELS[m]:34s} {s["bad2"]:7.3f} {s["bad2_est"]:8.3f} '
                  f'{s["coverage"]:8.3f}')
        figures.update({'bad2_raw': scores['raw']['bad2'], 'bad2_post': scores['post']['bad2'],
                        'bad2_sgbm': scores['sgbm']['bad2'],
                        'coverage_post': scores['post']['coverage'], 'methods': scores})
    else:
        print(f'{"method":30s} {"coverage (no ground truth)":>26s}')
        for m in METHODS:
            print(f'{METHOD_LABELS[m]:34s} {np.isfinite(disps[m]).mean():26.3f}')
        figures['coverage_post'] = float(np.isfinite(disps['post']).mean())
    if args.save_disparity is not None:
        np.save(args.save_disparity, disps['post'])
        print(f'post-processed disparity written to {args.save_disparity}')
    return figures


# ------------------------------------------------------------------------------ entry points


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--left', type=Path, help='left rectified image (PNG/NPY)')
    parser.add_argument('--right', type=Path, help='right rectified image (PNG/NPY)')
    parser.add_argument('--gt', type=Path, default=None,
                        help='ground-truth left disparity (PFM / NPY / KITTI 16-bit PNG)')
    parser.add_argument('--num-disparities', type=int, default=64,
                        help='search range for --left/--right [px], multiple of 16')
    parser.add_argument('--block-size', type=int, default=15,
                        help='SAD window for --left/--right [px], odd')
    parser.add_argument('--save-disparity', type=Path, default=None,
                        help='write the post-processed disparity (NPY) of --left/--right')
    parser.add_argument('--renderer', choices=('auto', 'raycast', 'pybullet'), default='auto',
                        help='simulated set: pybullet (sim world) or the ray-cast renderer')
    parser.add_argument('--supersample', type=int, default=SUPERSAMPLE,
                        help='simulated set: rays per pixel side (1 = as sim_bridge renders)')
    parser.add_argument('--views', type=int, default=3,
                        help='simulated set: views (course seeds) per robot and course')


def _mean(results: List[SceneResult], method: str, key: str) -> float:
    vals = [r.scores[method][key] for r in results]
    return float(np.nanmean(vals)) if vals else float('nan')


def run(args: argparse.Namespace) -> dict:
    if (args.left is None) != (args.right is None):
        raise ValueError('--left and --right go together')
    if args.left is not None:
        return run_files(args)
    renderer = getattr(args, 'renderer', 'auto')
    if renderer == 'auto':
        renderer = default_renderer()
    results, timing_pair = run_simulated(args.quick, renderer, args.views, args.supersample)

    print(f'\nSimulated set: {len(results)} pairs ({", ".join(sorted({r.robot for r in results}))}'
          f'; courses {", ".join(sorted({r.course for r in results}))}), bad2 = share of '
          'evaluable pixels missing or > 2 px off')
    header = (f'{"method":34s} {"bad2":>7s} {"bad2_est":>8s} {"coverage":>8s} {"h_rmse_m":>9s} '
              f'{"too_near":>8s} {"above_2cm":>9s}')
    for robot in sorted({r.robot for r in results}) + ['all']:
        sub = [r for r in results if robot in ('all', r.robot)]
        print(f'\n[{robot}] ({len(sub)} pairs)\n{header}')
        for m in METHODS:
            print(f'{METHOD_LABELS[m]:34s} {_mean(sub, m, "bad2"):7.3f} '
                  f'{_mean(sub, m, "bad2_est"):8.3f} {_mean(sub, m, "coverage"):8.3f} '
                  f'{_mean(sub, m, "height_rmse_m"):9.4f} {_mean(sub, m, "too_near_est"):8.4f} '
                  f'{_mean(sub, m, "above_2cm"):9.4f}')

    pitch = np.abs([r.pitch_err_deg for r in results])
    height = np.abs([r.height_err_m for r in results])
    print(f'\nRANSAC ground plane (defaults of GroundPlaneConfig) vs the true camera pitch:')
    print(f'{"robot":10s} {"course":12s} {"scenes":>6s} {"|pitch err| mean":>16s} '
          f'{"max [deg]":>9s} {"|height err| max [mm]":>21s} {"plain RANSAC max [deg]":>22s}')
    for robot, course in sorted({(r.robot, r.course) for r in results}) + [('all', '')]:
        sub = [r for r in results if robot == 'all' or (r.robot, r.course) == (robot, course)]
        pe = np.abs([r.pitch_err_deg for r in sub])
        he = np.abs([r.height_err_m for r in sub])
        pp = np.abs([r.pitch_err_plain_deg for r in sub])
        print(f'{robot:10s} {course:12s} {len(sub):6d} {pe.mean():16.3f} {pe.max():9.3f} '
              f'{1000 * he.max():21.1f} {pp.max():22.3f}')

    # Timing on the first FROG-I view (640x480) with 64 disparities.
    left, right, stereo = timing_pair
    t = time_pipeline(left, right, stereo, reps=10 if args.quick else 40)
    load = os.getloadavg()[0] if hasattr(os, 'getloadavg') else float('nan')
    print(f'\nTiming, 640x480, 64 disparities, cv2.setNumThreads(1); CPU time of the thread, '
          f'median of interleaved runs (wall-clock in brackets; load average {load:.1f} on '
          f'{os.cpu_count()} cores):')
    for key, label in (('raw', 'raw StereoBM (same settings, no padding)'),
                       ('pipeline', 'full pipeline (checks, normalise, padded match, '
                                    'post-processing, reprojection, coarse)'),
                       ('sgbm', 'StereoSGBM')):
        print(f'  {label:75s} {1000 * t[key + "_cpu_s"]:6.1f} ms  '
              f'[{1000 * t[key + "_wall_s"]:6.1f} ms]')
    print(f'  pipeline / raw StereoBM = {t["ratio"]:.2f}x (wall-clock {t["ratio_wall"]:.2f}x) '
          f'-> {1 / t["pipeline_cpu_s"]:.1f} Hz on one core')

    details = {
        'renderer': renderer,
        'scenes': [{'robot': r.robot, 'course': r.course, 'seed': r.seed,
                    'pitch_err_deg': r.pitch_err_deg, 'height_err_m': r.height_err_m,
                    'pitch_err_plain_ransac_deg': r.pitch_err_plain_deg,
                    'scores': r.scores} for r in results],
        'methods_mean': {m: {k: _mean(results, m, k) for k in
                             ('bad2', 'bad2_est', 'coverage', 'height_rmse_m',
                              'too_near_est', 'above_2cm')}
                         for m in METHODS},
        'timing_s': t,
        'pitch_err_deg_mean': float(pitch.mean()),
        'camera_height_err_m_max': float(height.max()),
    }
    return {
        'bad2_raw': _mean(results, 'raw', 'bad2'),
        'bad2_post': _mean(results, 'post', 'bad2'),
        'bad2_sgbm': _mean(results, 'sgbm', 'bad2'),
        'coverage_post': _mean(results, 'post', 'coverage'),
        'height_rmse_post_m': _mean(results, 'post', 'height_rmse_m'),
        'above_2cm_post': _mean(results, 'post', 'above_2cm'),
        'above_2cm_post_shao': _mean(results, 'post_shao', 'above_2cm'),
        'time_ratio_pipeline_vs_stereobm': t['ratio'],
        'pipeline_hz_640x480': 1.0 / t['pipeline_cpu_s'],
        'pitch_err_deg': float(pitch.max()),
        'details': details,
    }


def default_renderer() -> str:
    """The simulator's pybullet renderer when it exists, else the ray-cast renderer."""
    try:
        from terrain_perception.sim import world  # noqa: F401
    except ImportError:
        return 'raycast'
    return 'pybullet' if hasattr(world, 'render_stereo') else 'raycast'
