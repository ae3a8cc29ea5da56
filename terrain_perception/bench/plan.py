"""Contact patches and footstep planning: speed, saliency statistics, true foothold cost, safety.

``terrain-bench plan [--quick] [--json PATH]``

Patches (paper 003): 640x480 frames (Kinect-like f = 525 px, the paper's sensor) ray cast from the
LittleDog-like robot's camera mount over ``rocks-6cm`` courses (5 mm height maps), with
stereo-like depth noise; the quadruped profile of ``config/footstep_planner.yaml``; n_s = 100.
Reports per-frame time by stage on one core, patches per second, and the statistics of DoN, DoNG,
kappa_min, kappa_max beside paper 003's Table I "auto" rows (curvatures also shown scaled to the
paper's 10 cm patch radius, since the robot's patches are 5x smaller).

Planner (papers 000 / 002): the robot walks each course from the flat approach across the rough
section; at every replan the planner gets a 1.5 m x 1.5 m, 1 cm map around the robot (ground
truth + 1 mm noise per cell, cost from ``features.cost_map``), plans a 4-step horizon and the
first gait period is executed. The same walk is done with the greedy nearest-nominal baseline
(search-area centre, cost and foot-safety filter ignored) and with random reachable footholds.
Footholds are scored on the clean ground truth: the true (Kolter) cost at the foothold, and
"unsafe" when the true terrain under the foot is an edge / crack / knob (heights deviate from
their local plane by more than half a foot radius RMS over a ~4 foot-radius square) or steeper
than 30 deg (friction limit atan(1.2) = 50 deg with margin). The bench reports both patch
rates: whole frame (the paper's ~700/s measure) and the fit stage alone.

Planner on perceived maps (``--perceived-only`` runs just this): the same walks, but each
replan's map is what a perfect range sensor on the camera mount saw so far (one capture where
the body stands at each replan and one half-way through the period before; the approach seen
from 0.15-0.6 m behind the start), filled by the fill node's ``TerrainFiller`` (Fill-Terrain
under the captures' line-of-sight bounds): the foothold cost perception without stereo error
allows, and the share of footholds chosen on never-seen (filled) cells. ``--body-yaw feet``
places the body after each period at the stance feet's heading, as the walking controller does,
instead of the plan's, and the largest heading and sideways drift per seed show what that does.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import yaml

from terrain_perception import features
from terrain_perception import footsteps as fs
from terrain_perception.camera import PinholeCamera
from terrain_perception.config import make_config
from terrain_perception.gait import body_pose_from_feet
from terrain_perception.grid import ELEVATION, GridMap, crop_or_pad
from terrain_perception.patches import (PatchConfig, find_patches, gravity_in_camera,
                                        use_compiled_kernels)
from terrain_perception.robot_model import REPO_ROOT, load_robot_model
from terrain_perception.transforms import R_to_quat, make_T

CONFIG = REPO_ROOT / 'config' / 'footstep_planner.yaml'

# Paper 003, Table I, rows "auto": min, max, med, avg, std.
TABLE1_AUTO = {'DoN (deg)': (0.00, 15.31, 2.83, 3.65, 2.85),
               'DoNG (deg)': (0.00, 34.96, 11.89, 13.40, 8.08),
               'kappa_min (1/m)': (-11.97, 7.64, -0.87, -1.14, 1.75),
               'kappa_max (1/m)': (-7.81, 16.97, 1.01, 1.32, 1.76)}


def add_arguments(parser) -> None:
    parser.add_argument('--course', default='rocks-6cm', help='course class (terrain.py)')
    parser.add_argument('--seeds', type=int, default=None, help='number of course seeds')
    parser.add_argument('--frames', type=int, default=None, help='patch frames per course')
    parser.add_argument('--perceived-only', action='store_true',
                        help='only the planner on perceived + filled maps')
    parser.add_argument('--body-yaw', choices=('plan', 'feet'), default='plan',
                        help="with --perceived-only: the body's heading after each period, "
                             "the plan's or the stance feet's (as the walking controller)")


def load_profile(path: Path = CONFIG):
    """(robot name, PatchConfig, PlannerConfig, CostConfig) of the node's YAML."""
    data = yaml.safe_load(Path(path).read_text())['footstep_planner']['ros__parameters']
    return (data.get('robot', 'littledog'), make_config(PatchConfig, data.get('patches', {})),
            make_config(fs.PlannerConfig, data.get('planner', {})),
            make_config(features.CostConfig, data.get('cost', {})))


def robot_planner_overrides(robot: str) -> dict:
    """The ``planner`` keys of ``config/footstep_planner.ROBOT.yaml`` (the robot's overlay
    of the node's YAML, which the launch profiles load after it), or {} without one."""
    path = CONFIG.with_name(f'footstep_planner.{robot}.yaml')
    if not path.is_file():
        return {}
    data = yaml.safe_load(path.read_text())['footstep_planner']['ros__parameters']
    return dict(data.get('planner', {}))


def _stats(v):
    v = np.asarray(v, dtype=np.float64)
    if v.size == 0:
        return (np.nan,) * 5
    return (float(v.min()), float(v.max()), float(np.median(v)), float(v.mean()), float(v.std()))


def _fmt(row):
    return '  '.join(f'{x:7.2f}' for x in row)


# --------------------------------------------------------------------------------------------
# patches
# --------------------------------------------------------------------------------------------

def _depth_noise(depth, rng):
    """Stereo-like depth noise: sigma = 0.5 mm + 2 mm/m^2 * z^2."""
    return depth + rng.normal(0.0, 1.0, depth.shape) * (0.0005 + 0.002 * depth ** 2)


def bench_patches(courses, robot, cfg: PatchConfig, frames: int, seed: int = 0):
    from terrain_perception.raycast import HeightFieldScene
    cam = PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)
    rng = np.random.default_rng(seed)
    totals, walls = [], []
    compiled = use_compiled_kernels(None)       # (the default: numba kernels when available)
    ref_totals, ref_npatch, ref_same = [], [], 0
    stages, counts = {'stage1_ms': [], 'stage23_ms': [], 'stage4_ms': []}, []
    don, dong, kmin, kmax, npatch = [], [], [], [], []
    for grid in courses:
        scene = HeightFieldScene(grid)
        x0, x1 = grid.metadata['rough_extent_xy'][:2]
        for k in range(frames):
            x = x0 - 0.25 + (x1 - x0) * (k + 0.5) / frames
            yaw = rng.uniform(-0.3, 0.3)
            y = rng.uniform(-0.2, 0.2)
            c, s_ = np.cos(yaw), np.sin(yaw)
            T_base = make_T(np.array([[c, -s_, 0], [s_, c, 0], [0, 0, 1]]),
                            [x, y, robot.standing_height_m + 0.03])
            T_cam = T_base @ robot.T_base_camera
            depth = scene.depth_image(cam, T_cam)
            cloud = cam.depth_to_points(_depth_noise(depth, rng).astype(np.float32))
            q = R_to_quat(T_base[:3, :3] @ robot.T_base_imu[:3, :3])
            R_imu_cam = robot.T_base_imu[:3, :3].T @ robot.T_base_camera[:3, :3]
            g = gravity_in_camera(q, R_imu_cam)
            t, tw = time.process_time(), time.perf_counter()
            p = find_patches(cloud, cam.fx, cam.fy, g, cfg, timing=True)
            totals.append(1e3 * (time.process_time() - t))
            walls.append(1e3 * (time.perf_counter() - tw))
            if compiled:
                # the baseline, alternating frame by frame: the numpy reference steps
                use_compiled_kernels(False)
                try:
                    t = time.process_time()
                    p_ref = find_patches(cloud, cam.fx, cam.fy, g, cfg)
                    ref_totals.append(1e3 * (time.process_time() - t))
                finally:
                    use_compiled_kernels(None)
                ref_npatch.append(len(p_ref))
                ref_same += int(len(p_ref) == len(p) and np.allclose(p_ref.vertex, p.vertex,
                                                                      rtol=1e-9, atol=1e-12))
            for key in stages:
                stages[key].append(p.timings_ms[key])
            counts.append(p.counts)
            npatch.append(len(p))
            don += np.degrees(p.don).tolist()
            dong += np.degrees(p.dong).tolist()
            kmin += p.kx.tolist()
            kmax += p.ky.tolist()
    fitted = np.array([c.get('neighbourhoods', 0) for c in counts])
    st4 = np.array(stages['stage4_ms'])
    if ref_totals:
        ref = {'patch_ms_per_frame_numpy_ref': float(np.median(ref_totals)),
               'patches_per_s_numpy_ref': float(np.sum(ref_npatch) / (np.sum(ref_totals)
                                                                       / 1e3)),
               'numpy_ref_same_patches_frames': int(ref_same)}
    else:
        ref = {}
    out = {**ref,
        'frames': len(totals),
        'patch_ms_per_frame': float(np.median(totals)),
        'patch_ms_per_frame_p90': float(np.percentile(totals, 90)),
        'patch_wall_ms_per_frame': float(np.median(walls)),
        'stage_ms_median': {k: float(np.median(v)) for k, v in stages.items()},
        'patches_per_frame_mean': float(np.mean(npatch)),
        # Whole-frame throughput: accepted patches / total frame CPU time, the paper's measure
        # (~100 patches per 138 ms frame = ~700/s). With n_s seeds a frame yields at most n_s
        # patches, so this is bounded by n_s / (frame time).
        'patches_per_s': float(np.sum(npatch) / (np.sum(totals) / 1e3)),
        # Fit stage only: fitted neighbourhoods / stage IV CPU time (neighbourhood search,
        # paraboloid fit, curvature and residual filters), stages I-III excluded.
        'patches_fitted_per_s_stage4': (float(fitted.sum() / (st4.sum() / 1e3)) if st4.sum()
                                        else 0.0),
        'kept_share': float(np.sum(npatch) / max(fitted.sum(), 1)),
        'stats': {'DoN (deg)': _stats(don), 'DoNG (deg)': _stats(dong),
                  'kappa_min (1/m)': _stats(kmin), 'kappa_max (1/m)': _stats(kmax)},
    }
    return out


# --------------------------------------------------------------------------------------------
# planner
# --------------------------------------------------------------------------------------------

def unsafe_mask(truth: GridMap, foot_radius_m: float) -> np.ndarray:
    """Unsafe cells of the true terrain for a ball foot (:func:`footsteps.unsafe_cells`, 30 deg,
    half a foot radius RMS)."""
    return fs.unsafe_cells(truth[ELEVATION], truth.resolution_m, foot_radius_m)


def _window(course: GridMap, center_xy, size_m=1.5):
    r = course.resolution_m
    n = int(round(size_m / r))
    org = np.asarray(course.origin_xy) + np.round((np.asarray(center_xy) - size_m / 2
                                                   - np.asarray(course.origin_xy)) / r) * r
    return crop_or_pad(course, tuple(org), (n, n))


def _body_xy(robot, feet, yaw):
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s], [s, c]])
    return np.mean(feet[:, :2] - np.array(robot.nominal_feet)[:, :2] @ R.T, axis=0)


class PerceivedMaps:
    """Maps as the robot would have them: the cells a perfect range sensor on LittleDog's camera
    mount saw from every capture so far (``raycast.visible_cells``, 1.5 m range, at their true
    height), filled by the fill node's :class:`~terrain_perception.fill.TerrainFiller`
    (Fill-Terrain under the line-of-sight bounds of those captures; cost from ``cost_cfg``).
    Every cell keeps ``observed`` = seen or not, so the planner can tell fill from sight."""

    def __init__(self, course: GridMap, robot, cost_cfg: features.CostConfig, library):
        from terrain_perception.fill import TerrainFiller
        from terrain_perception.mapping import FineHeightMap
        from terrain_perception.raycast import HeightFieldScene
        self.course, self.robot = course, robot
        self.scene = HeightFieldScene(course, nthreads=1)
        self.fine = FineHeightMap(course.resolution_m, course.shape, course.origin_xy, 'mean')
        self.filler = TerrainFiller(library, course.resolution_m, cost_config=cost_cfg)
        self.poses = []
        self.xs, self.ys = course.cell_centers()

    def capture(self, T_world_base: np.ndarray) -> None:
        from terrain_perception.raycast import visible_cells
        T = T_world_base @ self.robot.T_base_camera
        vis = visible_cells(self.course, T, self.robot.camera, max_range_m=1.5,
                            scene=self.scene)
        ii, jj = np.nonzero(vis)
        if len(ii):
            self.fine.add(np.c_[self.xs[ii], self.ys[jj], self.course[ELEVATION][ii, jj]], 0.0)
            self.poses.append(T)

    def grid(self) -> GridMap:
        return self.filler.update(self.fine.to_grid(stamp_s=float(len(self.poses))),
                                  np.array(self.poses))


def walk_course(course: GridMap, truth_cost: np.ndarray, truth: GridMap, unsafe: np.ndarray,
                robot,
                cfg: fs.PlannerConfig, cost_cfg: features.CostConfig, seed: int,
                max_replans: int = 80, noise_m: float = 0.001,
                perceived: Optional[PerceivedMaps] = None, body_yaw: str = 'plan'):
    """Walk the course with receding-horizon replanning; returns per-foothold records (and
    per period the body's ``yaw_deg`` and ``y``).

    The map of each replan is a 1.5 m window of the course with ``noise_m`` per cell, or with
    ``perceived`` what the robot saw and filled: one capture where the body stands at each
    replan and one half-way through the gait period before it. After each period the body
    stands over the feet at the plan's heading (``body_yaw='plan'``) or, as the walking
    controller places it, at the stance feet's (``'feet'``: hind-feet midpoint to front-feet
    midpoint, ``gait.body_pose_from_feet``)."""
    if body_yaw not in ('plan', 'feet'):
        raise ValueError(f"body_yaw must be 'plan' or 'feet', got {body_yaw!r}")
    rng = np.random.default_rng(seed)
    planner = fs.FootstepPlanner(robot, cfg, cost_cfg)
    x0, x1, _, _ = course.metadata['rough_extent_xy']
    goal = np.array([x1 + 0.3, 0.0])
    T = make_T(np.eye(3), [x0 - 0.25, 0.0, robot.standing_height_m])
    T_prev = None
    feet = None
    next_leg = fs.LH
    rec = {'cost': [], 'unsafe': [], 'rough': [], 'seen': [], 'yaw_deg': [], 'y': [],
           'replan_ms': [],
           'replan_wall_ms': [], 'cost_ms': [],
           'gaits': [], 'failures': 0, 'reached_x': float(T[0, 3])}
    if perceived is not None:           # it walked up the approach: the ground it stands on
        for back in (0.6, 0.45, 0.3, 0.15):
            perceived.capture(make_T(np.eye(3), T[:3, 3] - [back, 0.0, 0.0]))
    for _ in range(max_replans):
        if perceived is not None:
            if T_prev is not None:
                mid = T.copy()
                mid[:3, 3] = 0.5 * (T[:3, 3] + T_prev[:3, 3])
                perceived.capture(mid)
            perceived.capture(T)
            t = time.process_time()
            m = perceived.grid()
            rec['cost_ms'].append(1e3 * (time.process_time() - t))
        else:
            win = _window(course, T[:2, 3])
            seen = win[ELEVATION] + rng.normal(0, noise_m, win.shape).astype(np.float32)
            t = time.process_time()
            cost = features.cost_map(seen, win.resolution_m, cost_cfg)
            rec['cost_ms'].append(1e3 * (time.process_time() - t))
            m = GridMap(win.resolution_m, win.origin_xy, win.shape,
                        {ELEVATION: seen, 'cost': cost})
        t, tw = time.process_time(), time.perf_counter()
        bad = planner.set_map(m)
        plan = bad if bad is not None else planner.plan(T, goal, feet=feet, first_leg=next_leg)
        rec['replan_ms'].append(1e3 * (time.process_time() - t))
        rec['replan_wall_ms'].append(1e3 * (time.perf_counter() - tw))
        if plan.status == fs.STATUS_GOAL_REACHED:
            break
        if not plan.ok:
            rec['failures'] += 1
            rec['failure'] = f'{plan.status_text} at x = {T[0, 3]:.2f} m'
            break
        rec['gaits'].append(plan.gait)
        period = 2 if plan.gait == fs.GAIT_TROT else 4
        steps = [s for s in plan.footsteps if s.step_index < period]
        feet = plan.initial_feet.copy()
        for s in steps:
            feet[s.leg] = s.position
            next_leg = fs.CRAWL_ORDER[(fs.CRAWL_ORDER.index(s.leg) + 1) % 4]
            ij = course.world_to_index(s.position[:2])
            if not course.inside(ij):
                continue
            rec['cost'].append(float(truth_cost[ij[0], ij[1]]))
            ij = truth.world_to_index(s.position[:2])
            rec['unsafe'].append(bool(unsafe[ij[0], ij[1]]) if truth.inside(ij) else False)
            rec['rough'].append(bool(x0 <= s.position[0] <= x1))
            rec['seen'].append(bool(m.sample('observed', s.position[None, :2])[0] > 0.5)
                               if 'observed' in m.layers else True)
        yaw = (plan.yaw if body_yaw == 'plan'
               else float(body_pose_from_feet(feet, robot.standing_height_m)[3]))
        xy = _body_xy(robot, feet, yaw)
        T_prev, T = T, fs.body_pose(xy, feet, yaw, robot)
        rec['yaw_deg'].append(float(np.degrees(yaw)))
        rec['y'].append(float(T[1, 3]))
        rec['reached_x'] = float(T[0, 3])
        if T[0, 3] >= goal[0] - cfg.goal_tolerance_m:
            break
    return rec


def _strategy_walks(courses, truths, robot, cfg, cost_cfg, selection: str, maps=None, **kw):
    """``(config, records)``: :func:`walk_course` on every course with footholds chosen by
    ``selection``; the baselines are terrain-blind (no cost and no foot-safety filter, only
    reach, stability and known cells). ``maps(course)`` makes each walk's
    :class:`PerceivedMaps` (None: ground-truth windows)."""
    c = dataclasses.replace(cfg, selection=selection,
                            max_unevenness=cfg.max_unevenness if selection == 'cost' else 0.0)
    recs = []
    for k, (course, truth) in enumerate(zip(courses, truths)):
        tcost = features.cost_map(course[ELEVATION], course.resolution_m, cost_cfg)
        unsafe = unsafe_mask(truth, robot.foot_radius_m)
        recs.append(walk_course(course, tcost, truth, unsafe, robot, c, cost_cfg, seed=k,
                                perceived=None if maps is None else maps(course), **kw))
    return c, recs


def bench_planner(courses, truths, robot, cfg, cost_cfg):
    out = {}
    for name, sel in (('planner', 'cost'), ('greedy', 'nominal'), ('random', 'random')):
        _, recs = _strategy_walks(courses, truths, robot, cfg, cost_cfg, sel)
        rough = np.concatenate([np.array(r['rough'], bool) for r in recs])
        cost = np.concatenate([np.array(r['cost']) for r in recs])
        unsafe = np.concatenate([np.array(r['unsafe'], bool) for r in recs])
        replan = np.concatenate([np.array(r['replan_ms']) for r in recs])
        replan_wall = np.concatenate([np.array(r['replan_wall_ms']) for r in recs])
        costms = np.concatenate([np.array(r['cost_ms']) for r in recs])
        gaits = np.concatenate([np.array(r['gaits']) for r in recs]) if recs else np.zeros(0)
        out[name] = {
            'footholds_rough': int(rough.sum()),
            'true_cost_mean_rough': float(cost[rough].mean()) if rough.any() else float('nan'),
            'unsafe_share_rough': float(unsafe[rough].mean()) if rough.any() else float('nan'),
            'replan_ms_median': float(np.median(replan)),
            'replan_ms_p90': float(np.percentile(replan, 90)),
            'replan_wall_ms_median': float(np.median(replan_wall)),
            'cost_map_ms_median': float(np.median(costms)),
            'trot_share': float(np.mean(gaits == fs.GAIT_TROT)) if gaits.size else 0.0,
            'failures': int(sum(r['failures'] for r in recs)),
            'crossed': int(sum(r['reached_x'] >= c2.metadata['rough_extent_xy'][1]
                               for r, c2 in zip(recs, courses))),
        }
    return out


def bench_perceived(courses, truths, robot, cfg, cost_cfg, body_yaw: str = 'plan') -> dict:
    """The planner and the terrain-blind greedy baseline on perceived + filled maps
    (:class:`PerceivedMaps`): the foothold cost perfect perception allows; ``body_yaw`` as in
    :func:`walk_course`."""
    from terrain_perception.terrain import library_terrains
    library = [np.asarray(t[ELEVATION], np.float64)
               for t in library_terrains(10, 0, courses[0].resolution_m, 0.06,
                                         cache_dir=REPO_ROOT / 'build' / 'cache'
                                         / 'fill_library')]
    out = {}
    for name, sel in (('planner', 'cost'), ('greedy', 'nominal')):
        _, recs = _strategy_walks(
            courses, truths, robot, cfg, cost_cfg, sel, body_yaw=body_yaw,
            maps=lambda course: PerceivedMaps(course, robot, cost_cfg, library))
        rough = np.concatenate([np.array(r['rough'], bool) for r in recs])
        cost = np.concatenate([np.array(r['cost']) for r in recs])[rough]
        unsafe = np.concatenate([np.array(r['unsafe'], bool) for r in recs])[rough]
        seen = np.concatenate([np.array(r['seen'], bool) for r in recs])[rough]
        max_yaw = [float(np.max(np.abs(r['yaw_deg']))) if r['yaw_deg'] else 0.0 for r in recs]
        max_y = [float(np.max(np.abs(r['y']))) if r['y'] else 0.0 for r in recs]
        nan = float('nan')
        out[name] = {
            'footholds_rough': int(rough.sum()),
            'true_cost_mean_rough': float(cost.mean()) if cost.size else nan,
            'true_cost_median_rough': float(np.median(cost)) if cost.size else nan,
            'unsafe_share_rough': float(unsafe.mean()) if unsafe.size else nan,
            'on_fill_share_rough': float(np.mean(~seen)) if seen.size else nan,
            'max_abs_yaw_deg': max_yaw, 'max_abs_y_m': max_y,
            'failures': int(sum(r['failures'] for r in recs)),
            'crossed': int(sum(r['reached_x'] >= c2.metadata['rough_extent_xy'][1]
                               for r, c2 in zip(recs, courses))),
        }
    return out


def print_perceived(R: dict, n_seeds: int, body_yaw: str = 'plan') -> None:
    print('\n== Footstep planner on perceived + filled maps (perfect range sensor on the camera '
          f'mount, Fill-Terrain in the occlusions; body at the {body_yaw}\'s yaw) ==')
    print('(footholds over the rough sections; "on fill %" = chosen on a never-seen cell; true '
          'cost on the true terrain)')
    print(f'{"strategy":9s} {"footholds":>9s} {"mean":>7s} {"median":>7s} {"on fill %":>9s} '
          f'{"unsafe %":>8s} {"crossed":>8s} {"failed":>6s}')
    for name, r in R.items():
        print(f'{name:9s} {r["footholds_rough"]:9d} {r["true_cost_mean_rough"]:7.4f} '
              f'{r["true_cost_median_rough"]:7.4f} {100 * r["on_fill_share_rough"]:9.1f} '
              f'{100 * r["unsafe_share_rough"]:8.2f} {r["crossed"]:5d}/{n_seeds:<2d} '
              f'{r["failures"]:6d}')
    print(f'true-cost mean ratio planner / greedy = '
          f'{R["planner"]["true_cost_mean_rough"] / R["greedy"]["true_cost_mean_rough"]:.3f}')
    r = R['planner']
    print('planner heading, largest |yaw| per seed [deg]: '
          + ', '.join(f'{v:.1f}' for v in r['max_abs_yaw_deg'])
          + '; largest |y| per seed [m]: ' + ', '.join(f'{v:.3f}' for v in r['max_abs_y_m']))


def run(args) -> dict:
    import cv2
    from terrain_perception.terrain import make_course
    cv2.setNumThreads(1)
    quick = bool(getattr(args, 'quick', False))
    n_seeds = args.seeds or (2 if quick else 5)
    frames = args.frames or (4 if quick else 10)
    robot_name, patch_cfg, plan_cfg, cost_cfg = load_profile()
    robot = load_robot_model(robot_name)
    if args.perceived_only:
        print(f'terrain-bench plan --perceived-only: {args.course} x {n_seeds} seeds, robot '
              f'{robot_name}')
        coarse = [make_course(args.course, s, 0.01) for s in range(n_seeds)]
        fine = [make_course(args.course, s, 0.005) for s in range(n_seeds)]
        R = bench_perceived(coarse, fine, robot, plan_cfg, cost_cfg, args.body_yaw)
        print_perceived(R, n_seeds, args.body_yaw)
        return {'perceived': R, 'body_yaw': args.body_yaw, 'course': args.course,
                'seeds': n_seeds}
    print(f'terrain-bench plan: {args.course} x {n_seeds} seeds, robot {robot_name}, '
          f'{"quick" if quick else "full"} run (cv2 threads 1)')
    fine = [make_course(args.course, s, 0.005) for s in range(n_seeds)]
    coarse = [make_course(args.course, s, 0.01) for s in range(n_seeds)]

    # ---- patches
    P = bench_patches(fine, robot, patch_cfg, frames)
    print('\n== Contact patches (paper 003), 640x480 frames, n_s = '
          f'{patch_cfg.max_seeds}, r = {patch_cfg.patch_radius_m} m ==')
    print(f'frames {P["frames"]}; CPU ms/frame median {P["patch_ms_per_frame"]:.1f} '
          f'(p90 {P["patch_ms_per_frame_p90"]:.1f}, wall {P["patch_wall_ms_per_frame"]:.1f}); '
          'stages (median CPU ms) '
          + ', '.join(f'{k} {v:.1f}' for k, v in P['stage_ms_median'].items()))
    print(f'patches/frame {P["patches_per_frame_mean"]:.1f} (kept {100 * P["kept_share"]:.1f} % '
          f'of fitted); paper: ~700 patches/s, 138 ms/frame on one 2.5 GHz core')
    print(f'patches/s, whole frame (accepted / total frame CPU, the paper\'s measure): '
          f'{P["patches_per_s"]:.0f}; fit stage only (fitted / stage IV CPU): '
          f'{P["patches_fitted_per_s_stage4"]:.0f}')
    if 'patch_ms_per_frame_numpy_ref' in P:
        print(f'baseline, the numpy reference steps (TERRAIN_PATCHES_NUMBA=0) on the same '
              f'frames, alternating: {P["patch_ms_per_frame_numpy_ref"]:.1f} ms/frame, '
              f'{P["patches_per_s_numpy_ref"]:.0f} patches/s; compiled kernels '
              f'{P["patches_per_s"] / P["patches_per_s_numpy_ref"]:.2f}x the throughput; same '
              f'patches on {P["numpy_ref_same_patches_frames"]} of {P["frames"]} frames')
    else:
        print('(numba missing: the numpy reference steps ran; no compiled-kernel figures)')
    print(f'(n_s = {patch_cfg.max_seeds} caps a frame at {patch_cfg.max_seeds} patches: '
          f'7000/s whole-frame would need <= {1e3 * patch_cfg.max_seeds / 7000:.1f} ms/frame)')
    scale = patch_cfg.patch_radius_m / 0.10
    print(f'\n{"measure":18s} {"":6s}    min      max      med      avg      std')
    for key, row in P['stats'].items():
        print(f'{key:18s} {"ours":6s} {_fmt(row)}')
        if key.startswith('kappa'):
            print(f'{"":18s} {"ours*":6s} {_fmt([v * scale for v in row])}')
        print(f'{"":18s} {"auto":6s} {_fmt(TABLE1_AUTO[key])}')
    print(f'(ours* = curvature x r/0.10 m = x{scale:.2f}: the same shapes at the paper\'s patch '
          'size; auto = paper 003 Table I)')

    # ---- planner
    Q = bench_planner(coarse, fine, robot, plan_cfg, cost_cfg)
    print('\n== Footstep planner, 4-step horizon, 1.5 m x 1.5 m map at 1 cm ==')
    print('(footholds, true cost and unsafe share over the rough sections; replan = CPU ms of '
          'set_map + plan, wall in brackets)')
    print(f'{"strategy":9s} {"footholds":>9s} {"true cost":>10s} {"unsafe %":>9s} '
          f'{"replan ms":>10s} {"p90":>6s} {"(wall)":>7s} {"trot %":>7s} {"crossed":>8s} '
          f'{"failed":>7s}')
    for name, r in Q.items():
        print(f'{name:9s} {r["footholds_rough"]:9d} {r["true_cost_mean_rough"]:10.4f} '
              f'{100 * r["unsafe_share_rough"]:9.2f} {r["replan_ms_median"]:10.1f} '
              f'{r["replan_ms_p90"]:6.1f} {r["replan_wall_ms_median"]:7.1f} '
              f'{100 * r["trot_share"]:7.1f} '
              f'{r["crossed"]:5d}/{n_seeds:<2d} {r["failures"]:7d}')
    ratio = Q['planner']['true_cost_mean_rough'] / Q['greedy']['true_cost_mean_rough']
    print(f'true-cost ratio planner / greedy = {ratio:.3f} (target <= 0.5); planner / random = '
          f'{Q["planner"]["true_cost_mean_rough"] / Q["random"]["true_cost_mean_rough"]:.3f}; '
          f'cost map {Q["planner"]["cost_map_ms_median"]:.1f} CPU ms median (features.cost_map, '
          'not in replan time)')
    shares = []
    for f in fine:
        xs = f.cell_centers()[0]
        x0, x1 = f.metadata['rough_extent_xy'][:2]
        shares.append(unsafe_mask(f, robot.foot_radius_m)[(xs >= x0) & (xs <= x1)].mean())
    unsafe_all = float(np.mean(shares))
    print(f'share of unsafe cells in the rough sections: {100 * unsafe_all:.1f} %')
    R = bench_perceived(coarse, fine, robot, plan_cfg, cost_cfg)
    print_perceived(R, n_seeds)
    return {
        'patches_per_s': P['patches_per_s'],
        'patches_fitted_per_s_stage4': P['patches_fitted_per_s_stage4'],
        'patch_stage_ms_median': P['stage_ms_median'],
        'patch_ms_per_frame': P['patch_ms_per_frame'],
        **{k: P[k] for k in ('patch_ms_per_frame_numpy_ref', 'patches_per_s_numpy_ref',
                             'numpy_ref_same_patches_frames') if k in P},
        'replan_ms_median': Q['planner']['replan_ms_median'],
        'true_cost_ratio_vs_greedy': float(ratio),
        'unsafe_foothold_share': Q['planner']['unsafe_share_rough'],
        'patch_stats': P['stats'],
        'planner': Q,
        'unsafe_cell_share_rough': float(unsafe_all),
        'perceived': R,
        'course': args.course, 'seeds': n_seeds, 'frames_per_course': frames,
    }
