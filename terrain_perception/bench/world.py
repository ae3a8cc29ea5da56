"""Terrain generation and the simulated world: generation time, geometric fidelity, render cost.

* Course generation per class (``terrain.make_course`` at 5 mm): wall time, the rough
  section's max height differential and its share of cells above 20 % of that height.
* Heightfield fidelity: pybullet ray casts at the cell centres of a ``rocks-12cm`` course vs
  the GridMap (the simulator's physics surface vs the published ground truth).
* Render fidelity: rendered left z-depth back-projected to the world vs the ray-cast terrain,
  and the pixel shift between the left and right renders (SAD search along the row) vs the
  ground-truth disparity f*B/Z.
* Render cost: milliseconds per stereo pair (TinyRenderer, single process) per robot profile,
  image scale and shadows on/off, from the profile's camera mount at the course start.

JSON keys: ``gen_s_<class>``, ``height_diff_m_<class>``, ``heightfield_max_err_m``,
``depth_surface_err_median_m``, ``disparity_shift_err_median_px``, ``disparity_shift_bias_px``,
``render_ms_<robot>_<W>x<H>_<shadows|noshadows>``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from terrain_perception.grid import ELEVATION

CLASSES = ('rocks-6cm', 'rocks-12cm', 'stones-15cm')


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--seeds', type=int, default=3, help='course seeds per class')


def _generation(seeds: int) -> dict:
    from terrain_perception.terrain import make_course
    out = {}
    print(f'{"class":12s} {"seeds":>5s} {"gen s (mean)":>12s} {"max diff m":>10s} '
          f'{"rough >20%":>10s}')
    for cls in CLASSES:
        times, diffs, cover = [], [], []
        for seed in range(seeds):
            t0 = time.perf_counter()
            g = make_course(cls, seed, 0.005)
            times.append(time.perf_counter() - t0)
            x0, x1, y0, y1 = g.metadata['rough_extent_xy']
            xs, ys = g.cell_centers()
            m = (xs[:, None] > x0) & (xs[:, None] < x1) & (ys[None] > y0) & (ys[None] < y1)
            e = g[ELEVATION][m]
            diffs.append(float(e.max() - e.min()))
            cover.append(float((e > 0.2 * e.max()).mean()))
        out[f'gen_s_{cls}'] = float(np.mean(times))
        out[f'height_diff_m_{cls}'] = float(np.max(diffs))
        print(f'{cls:12s} {seeds:5d} {np.mean(times):12.2f} {np.max(diffs):10.3f} '
              f'{np.mean(cover):10.2f}')
    return out


def _fidelity() -> dict:
    import pybullet
    from pybullet_utils.bullet_client import BulletClient

    from terrain_perception.camera import PinholeCamera, StereoCamera
    from terrain_perception.sim.world import (LightConfig, SimWorld, ground_truth_disparity,
                                              render_stereo)
    from terrain_perception.terrain import make_course
    from terrain_perception.transforms import make_T, rpy_to_R
    course = make_course('rocks-12cm', 0, 0.005)
    client = BulletClient(pybullet.DIRECT)
    try:
        world = SimWorld(client, course)
        xs, ys = course.cell_centers()
        X, Y = np.meshgrid(xs[::2], ys[::2], indexing='ij')
        got = world.ray_heights(np.column_stack([X.ravel(), Y.ravel()]))
        hf_err = float(np.nanmax(np.abs(got - course[ELEVATION][::2, ::2].ravel())))
        cam = PinholeCamera.from_fov(320, 240, 50.0)
        stereo = StereoCamera(cam, 0.05)
        R = rpy_to_R(0.0, np.radians(40.0), 0.0) @ np.array([[0, 0, 1.0], [-1, 0, 0],
                                                            [0, -1, 0]])
        T = make_T(R, [0.75, 0.0, 0.35])
        left, right, depth = render_stereo(client, T, stereo, 0.05, 5.0,
                                           LightConfig(shadow=False))
        pts = cam.depth_to_points(depth).reshape(-1, 3)
        pts = pts[np.isfinite(pts[:, 2])] @ T[:3, :3].T + T[:3, 3]
        surf_err = np.abs(pts[:, 2] - world.ray_heights(pts[:, :2]))
        shift = _shift_errors(left, right, ground_truth_disparity(stereo, depth))
        shift_err = np.abs(shift)
    finally:
        client.disconnect()
    print(f'\nheightfield vs grid (ray casts at {got.size} cell centres): max |err| '
          f'{hf_err * 1e3:.3f} mm')
    print(f'rendered depth vs physics surface ({surf_err.size} px): median '
          f'{np.median(surf_err) * 1e3:.3f} mm, 90 % {np.percentile(surf_err, 90) * 1e3:.3f} mm')
    print(f'left/right pixel shift vs f*B/Z ({shift_err.size} textured px off edges): median '
          f'{np.median(shift_err):.3f} px, mean signed {np.mean(shift):+.3f} px, within 1 px '
          f'{np.mean(shift_err <= 1.0) * 100:.1f} %')
    return {'heightfield_max_err_m': hf_err,
            'depth_surface_err_median_m': float(np.median(surf_err)),
            'disparity_shift_err_median_px': float(np.median(shift_err)),
            'disparity_shift_bias_px': float(np.mean(shift))}


def _shift_errors(left, right, disp, r: int = 3, n: int = 2000) -> np.ndarray:
    """Best sub-pixel SAD shift - ground truth [px] (signed) at random textured, smooth
    pixels."""
    L, R = left.mean(axis=2), right.mean(axis=2)
    H, W = L.shape
    rng = np.random.default_rng(0)
    shifts = np.arange(-3.0, 3.001, 0.05)
    errs = []
    for _ in range(n):
        u, v = int(rng.integers(r + 1, W - r - 1)), int(rng.integers(r, H - r))
        d = disp[v, u]
        win = disp[v - r:v + r + 1, u - r:u + r + 1]
        if not np.isfinite(d) or not np.all(np.isfinite(win)) or np.ptp(win) > 2.0 \
                or u - d - 5 - r < 0:
            continue
        patch = L[v - r:v + r + 1, u - r:u + r + 1]
        if patch.std() < 3.0:
            continue
        cols = u - d + shifts[:, None] + np.arange(-r, r + 1)[None, :]
        c0 = np.floor(cols).astype(int)
        a = cols - c0
        rows = R[v - r:v + r + 1]
        sampled = rows[:, c0] * (1 - a) + rows[:, c0 + 1] * a
        errs.append(shifts[np.argmin(np.abs(sampled - patch[:, None, :]).sum((0, 2)))])
    return np.asarray(errs)


def _render_cost(quick: bool) -> dict:
    from terrain_perception.camera import StereoCamera
    from terrain_perception.sim.session import SimSession, SimSessionConfig, scaled_camera
    from terrain_perception.sim.world import LightConfig, render_stereo
    out = {}
    print(f'\n{"robot":10s} {"course":12s} {"image":>8s} {"shadows":>8s} {"ms/pair":>8s}')
    cases = [('littledog', 'rocks-6cm'), ('frog', 'stones-15cm')]
    for robot, course in cases:
        s = SimSession(SimSessionConfig(robot=robot, course_class=course, settle_s=0.05))
        try:
            T = s.robot.camera_pose()
            for scale in ((1.0,) if quick else (1.0, 0.5)):
                stereo = StereoCamera(scaled_camera(s.model.camera, scale), s.model.baseline_m)
                for shadow in (True, False):
                    ts = []
                    for _ in range(2 if quick else 3):
                        t0 = time.perf_counter()
                        render_stereo(s.client, T, stereo, 0.03, 8.0,
                                      LightConfig(shadow=shadow))
                        ts.append(time.perf_counter() - t0)
                    ms = 1e3 * float(np.median(ts))
                    size = f'{stereo.left.width}x{stereo.left.height}'
                    key = f'render_ms_{robot}_{size}_{"shadows" if shadow else "noshadows"}'
                    out[key] = ms
                    print(f'{robot:10s} {course:12s} {size:>8s} {str(shadow):>8s} {ms:8.0f}')
        finally:
            s.close()
    return out


def run(args: argparse.Namespace) -> dict:
    import cv2
    cv2.setNumThreads(1)
    seeds = 1 if args.quick else max(1, args.seeds)
    figures = _generation(seeds)
    figures.update(_fidelity())
    figures.update(_render_cost(args.quick))
    return figures
