"""ICP mapper: localisation and map accuracy on a simulated walk with drifting dead reckoning.

A body walks a gently weaving path across a ``rocks-6cm`` course (``terrain.make_course``); its
height, roll and pitch follow the terrain under its four nominal feet. Captures come from the
robot profile's camera at ``T_base_camera``:

* depth-buffer clouds: :mod:`terrain_perception.raycast` over the course's true height field (a
  perfect range sensor);
* stereo-node clouds: ``terrain_perception.sim.world.render_stereo`` images through the stereo
  pipeline (``terrain_perception.stereo``), when the simulator provides them; the stereo map's
  error is also split by terrain region (:func:`map_error_by_region`: floor, floor near a
  flank, flanks, rock tops) for the default pipeline, Shao's post-processing alone, each
  ``--stereo-variant`` (all from true poses) and the default at our ICP's poses.

Dead reckoning integrates the true body increments with a stride-length error (default +5 %)
and a yaw drift (default 2 deg per metre walked). Methods compared on the same captures:
dead reckoning alone; our mapper (point-to-plane ICP with the configured ``icp_solver``, by
default ``constrained``: the prior kept along unobserved directions in every iteration; Tukey
kernel, guards); the same mapper with ``icp_solver: open3d`` (Open3D's ICP, unobserved
directions reset afterwards: the default until the twenty-ninth session), on the depth and the
stereo clouds; the same mapper with Open3D point-to-point ICP; KISS-ICP (pip ``kiss-icp``,
seeded with the dead-reckoning increment as its motion prediction) when installed.

Timing is wall-clock on this machine with every library's default threading; ``icp_ms`` is the
alignment step (ICP + guards), ``update_ms`` the whole capture (validation, ICP, fusion into both
maps). The table shows wall-clock times; the JSON's ``icp_ms_median`` and ``max_rate_hz = 1000 /
mean(update_ms)`` use process CPU time (all threads summed), because the machine is shared and
wall time measures the other jobs as much as the mapper.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import time
from typing import Dict, List, Optional

import numpy as np

from terrain_perception import mapping as mp
from terrain_perception import raycast as rc
from terrain_perception.camera import PinholeCamera
from terrain_perception.grid import ELEVATION, GridMap, crop_or_pad
from terrain_perception.transforms import invert, make_T, rpy_to_R


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--terrain', default='rocks-6cm', help='course class')
    parser.add_argument('--seed', type=int, default=0, help='course seed')
    parser.add_argument('--robot', default='littledog', help='robot profile')
    parser.add_argument('--path', default='straight', choices=('straight', 'u-turn', 'loop'),
                        help='straight: from the flat approach onto and across the rocks; '
                        'u-turn: 1 m across the rocks, a 0.25 m-radius turn, back; loop: '
                        'circles of 0.3 m radius inside the rough section')
    parser.add_argument('--start-x', type=float, default=None,
                        help='walk start x [m] (the rough section spans x = 1..2 m; default '
                        '-0.45 straight, 0.75 u-turn, 1.5 loop)')
    parser.add_argument('--distance', type=float, default=2.05, help='walk length [m]')
    parser.add_argument('--stereo-max-range', type=float, default=1.5,
                        help='max_range_m of the mapper for stereo clouds [m] (3 cm baseline: '
                        'depth noise grows with range squared; the rocks are in view from the '
                        'start only beyond 1 m)')
    parser.add_argument('--step', type=float, default=None,
                        help='distance between captures [m] (default 0.05, quick 0.1)')
    parser.add_argument('--speed', type=float, default=0.1, help='walking speed [m/s]')
    parser.add_argument('--stride-error', type=float, default=0.05,
                        help='dead-reckoning stride-length error (fraction)')
    parser.add_argument('--yaw-drift', type=float, default=2.0,
                        help='dead-reckoning yaw drift [deg per metre walked]')
    parser.add_argument('--image-scale', type=float, default=None,
                        help='camera resolution factor (default 1.0, quick 0.5)')
    parser.add_argument('--no-alternatives', action='store_true',
                        help='skip the point-to-point and KISS-ICP comparisons')
    parser.add_argument('--no-stereo', action='store_true', help='skip the stereo-cloud run')
    parser.add_argument('--basin', action='store_true',
                        help='instead of the walk: how far off a prior ICP still comes back '
                        'from (the depth clouds of the walk, the coarse model fused at the true '
                        'poses up to each tested capture): from priors offset by 0-15 cm, the '
                        'single ICP from the prior against the mapper\'s relocalisation '
                        '(multi_start_icp: starts on rings around the prior, the config\'s '
                        'relocalise_* parameters); the share of trials within 1 cm of the '
                        'truth')
    parser.add_argument('--basin-stereo', action='store_true',
                        help='--basin on stereo clouds (the simulator\'s rendered pairs through '
                        'the stereo pipeline, as the robot sees) instead of exact depth '
                        '(implies --basin)')
    parser.add_argument('--stereo-variant', action='append', default=[], metavar='NAME=JSON',
                        type=parse_stereo_variant,
                        help='also map the same stereo images through the stereo pipeline '
                        'with these StereoConfig overrides, from the true poses, e.g. '
                        '\'wide={"fattening_radius_px": 7, "fattening_jump_px": 2}\' '
                        '(repeatable): map error by terrain region against the default')


# ------------------------------------------------------------------------------------------
# the walk
# ------------------------------------------------------------------------------------------
#: rows of the stereo map-by-region table that every run has
RESERVED_ROWS = ('default', 'shao', 'default_icp')
#: the 'shao' row's StereoConfig overrides: Shao's post-processing without our fattening guard
SHAO_OVERRIDES = {'fattening_radius_px': 0}


def parse_stereo_variant(text: str):
    """``NAME=JSON`` -> (name, dict of :class:`~terrain_perception.stereo.StereoConfig`
    overrides); the field names are checked against StereoConfig."""
    import json

    from terrain_perception.stereo import StereoConfig
    name, sep, body = text.partition('=')
    name = name.strip()
    if not sep or not name or name in RESERVED_ROWS:
        raise argparse.ArgumentTypeError(
            f'stereo variant {text!r}: expected NAME=JSON with a name other than '
            + ', '.join(f'"{r}"' for r in RESERVED_ROWS) + ' (the rows every run has)')
    try:
        overrides = json.loads(body)
    except json.JSONDecodeError as e:
        raise argparse.ArgumentTypeError(f'stereo variant {name!r}: not JSON ({e})') from None
    if not isinstance(overrides, dict):
        raise argparse.ArgumentTypeError(f'stereo variant {name!r}: JSON must be an object')
    fields = {f.name for f in dataclasses.fields(StereoConfig)}
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise argparse.ArgumentTypeError(
            f'stereo variant {name!r}: not StereoConfig fields: {", ".join(unknown)}')
    return name, overrides


def path_xy_yaw(path: str, start_x: float, distance: float, step: float):
    """Sampled path: ``(x, y, heading)`` arrays every ``step`` metres of arc length.

    ``straight``: along +x from ``start_x`` with a gentle +-6 cm weave. ``u-turn``: 1 m along +x
    at y = -0.25 m from ``start_x``, a 180-degree left turn of radius 0.25 m, and back along -x
    for the rest of ``distance`` (it stays on a 1 m-wide rough section when it starts just
    before it)."""
    s = np.arange(0.0, distance + 1e-9, step)
    if path == 'straight':
        x = start_x + s
        y = 0.06 * np.sin(2 * np.pi * s / 1.2)
        yaw = np.arctan(0.06 * 2 * np.pi / 1.2 * np.cos(2 * np.pi * s / 1.2))
        return x, y, yaw
    if path == 'loop':
        R = 0.3
        th = s / R
        return start_x + R * np.sin(th), -R * np.cos(th), th
    if path != 'u-turn':
        raise ValueError(f'unknown path {path!r} (straight, u-turn, loop)')
    R = 0.25
    arc = np.pi * R
    leg = min(1.0, distance)
    x = np.empty_like(s)
    y = np.empty_like(s)
    yaw = np.empty_like(s)
    a = s <= leg
    x[a], y[a], yaw[a] = start_x + s[a], -R, 0.0
    b = (s > leg) & (s <= leg + arc)
    th = (s[b] - leg) / R
    x[b], y[b], yaw[b] = start_x + leg + R * np.sin(th), -R * np.cos(th), th
    c = s > leg + arc
    x[c], y[c], yaw[c] = start_x + leg - (s[c] - leg - arc), R, np.pi
    return x, y, yaw


def body_poses(course: GridMap, nominal_feet: np.ndarray, standing_height_m: float,
               start_x: float, distance: float, step: float, path: str = 'straight'
               ) -> np.ndarray:
    """True ``T_map_base`` ``(K, 4, 4)`` along a path (:func:`path_xy_yaw`) with a small gait
    yaw wiggle and bob; height, roll and pitch follow a plane through the terrain under the
    four nominal feet."""
    s = np.arange(0.0, distance + 1e-9, step)
    x, y, yaw = path_xy_yaw(path, start_x, distance, step)
    yaw = yaw + 0.03 * np.sin(2 * np.pi * s / 0.35)
    out = np.empty((len(s), 4, 4))
    feet = np.asarray(nominal_feet)[:, :2]
    for k in range(len(s)):
        c, sn = np.cos(yaw[k]), np.sin(yaw[k])
        R2 = np.array([[c, -sn], [sn, c]])
        fw = np.array([x[k], y[k]]) + feet @ R2.T
        hz = rc.interpolate_height(course, fw)
        hz = np.where(np.isfinite(hz), hz, 0.0)
        A = np.c_[np.ones(4), feet]
        a, b, cc = np.linalg.lstsq(A, hz, rcond=None)[0]
        bob = 0.004 * np.sin(2 * np.pi * s[k] / 0.08)
        out[k] = make_T(rpy_to_R(np.arctan(cc), -np.arctan(b), yaw[k]),
                        [x[k], y[k], a + standing_height_m + bob])
    return out


def dead_reckoning(T_true: np.ndarray, stride_error: float, yaw_drift_deg_per_m: float
                   ) -> np.ndarray:
    """Integrate the true body increments with a stride-length error and a yaw drift; starts
    at the true first pose (the map frame is anchored there)."""
    out = np.empty_like(T_true)
    out[0] = T_true[0]
    for k in range(1, len(T_true)):
        d = invert(T_true[k - 1]) @ T_true[k]
        d[:2, 3] *= 1.0 + stride_error
        walked = float(np.linalg.norm(d[:2, 3]))
        d = d @ make_T(rpy_to_R(0.0, 0.0, np.radians(yaw_drift_deg_per_m) * walked))
        out[k] = out[k - 1] @ d
    return out


def scaled_camera(cam: PinholeCamera, scale: float) -> PinholeCamera:
    if scale == 1.0:
        return cam
    w, h = int(round(cam.width * scale)), int(round(cam.height * scale))
    return PinholeCamera(w, h, cam.fx * w / cam.width, cam.fy * h / cam.height,
                         (w - 1) / 2.0, (h - 1) / 2.0)


def pose_errors(T_est: np.ndarray, T_true: np.ndarray) -> Dict[str, float]:
    pos = np.linalg.norm(T_est[:, :3, 3] - T_true[:, :3, 3], axis=1)
    yaw = np.degrees(np.abs(np.angle(np.exp(1j * (
        np.arctan2(T_est[:, 1, 0], T_est[:, 0, 0]) - np.arctan2(T_true[:, 1, 0],
                                                                T_true[:, 0, 0]))))))
    return {'final_m': float(pos[-1]), 'rms_m': float(np.sqrt(np.mean(pos ** 2))),
            'final_yaw_deg': float(yaw[-1]), 'rms_yaw_deg': float(np.sqrt(np.mean(yaw ** 2)))}


def _truth_at_cells(grid: GridMap, course: GridMap) -> np.ndarray:
    """The course's true surface height at ``grid``'s cell centres (NaN off the course)."""
    xs, ys = grid.cell_centers()
    X, Y = np.meshgrid(xs, ys, indexing='ij')
    return rc.interpolate_height(course, np.stack([X, Y], -1))


def map_rmse(grid: GridMap, course: GridMap) -> Dict[str, float]:
    """Height RMSE [m] of observed cells against the true surface at the cell centres, the
    p95 of the absolute error and ``above_5cm``: cells more than 5 cm above the truth (ledges
    that are not there: a planner steps around them, a swing lifts over them)."""
    truth = _truth_at_cells(grid, course)
    h = grid[ELEVATION]
    ok = np.isfinite(h) & np.isfinite(truth)
    if not np.any(ok):
        return {'rmse_m': float('nan'), 'cells': 0, 'p95_abs_m': float('nan')}
    d = h[ok] - truth[ok]
    return {'rmse_m': float(np.sqrt(np.mean(d ** 2))), 'cells': int(ok.sum()),
            'p95_abs_m': float(np.percentile(np.abs(d), 95)),
            'above_5cm': int(np.sum(d > 0.05))}


#: terrain regions of :func:`map_error_by_region`, in print order
REGIONS = ('floor', 'floor_near_flank', 'flank', 'top')


def map_error_by_region(grid: GridMap, course: GridMap, flank_slope_deg: float = 30.0,
                        near_m: float = 0.03, floor_m: float = 0.005,
                        top_m: float = 0.02) -> Dict[str, Dict[str, float]]:
    """Height error of the observed cells by what the true surface is there: ``flank`` (true
    slope above ``flank_slope_deg``), ``floor_near_flank`` (true height under ``floor_m``
    within ``near_m`` of a flank: where stereo's foreground fattening draws rocks wider),
    ``floor`` (the rest of the floor), ``top`` (not a flank, at least ``top_m`` high). Each
    region: ``cells``, ``rmse_m`` and ``mean_m`` (the bias: > 0 drawn too high); an empty
    region has NaN errors. The slope is measured on the truth sampled at the map's cells."""
    from scipy import ndimage

    truth = _truth_at_cells(grid, course)
    h = grid[ELEVATION]
    ok = np.isfinite(h) & np.isfinite(truth)
    gx, gy = np.gradient(np.nan_to_num(truth), grid.resolution_m)
    steep = np.degrees(np.arctan(np.hypot(gx, gy))) > flank_slope_deg
    dist = (ndimage.distance_transform_edt(~steep) * grid.resolution_m if steep.any()
            else np.full(steep.shape, np.inf))       # (the transform needs a flank cell)
    low = truth < floor_m
    masks = {'floor': ok & low & (dist > near_m),
             'floor_near_flank': ok & low & (dist > 0.0) & (dist <= near_m),
             'flank': ok & steep,
             'top': ok & ~steep & (truth >= top_m)}
    out = {}
    for name in REGIONS:
        d = (h - truth)[masks[name]]
        out[name] = {'cells': int(d.size),
                     'rmse_m': float(np.sqrt(np.mean(d ** 2))) if d.size else float('nan'),
                     'mean_m': float(np.mean(d)) if d.size else float('nan')}
    return out


def _region_row(name: str, rm: Dict[str, float], regions: Dict[str, Dict[str, float]]) -> str:
    cols = ' '.join(f'{1e3 * regions[r]["rmse_m"]:7.1f} {1e3 * regions[r]["mean_m"]:+6.1f}'
                    for r in REGIONS)
    return f'{name:<14} {1e3 * rm["rmse_m"]:7.2f} {rm["cells"]:7d} {cols}'


# ------------------------------------------------------------------------------------------
# methods
# ------------------------------------------------------------------------------------------
def run_mapper(config: mp.MapperConfig, T_base_camera: np.ndarray, clouds: List[np.ndarray],
               T_dr: np.ndarray, stamps: np.ndarray,
               focal_baseline_px_m: Optional[float] = None) -> Dict[str, object]:
    """Feed every capture through :class:`IcpMapper`; time the alignment and the update, as
    wall-clock and as process CPU time (all threads; on a shared machine CPU time is what the
    mapper costs, wall time also counts the other jobs). ``focal_baseline_px_m``: the stereo
    noise model (None for the noise-free depth-buffer clouds)."""
    m = mp.IcpMapper(config, T_base_camera, focal_baseline_px_m)
    est = np.empty_like(T_dr)
    icp_ms, upd_ms, icp_cpu, upd_cpu = [], [], [], []
    n_degenerate = np.zeros(len(clouds), int)
    for k, cloud in enumerate(clouds):
        c0, t0 = time.process_time(), time.perf_counter()
        fine, src = m.prepare(cloud)
        c1, t1 = time.process_time(), time.perf_counter()
        u = m.align(src, T_dr[k])
        c2, t2 = time.process_time(), time.perf_counter()
        if u.accepted:
            m.fuse(fine, src, u.T_map_camera, u.T_map_base, float(stamps[k]))
        c3, t3 = time.process_time(), time.perf_counter()
        est[k] = u.T_map_base
        n_degenerate[k] = u.n_degenerate
        if k > 0:  # the first capture has nothing to align to
            icp_ms.append(1e3 * (t2 - t1))
            upd_ms.append(1e3 * (t3 - t0))
            icp_cpu.append(1e3 * (c2 - c1))
            upd_cpu.append(1e3 * (c3 - c0))
    return {'poses': est, 'icp_ms': np.array(icp_ms), 'update_ms': np.array(upd_ms),
            'icp_cpu_ms': np.array(icp_cpu), 'update_cpu_ms': np.array(upd_cpu),
            'counters': dict(m.counters), 'grid': m.fine_grid(), 'mapper': m,
            'n_degenerate': n_degenerate}


def map_at_true_poses(config: mp.MapperConfig, T_base_camera: np.ndarray,
                      clouds: List[np.ndarray], T_true: np.ndarray, stamps: np.ndarray,
                      focal_baseline_px_m: Optional[float] = None) -> GridMap:
    """The fine map fused from the true poses (the map's own error, without localisation)."""
    m = mp.IcpMapper(config, T_base_camera, focal_baseline_px_m)
    for k, cloud in enumerate(clouds):
        fine, src = m.prepare(cloud)
        m.fuse(fine, src, T_true[k] @ T_base_camera, T_true[k], float(stamps[k]))
    return m.fine_grid()


def kiss_available() -> Optional[str]:
    """KISS-ICP's version, or None when it is not installed."""
    try:
        mod = importlib.import_module('kiss_icp')
        importlib.import_module('kiss_icp.kiss_icp')
    except ImportError:
        return None
    try:
        from importlib.metadata import version
        return version('kiss-icp')
    except Exception:  # noqa: BLE001 - metadata lookup only decorates the report
        return getattr(mod, '__version__', 'unknown')


def run_kiss(clouds: List[np.ndarray], T_dr: np.ndarray, T_base_camera: np.ndarray,
             max_range_m: float, voxel_m: float) -> Dict[str, object]:
    """KISS-ICP on the same camera-frame clouds, seeded with the dead-reckoning increment."""
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP
    cfg = KISSConfig()
    cfg.data.max_range = max_range_m
    cfg.data.min_range = 0.05
    cfg.data.deskew = False
    cfg.mapping.voxel_size = voxel_m
    cfg.adaptive_threshold.initial_threshold = 0.05
    cfg.adaptive_threshold.min_motion_th = 0.005
    cfg.registration.max_num_threads = 1
    kiss = KissICP(cfg)
    T_cam_dr = T_dr @ T_base_camera
    T_world_cam0 = T_cam_dr[0]
    est = np.empty_like(T_dr)
    icp_ms = []
    for k, cloud in enumerate(clouds):
        pts = mp.valid_points(cloud, 0.05, max_range_m)
        if k > 0:  # DR prediction of the camera motion, in the first camera's frame
            kiss.last_delta = invert(T_cam_dr[k - 1]) @ T_cam_dr[k]
        t0 = time.perf_counter()
        kiss.register_frame(pts, np.zeros(len(pts)))
        if k > 0:
            icp_ms.append(1e3 * (time.perf_counter() - t0))
        est[k] = T_world_cam0 @ kiss.last_pose @ invert(T_base_camera)
    return {'poses': est, 'icp_ms': np.array(icp_ms), 'update_ms': np.array(icp_ms)}


# ------------------------------------------------------------------------------------------
# stereo captures
# ------------------------------------------------------------------------------------------
def stereo_clouds(course: GridMap, robot, T_true: np.ndarray, camera: PinholeCamera,
                  **overrides) -> Optional[List[List[np.ndarray]]]:
    """Organized clouds from simulated stereo pairs through the stereo pipeline (the default
    config, then each of ``overrides``' StereoConfig changes, e.g. ``shao={'fattening_radius_px':
    0}``, on the same images): one list of clouds per config, or None when the simulator's
    ``render_stereo`` is not available."""
    try:
        world = importlib.import_module('terrain_perception.sim.world')
        stereo = importlib.import_module('terrain_perception.stereo')
    except ImportError:
        return None
    render = getattr(world, 'render_stereo', None)
    if render is None:
        return None
    return _stereo_clouds(world, stereo, course, robot, T_true, camera, overrides)


def _stereo_clouds(world, stereo, course, robot, T_true, camera, overrides):
    import pybullet
    from pybullet_utils.bullet_client import BulletClient
    from terrain_perception.camera import StereoCamera
    pair = StereoCamera(camera, robot.baseline_m)
    # search range covering the nearest ground the camera sees (~0.15 m)
    d_max = camera.fx * robot.baseline_m / 0.15
    cfg = stereo.StereoConfig(num_disparities=int(min(512, 16 * np.ceil(d_max / 16))))
    pipes = [stereo.StereoPipeline(c, pair) for c in
             [cfg] + [dataclasses.replace(cfg, **o) for o in overrides.values()]]
    T_bc = np.asarray(robot.T_base_camera)
    client = BulletClient(connection_mode=pybullet.DIRECT)
    out: List[List[np.ndarray]] = [[] for _ in pipes]
    try:
        world.SimWorld(client, course, texture_seed=int(course.metadata.get('seed', 0)))
        for T in T_true:
            left, right, _ = world.render_stereo(client, T @ T_bc, pair)
            for clouds, pipe in zip(out, pipes):
                clouds.append(pipe.process(left, right, 'rgb').points)
    finally:
        client.disconnect()
    return out


# ------------------------------------------------------------------------------------------
def _row(name: str, e: Dict[str, float], times: Optional[Dict[str, np.ndarray]],
         extra: str = '') -> str:
    if times is None or len(times['icp_ms']) == 0:
        t = f'{"-":>8} {"-":>8} {"-":>8}'
    else:
        rate = 1e3 / float(np.mean(times['update_ms']))
        t = (f'{np.median(times["icp_ms"]):8.1f} {np.mean(times["update_ms"]):8.1f} '
             f'{rate:8.1f}')
    return (f'{name:<26} {e["final_m"] * 1e3:9.1f} {e["rms_m"] * 1e3:9.1f} '
            f'{e["final_yaw_deg"]:8.2f} {e["rms_yaw_deg"]:8.2f} {t} {extra}')


def build_sequence(args: argparse.Namespace) -> Dict[str, object]:
    """The course, robot, camera, true and dead-reckoning poses, depth clouds and mapper
    config of one benchmark walk."""
    from terrain_perception.robot_model import load_robot_model
    from terrain_perception.terrain import make_course

    quick = bool(getattr(args, 'quick', False))
    step = args.step if args.step is not None else (0.1 if quick else 0.05)
    scale = args.image_scale if args.image_scale is not None else (0.5 if quick else 1.0)
    robot = load_robot_model(args.robot)
    course = make_course(args.terrain, args.seed)
    # the simulator puts a flat floor around the course; so does the ray-cast scene
    r = course.resolution_m
    pad = int(round(0.6 / r))
    course = crop_or_pad(course, (course.origin_xy[0] - pad * r, course.origin_xy[1] - pad * r),
                         (course.shape[0] + 2 * pad, course.shape[1] + 2 * pad), fill=0.0)
    cam = scaled_camera(robot.camera, scale)
    T_bc = np.asarray(robot.T_base_camera)
    start_x = args.start_x if args.start_x is not None else \
        {'u-turn': 0.75, 'loop': 1.5}.get(args.path, -0.45)
    T_true = body_poses(course, robot.nominal_feet, robot.standing_height_m, start_x,
                        args.distance, step, args.path)
    scene = rc.HeightFieldScene(course)
    # same angular sampling as the full-size camera: strides scale with the image
    base = mp.MapperConfig()
    config = dataclasses.replace(
        base, coarse_stride_px=max(1, int(round(base.coarse_stride_px * scale))),
        fine_stride_px=max(1, int(round(base.fine_stride_px * scale))))
    return {
        'robot': robot, 'course': course, 'cam': cam, 'T_bc': T_bc, 'T_true': T_true,
        'stamps': np.arange(len(T_true)) * step / args.speed, 'step': step,
        'T_dr': dead_reckoning(T_true, args.stride_error, args.yaw_drift), 'config': config,
        'clouds': [cam.depth_to_points(scene.depth_image(cam, T @ T_bc, max_range_m=2.0))
                   for T in T_true]}


#: --basin: prior offsets [m]
BASIN_OFFSETS = (0.0, 0.03, 0.06, 0.10, 0.15)


def icp_basin(seq: Dict[str, object], offsets=BASIN_OFFSETS, first: int = 8, every: int = 4,
              trials: int = 4, seed: int = 0) -> Dict[str, object]:
    """ICP's basin along a walk: for captures ``first``, ``first + every``, ... the coarse
    model is what the captures before fused at their true poses; from the true camera pose
    shifted ``d`` in a random x-y direction (``trials`` per capture and offset), the
    constrained ICP from that prior, and the mapper's relocalisation
    (:func:`mapping.multi_start_icp`: starts on rings around the prior, the alignment
    :func:`mapping.choose_alignment` keeps). Returns per offset the x-y errors [m] of both,
    their shares within 1 cm, and how often the multi-start left the prior's ICP."""
    import open3d as o3d
    from scipy.spatial import cKDTree
    T_true, T_bc, clouds, cfg = seq['T_true'], seq['T_bc'], seq['clouds'], seq['config']
    m = mp.IcpMapper(cfg, T_bc)
    rng = np.random.default_rng(seed)
    single = {d: [] for d in offsets}
    multi = {d: [] for d in offsets}
    moved = {d: [] for d in offsets}
    for k, cloud in enumerate(clouds):
        fine, src = m.prepare(cloud)
        model = m.coarse_points() if k >= first and (k - first) % every == 0 else np.empty(0)
        if len(model) and len(src):
            normals = m.coarse_normals()
            tree = cKDTree(model)
            pts = np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src))
                             .voxel_down_sample(cfg.coarse_voxel_m).points)
            Tc = T_true[k] @ T_bc
            for d in offsets:
                for _ in range(trials):
                    a = rng.uniform(0.0, 2.0 * np.pi)
                    T0 = Tc.copy()
                    T0[:2, 3] += d * np.array([np.cos(a), np.sin(a)])
                    r0 = mp.constrained_icp(pts, model, normals, tree, T0, cfg)
                    single[d].append(float(np.linalg.norm(r0.T[:2, 3] - Tc[:2, 3])))
                    best, i = mp.multi_start_icp(pts, model, normals, tree, T0, cfg, first=r0)
                    multi[d].append(float(np.linalg.norm(best.T[:2, 3] - Tc[:2, 3])))
                    moved[d].append(i > 0)
        m.fuse(fine, src, T_true[k] @ T_bc, T_true[k], float(seq['stamps'][k]))
    rows = []
    for d in offsets:
        e, em = np.array(single[d]), np.array(multi[d])
        rows.append({'offset_m': float(d), 'trials': int(len(e)),
                     'single_median_m': float(np.median(e)) if len(e) else float('nan'),
                     'single_within_1cm': float(np.mean(e < 0.01)) if len(e) else float('nan'),
                     'multi_median_m': float(np.median(em)) if len(em) else float('nan'),
                     'multi_within_1cm': float(np.mean(em < 0.01)) if len(em) else float('nan'),
                     'multi_moved': float(np.mean(moved[d])) if len(em) else float('nan')})
    return {'rows': rows}


def run_basin(args: argparse.Namespace) -> dict:
    seq = build_sequence(args)
    clouds = 'depth'
    if getattr(args, 'basin_stereo', False):
        got = stereo_clouds(seq['course'], seq['robot'], seq['T_true'], seq['cam'])
        if got is None:
            raise SystemExit('--basin-stereo needs the simulator (pybullet) to render stereo')
        seq['clouds'] = got[0]
        seq['config'] = dataclasses.replace(seq['config'], max_range_m=args.stereo_max_range)
        clouds = 'stereo'
    out = icp_basin(seq)
    cfg = seq['config']
    print(f'ICP basin on {args.terrain} (seed {args.seed}), {args.robot}, {clouds} clouds of '
          f'a {args.distance:.2f} m walk from x = {args.start_x}, model fused at true poses; '
          f'x-y error after ICP from a prior off by the offset (random direction); multi = '
          f'the mapper\'s relocalisation (multi_start_icp: {2 * cfg.relocalise_directions} '
          f'starts on rings of {cfg.relocalise_radius_m * 50:.0f} and '
          f'{cfg.relocalise_radius_m * 100:.0f} cm, choose_alignment); moved = share of '
          f'trials where it left the prior\'s ICP')
    print(f'{"offset":>7} {"trials":>7} {"single median":>14} {"within 1 cm":>12} '
          f'{"multi median":>13} {"within 1 cm":>12} {"moved":>6}')
    flat = {}
    for r in out['rows']:
        print(f'{r["offset_m"] * 100:5.0f} cm {r["trials"]:>7} '
              f'{r["single_median_m"] * 1e3:11.1f} mm {r["single_within_1cm"]:>12.2f} '
              f'{r["multi_median_m"] * 1e3:10.1f} mm {r["multi_within_1cm"]:>12.2f} '
              f'{r["multi_moved"]:>6.2f}')
        key = f'{r["offset_m"] * 100:.0f}cm'
        flat[f'basin_single_within_1cm_{key}'] = r['single_within_1cm']
        flat[f'basin_multi_within_1cm_{key}'] = r['multi_within_1cm']
    return {**flat, 'basin_rows': out['rows'], 'terrain': args.terrain, 'robot': args.robot,
            'clouds': clouds}


def run(args: argparse.Namespace) -> dict:
    if getattr(args, 'basin', False) or getattr(args, 'basin_stereo', False):
        return run_basin(args)
    if args.distance < 2.0:
        print('note: the issue asks for a walk of at least 2 m')
    seq = build_sequence(args)
    robot, course, cam, T_bc = seq['robot'], seq['course'], seq['cam'], seq['T_bc']
    T_true, T_dr, stamps, step = seq['T_true'], seq['T_dr'], seq['stamps'], seq['step']
    config, clouds = seq['config'], seq['clouds']
    walked = float(np.sum(np.linalg.norm(np.diff(T_true[:, :2, 3], axis=0), axis=1)))
    print(f'walk: {walked:.2f} m ({args.path}) on {args.terrain} (seed {args.seed}), '
          f'{len(T_true)} captures '
          f'every {step:.2f} m at {args.speed:.2f} m/s ({args.speed / step:.1f} Hz), camera '
          f'{cam.width}x{cam.height} ({args.robot}), dead reckoning: stride error '
          f'{args.stride_error * 100:.0f} %, yaw drift {args.yaw_drift:.1f} deg/m')

    results: Dict[str, dict] = {}
    e_dr = pose_errors(T_dr, T_true)
    ours = run_mapper(config, T_bc, clouds, T_dr, stamps)
    e_ours = pose_errors(ours['poses'], T_true)
    rm_depth = map_rmse(ours['grid'], course)
    rm_true = map_rmse(map_at_true_poses(config, T_bc, clouds, T_true, stamps), course)
    results['dead_reckoning'] = {'errors': e_dr}
    ours_name = f'ours: {config.icp_solver} p2plane'
    results['ours_point_to_plane'] = {
        'errors': e_ours, 'icp_ms_median': float(np.median(ours['icp_ms'])),
        'update_ms_mean': float(np.mean(ours['update_ms'])), 'counters': ours['counters'],
        'map': rm_depth}

    header = (f'{"method":<26} {"final mm":>9} {"RMS mm":>9} {"yaw deg":>8} {"RMSyaw":>8} '
              f'{"ICP ms":>8} {"upd ms":>8} {"rate Hz":>8}')
    print('\nDepth-buffer clouds')
    print(header)
    print(_row('dead reckoning', e_dr, None))
    print(_row(ours_name, e_ours, ours,
               f'accepted {ours["counters"].get("accepted", 0)}/{len(clouds) - 1}'))
    other = 'open3d' if config.icp_solver != 'open3d' else 'constrained'
    other_name = f'{other} solver p2plane'
    if not args.no_alternatives:
        alt = run_mapper(dataclasses.replace(config, icp_solver=other), T_bc, clouds, T_dr,
                         stamps)
        e_alt = pose_errors(alt['poses'], T_true)
        results[f'{other}_solver'] = {
            'errors': e_alt, 'icp_ms_median': float(np.median(alt['icp_ms'])),
            'icp_cpu_ms_median': float(np.median(alt['icp_cpu_ms'])),
            'counters': alt['counters'], 'map': map_rmse(alt['grid'], course)}
        print(_row(other_name, e_alt, alt,
                   f'accepted {alt["counters"].get("accepted", 0)}/{len(clouds) - 1}'))

    kiss_version = kiss_available()
    if not args.no_alternatives:
        p2p = run_mapper(dataclasses.replace(config, icp_method='point_to_point'), T_bc, clouds,
                         T_dr, stamps)
        e_p2p = pose_errors(p2p['poses'], T_true)
        results['o3d_point_to_point'] = {
            'errors': e_p2p, 'icp_ms_median': float(np.median(p2p['icp_ms'])),
            'counters': p2p['counters'], 'map': map_rmse(p2p['grid'], course)}
        print(_row('o3d point-to-point', e_p2p, p2p,
                   f'accepted {p2p["counters"].get("accepted", 0)}/{len(clouds) - 1}'))
        if kiss_version is None:
            print(f'{"kiss-icp":<26} NOT INSTALLED (pip install kiss-icp) - not measured')
            results['kiss_icp'] = {'installed': False}
        else:
            kiss = run_kiss(clouds, T_dr, T_bc, config.max_range_m, config.coarse_voxel_m)
            e_k = pose_errors(kiss['poses'], T_true)
            results['kiss_icp'] = {'installed': True, 'version': kiss_version, 'errors': e_k,
                                   'icp_ms_median': float(np.median(kiss['icp_ms']))}
            print(_row(f'kiss-icp {kiss_version} (DR-seeded)', e_k, kiss, '(pose only)'))
    print(f'\nfine map (1 cm) height RMSE on observed cells vs truth: '
          f'{rm_depth["rmse_m"] * 1e3:.2f} mm over {rm_depth["cells"]} cells '
          f'(p95 |err| {rm_depth["p95_abs_m"] * 1e3:.2f} mm); from true poses: '
          f'{rm_true["rmse_m"] * 1e3:.2f} mm')
    results['map_at_true_poses'] = rm_true

    rmse_stereo = float('nan')
    if args.no_stereo:
        print('stereo-node clouds: skipped (--no-stereo)')
    else:
        # the same images through Shao's post-processing alone (no fattening guard): the
        # guard's effect on the map, from true poses
        variants = dict(getattr(args, 'stereo_variant', None) or [])
        overrides = {'shao': SHAO_OVERRIDES, **variants}
        every = stereo_clouds(course, robot, T_true, cam, **overrides)
        sclouds, shao_clouds = (None, None) if every is None else every[:2]
        if sclouds is None:
            print('stereo-node clouds: NOT MEASURED (terrain_perception.sim.world.render_stereo '
                  'is not available)')
        else:
            st_cfg = dataclasses.replace(config, max_range_m=args.stereo_max_range)
            fb = cam.fx * robot.baseline_m
            st = run_mapper(st_cfg, T_bc, sclouds, T_dr, stamps, fb)
            e_st = pose_errors(st['poses'], T_true)
            rm_st = map_rmse(st['grid'], course)
            rmse_stereo = rm_st['rmse_m']
            g_st_true = map_at_true_poses(st_cfg, T_bc, sclouds, T_true, stamps, fb)
            g_shao = map_at_true_poses(st_cfg, T_bc, shao_clouds, T_true, stamps, fb)
            rm_st_true, rm_shao = map_rmse(g_st_true, course), map_rmse(g_shao, course)
            results['stereo'] = {'errors': e_st, 'map': rm_st, 'counters': st['counters'],
                                 'map_at_true_poses_no_fattening_guard': rm_shao,
                                 'icp_ms_median': float(np.median(st['icp_ms'])),
                                 'icp_cpu_ms_median': float(np.median(st['icp_cpu_ms'])),
                                 'map_at_true_poses': rm_st_true,
                                 'partial_updates': int(np.sum(st['n_degenerate'] > 0)),
                                 'directions_kept_at_prior': int(np.sum(st['n_degenerate']))}
            print(f'\nStereo-node clouds (max range {args.stereo_max_range:.2f} m)')
            print(header)
            print(_row(ours_name, e_st, st,
                       f'accepted {st["counters"].get("accepted", 0)}/{len(clouds) - 1}'))
            if not args.no_alternatives:
                alt = run_mapper(dataclasses.replace(st_cfg, icp_solver=other), T_bc, sclouds,
                                 T_dr, stamps, fb)
                e_alt = pose_errors(alt['poses'], T_true)
                rm_alt = map_rmse(alt['grid'], course)
                results['stereo'][f'{other}_solver'] = {
                    'errors': e_alt, 'map': rm_alt, 'counters': alt['counters'],
                    'icp_cpu_ms_median': float(np.median(alt['icp_cpu_ms']))}
                print(_row(other_name, e_alt, alt,
                           f'accepted {alt["counters"].get("accepted", 0)}/{len(clouds) - 1}'))
                print(f'fine map height RMSE (stereo), {other} solver: '
                      f'{rm_alt["rmse_m"] * 1e3:.2f} mm over {rm_alt["cells"]} cells')
            print(f'fine map height RMSE (stereo): {rmse_stereo * 1e3:.2f} mm over '
                  f'{rm_st["cells"]} cells; from true poses: '
                  f'{rm_st_true["rmse_m"] * 1e3:.2f} mm (the stereo clouds\' own error)')
            print(f'from true poses, cells > 5 cm above the truth: {rm_st_true["above_5cm"]} '
                  f'with the fattening guard (default), {rm_shao["above_5cm"]} with Shao\'s '
                  f'post-processing alone (RMSE {rm_shao["rmse_m"] * 1e3:.2f} mm over '
                  f'{rm_shao["cells"]} cells; guarded: {rm_st_true["cells"]} cells)')
            print(f'partial updates (x / y / yaw ... kept at the prior where the geometry does '
                  f'not constrain them): {results["stereo"]["partial_updates"]} of '
                  f'{len(sclouds) - 1} captures, '
                  f'{results["stereo"]["directions_kept_at_prior"]} directions in all')
            # the map's error by terrain region, from true poses: the stereo clouds' own
            # error where it matters to footholds (flanks drawn wide, rock tops)
            print('\nStereo map by terrain region (RMSE / mean error [mm]; flank: true '
                  'slope > 30 deg; near flank: floor within 3 cm of one); from true poses, '
                  'except default_icp: the default clouds at our ICP\'s poses')
            print(f'{"stereo config":<14} {"RMSE":>7} {"cells":>7} ' + ' '.join(
                f'{r:>14}' for r in REGIONS))
            grids = {'default': (rm_st_true, g_st_true), 'shao': (rm_shao, g_shao)}
            for name, vclouds in zip(variants, every[2:]):
                g = map_at_true_poses(st_cfg, T_bc, vclouds, T_true, stamps, fb)
                grids[name] = (map_rmse(g, course), g)
            # the same default clouds registered by our ICP from dead reckoning (the map the
            # planner gets): what localisation adds to the stereo clouds' own error
            grids['default_icp'] = (rm_st, st['grid'])
            by_region = {}
            for name, (rm, g) in grids.items():
                regions = map_error_by_region(g, course)
                by_region[name] = {'map': rm, 'regions': regions,
                                   'poses': 'icp' if name == 'default_icp' else 'true',
                                   'overrides': overrides.get(name, {})}
                print(_region_row(name, rm, regions))
            results['stereo']['by_region'] = by_region

    icp_med = float(np.median(ours['icp_cpu_ms']))
    rate = 1e3 / float(np.mean(ours['update_cpu_ms']))
    print(f'\nmapper cost in CPU time (shared machine; wall times above also count other jobs): '
          f'ICP median {icp_med:.1f} ms, update mean {np.mean(ours["update_cpu_ms"]):.1f} ms '
          f'-> {rate:.1f} Hz sustainable')
    figures = {
        'final_err_dr_m': e_dr['final_m'],
        'final_err_icp_m': e_ours['final_m'],
        'yaw_err_icp_deg': e_ours['final_yaw_deg'],
        'map_rmse_depth_m': rm_depth['rmse_m'],
        'map_rmse_stereo_m': rmse_stereo,
        # cells > 5 cm above the truth in the stereo map from true poses, with and without the
        # stereo pipeline's fattening guard (None: no stereo run)
        'map_above_5cm_stereo': results.get('stereo', {}).get('map_at_true_poses', {}).get(
            'above_5cm'),
        'map_above_5cm_stereo_no_guard': results.get('stereo', {}).get(
            'map_at_true_poses_no_fattening_guard', {}).get('above_5cm'),
        'icp_ms_median': icp_med,
        'max_rate_hz': rate,
        'final_err_icp_stereo_m': results.get('stereo', {}).get('errors', {}).get(
            'final_m', float('nan')),
        'yaw_err_icp_stereo_deg': results.get('stereo', {}).get('errors', {}).get(
            'final_yaw_deg', float('nan')),
        'icp_solver': config.icp_solver,
        # the other solver on the same captures (None with --no-alternatives)
        'final_err_icp_other_solver_m': results.get(f'{other}_solver', {}).get(
            'errors', {}).get('final_m'),
        'final_err_icp_stereo_other_solver_m': results.get('stereo', {}).get(
            f'{other}_solver', {}).get('errors', {}).get('final_m'),
        'rms_err_icp_stereo_m': results.get('stereo', {}).get('errors', {}).get('rms_m'),
        'rms_err_icp_stereo_other_solver_m': results.get('stereo', {}).get(
            f'{other}_solver', {}).get('errors', {}).get('rms_m'),
        'map_rmse_stereo_other_solver_m': results.get('stereo', {}).get(
            f'{other}_solver', {}).get('map', {}).get('rmse_m'),
        'partial_updates_depth': int(np.sum(ours['n_degenerate'] > 0)),
        'partial_updates_stereo': results.get('stereo', {}).get('partial_updates', 0),
        # stereo map from true poses by terrain region, per stereo config (default, shao =
        # no fattening guard, then each --stereo-variant); None without a stereo run
        'map_by_region_stereo': results.get('stereo', {}).get('by_region'),
        'details': {
            'walk_m': walked, 'captures': len(T_true), 'camera': [cam.width, cam.height],
            'terrain': args.terrain, 'seed': args.seed, 'step_m': step,
            'stride_error': args.stride_error, 'yaw_drift_deg_per_m': args.yaw_drift,
            'kiss_icp_version': kiss_version, 'methods': results,
            'yaw_err_dr_deg': e_dr['final_yaw_deg'],
            'icp_ms_median_wall': float(np.median(ours['icp_ms'])),
            'update_ms_mean_wall': float(np.mean(ours['update_ms'])),
            'update_ms_mean_cpu': float(np.mean(ours['update_cpu_ms'])),
        },
    }
    ok_final = e_ours['final_m'] <= 0.01 and e_ours['final_m'] <= 0.1 * e_dr['final_m']
    if 'stereo' in results:
        e_s = results['stereo']['errors']['final_m']
        print(f'stereo clouds: final error {e_s * 1e3:.1f} mm vs dead reckoning '
              f'{e_dr["final_m"] * 1e3:.1f} mm ({"better" if e_s < e_dr["final_m"] else "WORSE"}); '
              f'map RMSE <= 1 cm: {"met" if rmse_stereo <= 0.01 else "NOT met"}')
    print(f'\ntargets (depth-buffer clouds): final error <= 1 cm and <= DR/10: '
          f'{"met" if ok_final else "NOT met"}; '
          f'map RMSE (depth) <= 2 mm: {"met" if rm_depth["rmse_m"] <= 0.002 else "NOT met"}; '
          f'ICP < 30 ms median: {"met" if icp_med < 30 else "NOT met"}; '
          f'10 Hz: {"met" if rate >= 10 else "NOT met"}')
    return figures
