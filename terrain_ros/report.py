"""The closed-loop run report: ``summary.json`` and PNG figures from what a run recorded.

:class:`RunData` holds plain arrays (collected live by ``terrain-demo``'s monitor, from whatever
nodes ran); :func:`write_report` turns it into

* ``summary.json``: crossed or not, falls, distance, time, final localisation error, map height
  RMSE on observed cells against the true terrain, mean true cost of the executed (else planned)
  footholds, how far the executed footholds are from where the robot's estimate put them at
  touchdown, capture-to-plan latency, the state of every node, and for each figure and metric
  either its value/file or the reason it is missing (``null`` + ``missing`` entry: never a
  made-up number);
* ``heightmaps.png``: true vs perceived (``/map/fine``) vs filled (``/map/filled``) heights;
* ``footsteps.png``: the cost map with the planned and executed footsteps;
* ``path.png``: the true path against the robot's estimate (dead reckoning re-anchored by ICP),
  the ICP corrections marked where the estimate jumps (paper 000, Fig. 10), and the position
  error over time.

Frames: everything in ``map`` (x along the course, z up), poses as 4x4 ``T_map_base``. Times
are simulated seconds. Nothing here talks ROS: it runs on recorded arrays.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np

from terrain_perception.features import CostConfig, cost_map
from terrain_perception.grid import GridMap
from terrain_ros.timing import CPU_KEY

LEG_NAMES = ('LF', 'RF', 'LH', 'RH')
LEG_COLOURS = ('tab:red', 'tab:green', 'tab:blue', 'tab:orange')


@dataclass
class CourseInfo:
    """Where the run starts and what counts as crossed (x along the course) [m]."""

    name: str
    seed: int
    start_x_m: float
    rough_x0_m: float
    rough_x1_m: float
    finish_x_m: float        # base x at which every foot is past the rough section


@dataclass
class RunData:
    """Everything a report needs; arrays may be empty when a node did not deliver.

    Poses are ``(N, 4, 4)`` with their stamps ``(N,)`` [s sim]. ``plans`` holds one dict per
    received ``/footstep_plan``: ``stamp``, ``t_recv``, ``status``, ``status_text``, ``gait``,
    ``steps`` ``(K, 5)`` = leg, x, y, z, cost. ``joint_t``/``joint_q`` are joint states
    ``(N,)``, ``(N, 4, 3)`` in the robot model's leg order; ``joint_tau`` their efforts (motor
    torques [N m], NaN where a message had none).
    """

    course: CourseInfo
    robot: str
    gt_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    gt_T: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    icp_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    icp_T: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    dr_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    dr_T: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    corr_t: np.ndarray = field(default_factory=lambda: np.zeros(0))     # receipt, sim time
    corr_T: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    joint_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    joint_q: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 3)))
    joint_tau: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 3)))   # or NaN
    plans: List[dict] = field(default_factory=list)
    true_terrain: Optional[GridMap] = None
    map_fine: Optional[GridMap] = None
    map_filled: Optional[GridMap] = None
    latencies_ms: List[float] = field(default_factory=list)
    latency_stages_ms: Dict[str, List[float]] = field(default_factory=dict)
    counts: Dict[str, int] = field(default_factory=dict)
    node_counters: Dict[str, Dict[str, int]] = field(default_factory=dict)
    nodes: Dict[str, dict] = field(default_factory=dict)
    sim_time_s: float = 0.0
    wall_time_s: float = 0.0
    #: the whole machine over the run (:func:`machine_cpu_pct`): busy / stolen by the host [%]
    machine_cpu_pct: Dict[str, float] = field(default_factory=dict)
    end_reason: str = ''
    notes: List[str] = field(default_factory=list)


def cpu_ticks() -> Optional[List[int]]:
    """The machine's aggregate CPU time counters (``/proc/stat``'s ``cpu`` line: user, nice,
    system, idle, iowait, irq, softirq, steal, ...), or None where there is no such file."""
    try:
        with open('/proc/stat') as f:
            return [int(v) for v in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None


def machine_cpu_pct(before: Optional[List[int]], after: Optional[List[int]]) -> Dict[str, float]:
    """Between two :func:`cpu_ticks`: the share of all CPUs' time that was busy (neither idle
    nor waiting for I/O) and the share the hypervisor gave another guest (``steal``: a virtual
    machine's cores run slower by that much) [%]; empty without both."""
    if not before or not after or len(before) < 8 or len(after) < 8:
        return {}
    d = [b - a for a, b in zip(before[:8], after[:8])]
    total = sum(d)
    if total <= 0:
        return {}
    return {'busy': round(100.0 * (total - d[3] - d[4] - d[7]) / total, 1),
            'steal': round(100.0 * d[7] / total, 1)}


# ---------------------------------------------------------------------------------------------
# metrics


def tilt_rad(T: np.ndarray) -> np.ndarray:
    """Angle between the body z axis and the world z axis of poses ``(..., 4, 4)`` [rad]."""
    return np.arccos(np.clip(T[..., 2, 2], -1.0, 1.0))


def body_clearance(T: np.ndarray, terrain: GridMap, body_size_m) -> np.ndarray:
    """Height of the base origin above the highest true terrain under the body footprint [m].

    Samples a 5 x 3 lattice over the body's (length, width) rectangle around each pose."""
    L, W = float(body_size_m[0]), float(body_size_m[1])
    u, v = np.meshgrid(np.linspace(-L / 2, L / 2, 5), np.linspace(-W / 2, W / 2, 3),
                       indexing='ij')
    local = np.stack([u.ravel(), v.ravel(), np.zeros(u.size), np.ones(u.size)], axis=0)
    world = np.einsum('nij,jk->nik', T, local)          # (N, 4, 15)
    h = terrain.sample('elevation', np.moveaxis(world[:, :2, :], 1, 2))   # (N, 15)
    h = np.where(np.isfinite(h), h, 0.0)
    return T[:, 2, 3] - h.max(axis=1)


def fall_mask(T: np.ndarray, terrain: Optional[GridMap], body_size_m,
              max_tilt_rad: float = math.radians(50.0)) -> np.ndarray:
    """True where the robot lies fallen: tilted past ``max_tilt_rad`` or its belly on the
    terrain (base origin less than half the body height + 1 cm above the highest terrain
    under the body)."""
    fallen = tilt_rad(T) > max_tilt_rad
    if terrain is not None and len(T):
        fallen |= body_clearance(T, terrain, body_size_m) < 0.5 * float(body_size_m[2]) + 0.01
    return fallen


def count_falls(t: np.ndarray, fallen: np.ndarray, min_duration_s: float = 0.5) -> int:
    """Number of fallen episodes lasting at least ``min_duration_s``."""
    n, start = 0, None
    for k in range(len(t)):
        if fallen[k] and start is None:
            start = t[k]
        elif not fallen[k] and start is not None:
            n += int(t[k - 1] - start >= min_duration_s)
            start = None
    if start is not None:
        n += int(t[-1] - start >= min_duration_s)
    return n


CROSS_SETTLE_S = 1.0


def crossing_index(t: np.ndarray, x: np.ndarray, fallen: np.ndarray, finish_x: float,
                   settle_s: float = CROSS_SETTLE_S) -> Optional[int]:
    """Index of the sample at which the robot crossed, or None.

    Crossed: the true x reached ``finish_x`` and the robot had not fallen before then nor
    within ``settle_s`` after. A robot that topples over the line (run AB: carried past the
    finish by its fall, tilted 140 deg) has not crossed, even though its first fallen sample
    comes after its first sample past the finish."""
    past = np.nonzero(np.asarray(x) >= finish_x)[0]
    if not len(past):
        return None
    k = int(past[0])
    if np.any(np.asarray(fallen)[np.asarray(t) <= t[k] + settle_s]):
        return None
    return k


def interp_poses(t_src: np.ndarray, T_src: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Nearest-stamp lookup of poses (sources sampled densely enough for evaluation)."""
    if len(t_src) == 0:
        return np.full((len(t), 4, 4), np.nan)
    k = np.clip(np.searchsorted(t_src, t), 1, max(len(t_src) - 1, 1))
    k0 = np.maximum(k - 1, 0)
    k = np.where(np.abs(t_src[np.minimum(k, len(t_src) - 1)] - t)
                 < np.abs(t_src[k0] - t), np.minimum(k, len(t_src) - 1), k0)
    return T_src[k]


def heading_error_rad(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """Signed yaw of estimated minus true poses, (N, 4, 4) each, wrapped to [-pi, pi) [rad]."""
    yaw = lambda T: np.arctan2(T[:, 1, 0], T[:, 0, 0])
    return (yaw(T_est) - yaw(T_true) + np.pi) % (2.0 * np.pi) - np.pi


def estimated_path(d: RunData) -> Tuple[np.ndarray, np.ndarray, str]:
    """The robot's own pose estimate over time: dead reckoning re-anchored by the latest ICP
    correction ``T_map_odom`` (paper 000 Fig. 10), else the ICP poses. Returns (t, T, label)."""
    if len(d.dr_t):
        T = d.dr_T.copy()
        if len(d.corr_t):
            k = np.searchsorted(d.corr_t, d.dr_t, side='right') - 1
            has = k >= 0
            T[has] = np.einsum('nij,njk->nik', d.corr_T[k[has]], d.dr_T[has])
        label = ('dead reckoning + ICP corrections' if len(d.corr_t)
                 else 'dead reckoning (no ICP correction received)')
        return d.dr_t, T, label
    if len(d.icp_t):
        return d.icp_t, d.icp_T, 'ICP pose'
    return np.zeros(0), np.zeros((0, 4, 4)), ''


def sample_cell_mean(terrain: GridMap, grid: GridMap, layer: str = 'elevation',
                     T_world_grid: Optional[np.ndarray] = None) -> np.ndarray:
    """Mean of ``terrain`` over each cell of ``grid`` (4 x 4 sub-samples per cell), (nx, ny).
    With ``T_world_grid`` (4x4, or one per cell ``(nx, ny, 4, 4)``) the sub-sample points are
    moved by its x-y part (rotation and translation) before sampling: the grid is in a frame
    that is off the terrain's."""
    xs, ys = grid.cell_centers()
    offs = (np.arange(4) + 0.5) / 4.0 - 0.5
    acc = np.zeros(grid.shape, np.float64)
    for ox in offs:
        for oy in offs:
            xy = np.stack(np.meshgrid(xs + ox * grid.resolution_m, ys + oy * grid.resolution_m,
                                      indexing='ij'), axis=-1)
            if T_world_grid is not None:
                T = np.asarray(T_world_grid)
                xy = np.einsum('...ij,...j->...i', T[..., :2, :2], xy) + T[..., :2, 3]
            acc += terrain.sample(layer, xy)
    return (acc / offs.size ** 2).astype(np.float32)


def observed_mask(grid: GridMap) -> np.ndarray:
    """Cells measured by a sensor: the ``observed`` layer when present, else finite heights."""
    elev = grid['elevation']
    if 'observed' in grid.layers:
        return (grid['observed'] > 0.5) & np.isfinite(elev)
    return np.isfinite(elev)


def map_errors(grid: GridMap, terrain: GridMap, mask: np.ndarray,
               T_world_grid: Optional[np.ndarray] = None) -> np.ndarray:
    """Height errors [m] (map - truth) of ``grid``'s elevation on ``mask`` cells that lie on
    the true terrain. ``T_world_grid`` (see :func:`estimate_offsets`) compares each cell with
    the terrain where the robot's pose error puts it (the map registered to the world by the
    robot's own estimate error) instead of at the same coordinates; one per cell
    ``(nx, ny, 4, 4)`` (:func:`cell_offsets`) uses each cell's own."""
    h = grid['elevation']
    truth = sample_cell_mean(terrain, grid, T_world_grid=T_world_grid)
    if T_world_grid is not None:
        xs, ys = grid.cell_centers()
        X, Y = np.meshgrid(xs, ys, indexing='ij')
        r = np.moveaxis(np.asarray(T_world_grid)[..., 2, :], -1, 0)
        h = r[0] * X + r[1] * Y + r[2] * h + r[3]
    ok = mask & np.isfinite(truth) & np.isfinite(h)
    return (h[ok] - truth[ok]).astype(np.float64)


def map_rmse(grid: GridMap, terrain: GridMap, mask: np.ndarray,
             T_world_grid: Optional[np.ndarray] = None) -> Tuple[float, int]:
    """Height RMSE [m] of ``grid``'s elevation against the true terrain on ``mask`` cells
    (``T_world_grid``: see :func:`map_errors`)."""
    err = map_errors(grid, terrain, mask, T_world_grid)
    if err.size == 0:
        return float('nan'), 0
    return float(np.sqrt(np.mean(err ** 2))), int(err.size)


def _transform_each(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``(n, 3)``: each point ``p[k]`` moved by its own transform ``T[k]`` (``(n, 4, 4)``)."""
    return np.einsum('nij,nj->ni', T[:, :3, :3], p) + T[:, :3, 3]


def estimate_offsets(d: RunData, t: np.ndarray) -> np.ndarray:
    """``(n, 4, 4)`` = ``T_true T_est^-1`` at stamps ``t``: the robot's estimate error as a
    map-to-world transform (NaN where a pose is missing). A foot the robot puts at ``p`` in its
    map lands at ``C p`` in the world, and a map cell at ``p`` built with about the same error
    shows the terrain at ``C p``; so a foothold's true cost is read at ``C p`` (the map's
    misregistration, bounded on its own as the localisation error, does not count twice)."""
    t = np.atleast_1d(np.asarray(t, dtype=float))
    te, Te, _ = estimated_path(d)
    if not len(te) or not len(d.gt_t):
        return np.full((len(t), 4, 4), np.nan)
    return np.einsum('nij,njk->nik', interp_poses(d.gt_t, d.gt_T, t),
                     np.linalg.inv(interp_poses(te, Te, t)))


def drift_windows(d: RunData, window_s: float = 10.0) -> List[dict]:
    """Where the robot's position estimate (:func:`estimated_path`) gains its error, window by
    window of ``window_s`` simulated seconds over the ground truth's span.

    The error ``e = p_est - p_true`` is split in the true heading's frame (``along`` the body's
    x, ``across`` it) at each window's end, and its change over the window into what dead
    reckoning added with the ICP correction held at the window's start (``dr_*``: the odometry's
    displacement turned by that correction minus the true displacement) and what the
    corrections received within the window added (``icp_*``: the rest). ``dr_scale`` is the
    odometry's displacement over the true one across the window (1 = exact; > 1 overstates;
    None when the body moved less than 1 mm).
    Rows: ``t0``, ``t1`` [s], ``x`` [m] (true, at ``t1``), ``err_along``, ``err_across``,
    ``err_z`` [m], ``yaw_err_deg``, ``dr_along``, ``dr_across``, ``icp_along``, ``icp_across``
    [m], ``dr_scale``, ``corrections`` (received in the window). Empty without ground truth or
    dead reckoning. Raises ValueError for a window that is not positive and finite."""
    if not (math.isfinite(window_s) and window_s > 0.0):
        raise ValueError(f'window_s must be positive and finite, got {window_s!r}')
    if not len(d.gt_t) or not len(d.dr_t):
        return []
    te, Te, _ = estimated_path(d)
    edges = np.arange(max(d.gt_t[0], d.dr_t[0]), min(d.gt_t[-1], d.dr_t[-1]) + 1e-9, window_s)
    if len(edges) < 2:
        return []
    G = interp_poses(d.gt_t, d.gt_T, edges)
    E = interp_poses(te, Te, edges)
    D = interp_poses(d.dr_t, d.dr_T, edges)
    # the correction in force at each window's start (identity before the first)
    R0 = np.tile(np.eye(3), (len(edges), 1, 1))
    if len(d.corr_t):
        k = np.searchsorted(d.corr_t, edges, side='right') - 1
        R0[k >= 0] = d.corr_T[k[k >= 0], :3, :3]

    rows = []
    for i in range(1, len(edges)):
        t0, t1 = float(edges[i - 1]), float(edges[i])
        yaw = math.atan2(G[i, 1, 0], G[i, 0, 0])
        fwd = np.array([math.cos(yaw), math.sin(yaw)])
        left = np.array([-fwd[1], fwd[0]])
        e0 = E[i - 1, :3, 3] - G[i - 1, :3, 3]
        e1 = E[i, :3, 3] - G[i, :3, 3]
        dr = R0[i - 1] @ (D[i, :3, 3] - D[i - 1, :3, 3]) - (G[i, :3, 3] - G[i - 1, :3, 3])
        icp = (e1 - e0) - dr
        true_len = float(np.linalg.norm(G[i, :2, 3] - G[i - 1, :2, 3]))
        n_corr = int(np.sum((d.corr_t > t0) & (d.corr_t <= t1))) if len(d.corr_t) else 0
        rows.append({
            't0': t0, 't1': t1, 'x': float(G[i, 0, 3]),
            'err_along': float(e1[:2] @ fwd), 'err_across': float(e1[:2] @ left),
            'err_z': float(e1[2]),
            'yaw_err_deg': float(np.degrees(heading_error_rad(E[i:i + 1], G[i:i + 1])[0])),
            'dr_along': float(dr[:2] @ fwd), 'dr_across': float(dr[:2] @ left),
            'icp_along': float(icp[:2] @ fwd), 'icp_across': float(icp[:2] @ left),
            'dr_scale': (float(np.linalg.norm(D[i, :2, 3] - D[i - 1, :2, 3])) / true_len
                         if true_len > 1e-3 else None),
            'corrections': n_corr})
    return rows


def cell_offsets(d: RunData, grid: GridMap, mask: np.ndarray) -> np.ndarray:
    """``(nx, ny, 4, 4)``: for each ``mask`` cell of ``grid``, the estimate error
    (:func:`estimate_offsets`) at the stamp the cell was last seen (layer ``last_seen``): its
    height was placed through the pose estimate of its captures, whose error drifts during a
    walk, so one pose's error (the last ICP pose's, say, tilted by a few tenths of a degree)
    misregisters the cells seen at other times. Identity elsewhere and where no pose is known.
    Raises ValueError if the grid has no ``last_seen`` layer."""
    if 'last_seen' not in grid.layers:
        raise ValueError(f"the grid has no 'last_seen' layer (layers: {sorted(grid.layers)})")
    out = np.broadcast_to(np.eye(4), grid.shape + (4, 4)).copy()
    stamps = np.asarray(grid['last_seen'], np.float64)
    sel = np.asarray(mask, bool) & np.isfinite(stamps)
    if sel.any():
        C = estimate_offsets(d, stamps[sel])
        good = np.all(np.isfinite(C), axis=(1, 2))
        ii, jj = np.nonzero(sel)
        out[ii[good], jj[good]] = C[good]
    return out


def landing_positions(d: RunData, stamps: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """``(n, 3)`` world positions where points ``xyz`` the robot aims at in its map frame at
    ``stamps`` really are (:func:`estimate_offsets`)."""
    C = estimate_offsets(d, stamps)
    p = np.asarray(xyz, dtype=float)
    return _transform_each(C, p)


def true_cost_grid(terrain: GridMap, cost_cfg: CostConfig) -> GridMap:
    """The foothold cost computed on the true terrain (same function as the fill node)."""
    out = GridMap(terrain.resolution_m, terrain.origin_xy, terrain.shape,
                  {'elevation': terrain['elevation']})
    out['cost'] = cost_map(terrain['elevation'], terrain.resolution_m, cost_cfg)
    return out


def executed_footholds(joint_t: np.ndarray, joint_q: np.ndarray, gt_t: np.ndarray,
                       gt_T: np.ndarray, model, speed_mps: float = 0.03,
                       min_stance_s: float = 0.15, min_move_m: float = 0.01,
                       return_index: bool = False):
    """Where the feet actually stood: ``(K, 4)`` = leg, x, y, z (contact point, ``map``) [m];
    with ``return_index`` also the joint-state index of each foothold's touchdown ``(K,)``.

    Foot centres from forward kinematics on the joint states and the true base pose; a stance
    is a run of samples with the foot slower than ``speed_mps`` lasting ``min_stance_s``; a new
    foothold is counted when the stance position moved ``min_move_m`` from the leg's last one
    (the initial stance is not a foothold of the run).
    """
    from terrain_perception.kinematics import forward
    if len(joint_t) < 3 or len(gt_t) < 3:
        return (np.zeros((0, 4)), np.zeros(0, int)) if return_index else np.zeros((0, 4))
    T = interp_poses(gt_t, gt_T, joint_t)
    feet_b = forward(model, joint_q)                               # (N, 4, 3)
    feet = np.einsum('nij,nkj->nki', T[:, :3, :3], feet_b) + T[:, None, :3, 3]
    dt = np.gradient(joint_t)
    dt = np.where(dt > 1e-6, dt, 1e-6)
    speed = np.linalg.norm(np.gradient(feet, axis=0), axis=-1) / dt[:, None]   # (N, 4)
    out, index = [], []
    for leg in range(4):
        still = speed[:, leg] < speed_mps
        last = None
        k = 0
        n = len(joint_t)
        while k < n:
            if not still[k]:
                k += 1
                continue
            j = k
            while j + 1 < n and still[j + 1]:
                j += 1
            if joint_t[j] - joint_t[k] >= min_stance_s:
                p = np.median(feet[k:j + 1, leg], axis=0)
                p[2] -= model.foot_radius_m
                if last is None:
                    last = p          # the initial stance: where the foot was, not a step
                elif np.linalg.norm(p[:2] - last[:2]) >= min_move_m:
                    out.append([leg, *p])
                    index.append(k)
                    last = p
            k = j + 1
    out = np.asarray(out, dtype=np.float64).reshape(-1, 4)
    return (out, np.asarray(index, dtype=int)) if return_index else out


def foothold_belief_error(d: RunData, model, executed: np.ndarray, index: np.ndarray,
                          t_est: np.ndarray, T_est: np.ndarray) -> np.ndarray:
    """How far each executed foothold (:func:`executed_footholds`) is from where the robot
    believed it was at touchdown: the foot from the same joint angles placed with the robot's
    pose estimate ``t_est``, ``T_est`` (:func:`estimated_path`: dead reckoning re-anchored by
    the latest ICP correction) instead of the true pose, ``(K,)`` [m]. The controller puts a
    foot where its estimate says the planned foothold is, so this is the placement error
    perception leaves (the ground-truth walks of ``terrain-bench sim`` measure the same,
    localised or not); a heading error counts at the feet, not just at the body centre."""
    from terrain_perception.kinematics import forward
    if not len(executed) or not len(t_est) or not len(d.gt_t):
        return np.zeros(0)
    t = d.joint_t[index]
    feet_b = forward(model, d.joint_q[index])[np.arange(len(index)), executed[:, 0].astype(int)]
    T_true = interp_poses(d.gt_t, d.gt_T, t)
    T_bel = interp_poses(t_est, T_est, t)
    return np.linalg.norm(_transform_each(T_bel, feet_b) - _transform_each(T_true, feet_b),
                          axis=1)


def planned_footholds(plans: List[dict]) -> np.ndarray:
    """Every footstep of every OK plan, ``(K, 6)`` = leg, x, y, z, cost, step_index."""
    rows = [np.column_stack([p['steps'], np.arange(len(p['steps']))])
            for p in plans if len(p['steps'])]
    return np.concatenate(rows) if rows else np.zeros((0, 6))


def committed_footholds(plans: List[dict]) -> np.ndarray:
    """The first footstep of each plan (the one the controller executes next), de-duplicated:
    ``(K, 5)`` = leg, x, y, z, cost."""
    seen, rows = set(), []
    for p in plans:
        if not len(p['steps']):
            continue
        s = p['steps'][0]
        key = (int(s[0]), round(float(s[1]), 3), round(float(s[2]), 3))
        if key not in seen:
            seen.add(key)
            rows.append(s)
    return np.asarray(rows, dtype=np.float64).reshape(-1, 5)


def _finite(v) -> Optional[float]:
    return None if v is None or not np.isfinite(v) else float(v)


def compute_summary(d: RunData, model=None, cost_cfg: CostConfig = CostConfig()) -> dict:
    """The numbers of ``summary.json``; each unavailable metric is None with a reason in
    ``missing``."""
    c = d.course
    missing: Dict[str, str] = {}
    s: dict = {
        'robot': d.robot, 'course': c.name, 'seed': c.seed,
        'end_reason': d.end_reason,
        'sim_time_s': round(d.sim_time_s, 3), 'wall_time_s': round(d.wall_time_s, 1),
        'real_time_factor': (round(d.sim_time_s / d.wall_time_s, 3)
                             if d.wall_time_s > 0 else None),
        'machine_cpu_pct': dict(d.machine_cpu_pct),
        'course_geometry_m': {'start_x': c.start_x_m, 'rough_x0': c.rough_x0_m,
                              'rough_x1': c.rough_x1_m, 'finish_x': c.finish_x_m},
    }
    body = (model.body_size_m if model is not None else np.array([0.24, 0.10, 0.06]))
    # --- motion (ground truth)
    fallen = np.zeros(0, bool)
    if len(d.gt_t):
        x = d.gt_T[:, 0, 3]
        fallen = fall_mask(d.gt_T, d.true_terrain, body)
        falls = count_falls(d.gt_t, fallen)
        k_cross = crossing_index(d.gt_t, x, fallen, c.finish_x_m)
        crossed = k_cross is not None
        s['crossed'] = crossed
        s['falls'] = falls
        # From where the robot really started (a replayed bag may start anywhere).
        s['start_x_m'] = round(float(x[0]), 4)
        s['distance_m'] = round(float(x[-1] - x[0]), 4)
        s['max_distance_m'] = round(float(x.max() - x[0]), 4)
        s['distance_to_cross_m'] = round(c.finish_x_m - float(x[0]), 4)
        path = np.linalg.norm(np.diff(d.gt_T[:, :3, 3], axis=0), axis=1).sum()
        s['path_length_m'] = round(float(path), 4)
        s['time_to_cross_s'] = (round(float(d.gt_t[k_cross] - d.gt_t[0]), 3)
                                if crossed else None)
        if not crossed:
            missing['time_to_cross_s'] = 'did not cross'
        dur = d.gt_t[-1] - d.gt_t[0]
        s['mean_speed_mps'] = round(float((x[-1] - x[0]) / dur), 4) if dur > 0 else None
        s['max_tilt_deg'] = round(float(np.degrees(tilt_rad(d.gt_T).max())), 2)
    else:
        for k in ('crossed', 'falls', 'distance_m', 'time_to_cross_s', 'mean_speed_mps'):
            s[k] = None
            missing[k] = 'no /ground_truth/odom received'
    # --- localisation
    t_est, T_est, label = estimated_path(d)
    s['estimate_source'] = label or None
    if len(t_est) and len(d.gt_t):
        T_true = interp_poses(d.gt_t, d.gt_T, t_est[-1:])[0]
        s['final_localisation_error_m'] = round(
            float(np.linalg.norm(T_est[-1, :3, 3] - T_true[:3, 3])), 5)
        T_gt = interp_poses(d.gt_t, d.gt_T, t_est)
        err = np.linalg.norm(T_est[:, :3, 3] - T_gt[:, :3, 3], axis=1)
        s['rms_localisation_error_m'] = round(float(np.sqrt(np.mean(err ** 2))), 5)
        # Heading: a slip the leg odometry misses turns the robot under its estimate; the
        # position error alone hides it (the robot pivots roughly in place).
        yaw_err = np.degrees(np.abs(heading_error_rad(T_est, T_gt)))
        s['final_heading_error_deg'] = round(float(yaw_err[-1]), 2)
        s['max_heading_error_deg'] = round(float(np.max(yaw_err)), 2)
    else:
        s['final_localisation_error_m'] = None
        missing['final_localisation_error_m'] = (
            'no /odom/dead_reckoning and no /icp/pose received' if not len(t_est)
            else 'no /ground_truth/odom received')
    if len(d.icp_t) and len(d.gt_t):
        T_true = interp_poses(d.gt_t, d.gt_T, d.icp_t[-1:])[0]
        s['final_icp_pose_error_m'] = round(
            float(np.linalg.norm(d.icp_T[-1, :3, 3] - T_true[:3, 3])), 5)
    s['icp_corrections'] = int(len(d.corr_t))
    # --- map
    if d.map_fine is not None and d.true_terrain is not None:
        err = map_errors(d.map_fine, d.true_terrain, observed_mask(d.map_fine))
        n = int(err.size)
        s['map_rmse_observed_m'] = _finite(float(np.sqrt(np.mean(err ** 2)))) if n else None
        s['map_observed_cells'] = n
        if n:
            # Robust figures beside the RMSE: a few wild cells dominate an RMSE.
            s['map_abs_err_median_m'] = round(float(np.median(np.abs(err))), 5)
            s['map_cells_within_1cm'] = round(float(np.mean(np.abs(err) <= 0.01)), 4)
            s['map_cells_off_by_5cm'] = round(float(np.mean(np.abs(err) > 0.05)), 4)
        if n == 0:
            missing['map_rmse_observed_m'] = '/map/fine has no observed cell on the course'
    else:
        s['map_rmse_observed_m'] = None
        missing['map_rmse_observed_m'] = ('no /map/fine received' if d.map_fine is None
                                          else 'no /ground_truth/terrain received')
    if d.map_filled is not None and d.true_terrain is not None \
            and 'filled' in d.map_filled.layers:
        rmse, n = map_rmse(d.map_filled, d.true_terrain, d.map_filled['filled'] > 0.5)
        s['filled_rmse_m'] = _finite(rmse)
        s['filled_cells'] = n
    # --- footholds
    executed, index = (executed_footholds(d.joint_t, d.joint_q, d.gt_t, d.gt_T, model,
                                          return_index=True)
                       if model is not None else (np.zeros((0, 4)), np.zeros(0, int)))
    committed = committed_footholds(d.plans)
    belief = (foothold_belief_error(d, model, executed, index, t_est, T_est)
              if model is not None else [])
    if len(belief) and fallen.any():
        # Before the robot fell (a tipping robot's feet are not footholds; it tips in ~0.4 s)
        belief = belief[d.joint_t[index] < d.gt_t[np.argmax(fallen)] - 0.5]
    s['foothold_belief_error_footholds'] = int(len(belief))
    if len(belief):
        s['foothold_belief_error_m_mean'] = round(float(np.mean(belief)), 5)
        s['foothold_belief_error_m_p95'] = round(float(np.percentile(belief, 95)), 5)
    else:
        s['foothold_belief_error_m_mean'] = None
        missing['foothold_belief_error_m_mean'] = (
            'no robot model' if model is None else 'no executed footholds' if not len(executed)
            else 'no pose estimate (/odom/dead_reckoning, /icp/pose)'
            if not len(t_est) or not len(d.gt_t)
            else 'no executed foothold before the fall')
    s['plans_received'] = len(d.plans)
    s['plans_ok'] = int(sum(1 for p in d.plans if len(p['steps'])))
    s['executed_footholds'] = int(len(executed))
    s['planned_footholds'] = int(len(committed))
    if d.true_terrain is not None and (len(executed) or len(committed)):
        truth = true_cost_grid(d.true_terrain, cost_cfg)
        src, pts = (('executed', executed[:, 1:3]) if len(executed)
                    else ('planned', committed[:, 1:3]))
        cost = truth.sample('cost', pts)
        s['mean_true_foothold_cost'] = _finite(float(np.nanmean(cost)))
        s['foothold_cost_source'] = src
        if len(committed):
            s['mean_true_cost_planned'] = _finite(
                float(np.nanmean(truth.sample('cost', committed[:, 1:3]))))
            s['mean_believed_cost_planned'] = _finite(float(np.nanmean(committed[:, 4])))
    else:
        s['mean_true_foothold_cost'] = None
        missing['mean_true_foothold_cost'] = (
            'no footholds: no executed steps and no plan with footsteps'
            if d.true_terrain is not None else 'no /ground_truth/terrain received')
    # --- latency
    if d.latencies_ms:
        lat = np.asarray(d.latencies_ms)
        s['capture_to_plan_ms_median'] = round(float(np.median(lat)), 1)
        s['capture_to_plan_ms_p95'] = round(float(np.percentile(lat, 95)), 1)
        s['capture_to_plan_ms_all'] = [round(float(v), 1) for v in lat]
        # where the wall time goes: per node, first arrival on its output minus on its input
        s['latency_stages_ms'] = {
            name: {'median': round(float(np.median(v)), 1),
                   'p95': round(float(np.percentile(v, 95)), 1), 'captures': len(v)}
            for name, v in d.latency_stages_ms.items() if len(v)}
    else:
        s['capture_to_plan_ms_median'] = None
        missing['capture_to_plan_ms_median'] = 'no plan matched a captured image stamp'
    s['messages'] = dict(sorted(d.counts.items()))
    s['nodes'] = d.nodes
    # each node's process CPU [s] at its last diagnostics (a value, not a counter)
    s['node_cpu_s'] = {k: round(v[CPU_KEY] / 1000.0, 1)
                       for k, v in sorted(d.node_counters.items()) if CPU_KEY in v}
    s['node_counters'] = {k: {c: n for c, n in v.items() if c != CPU_KEY}
                          for k, v in d.node_counters.items()}
    s['complete_graph'] = bool(d.nodes) and all(
        n.get('state') == 'ran' for n in d.nodes.values())
    s['missing'] = missing
    s['notes'] = list(d.notes)
    s['fall_analysis'] = fall_analysis(d, model, fallen=fallen if len(fallen) else None)
    return s



# ---------------------------------------------------------------------------------------------
# falls

#: A foot sphere closer than this to the true terrain touches it [m] (the terrain grid is
#: sampled at cell centres: a few mm of slack).
CONTACT_GAP_M = 0.005
#: A foot slower than this is standing, faster it swings or slips [m/s].
FOOT_STILL_MPS = 0.03
#: The tipping itself: the base tilted past this [deg] (the same as the walk trace's).
TIP_TILT_DEG = 20.0

_DISC = np.array([(0.0, 0.0)] + [(rho * math.cos(a), rho * math.sin(a))
                                 for rho in (0.5, 0.9) for a in np.arange(8) * math.pi / 4])


def foot_gaps(terrain: GridMap, centres: np.ndarray, radius_m: float) -> np.ndarray:
    """Gap between foot spheres (centres ``(..., 3)``) and the terrain ``(...)`` [m]: the
    least, over terrain samples under the sphere's disc, of the sphere's underside height
    above the sample (<= 0: touching or sunk in). NaN off the terrain grid."""
    c = np.asarray(centres, dtype=np.float64)
    off = _DISC * radius_m                                             # (S, 2)
    xy = c[..., None, :2] + off                                        # (..., S, 2)
    h = terrain.sample('elevation', xy).astype(np.float64)
    under = c[..., None, 2] - np.sqrt(np.maximum(radius_m ** 2 - (off ** 2).sum(-1), 0.0))
    return np.min(under - h, axis=-1)


def _runs(mask: np.ndarray) -> List[Tuple[int, int]]:
    """(start, end exclusive) of the True runs of a 1-D mask."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.flatnonzero(np.diff(m.astype(np.int8)))
    return list(zip(d[::2].tolist(), d[1::2].tolist()))


def fall_analysis(d: RunData, model, window_s: float = 2.0,
                  fallen: Optional[np.ndarray] = None) -> List[dict]:
    """How each fall of a run happened, from the true base pose, the joint angles (and
    torques) and the true terrain: the closed loop's counterpart of the ground-truth walks'
    trace (:func:`terrain_perception.sim.trace.fall_report`), without the simulator's contact
    forces, so contact is geometric (a foot within :data:`CONTACT_GAP_M` of the terrain).

    Per fall (an episode of :func:`fall_mask` of 0.5 s or more) a dict: ``t_s``, ``x_m`` where
    the base first tilted past :data:`TIP_TILT_DEG` (or the fall began, if it went down on its
    belly); ``com_left_support_t_s`` (the last time the model COM was inside the polygon of
    the feet on the ground, within ``window_s``), ``support`` (those feet) and ``margin_mm``
    (a second earlier; negative: already outside), ``support_after`` (the feet on the ground
    the next sample) and ``swinging`` (the legs moving off the ground then); ``hanging``
    (stance feet standing still off the ground for 0.1 s or more before that: leg -> longest
    run [s], its start, largest gap [mm], torque-estimated load [N]);
    ``hard_contacts`` (feet whose torque-estimated vertical load exceeded the robot's weight
    in the last 0.5 s: leg -> N, time, fastest descent of that foot in the 50 ms before);
    ``belief_offset_mm`` (per leg, where the robot's pose
    estimate puts the foot minus where it is, x-y and z, at ``belief_t_s``: the COM's last
    moment inside, but at most 0.5 s before the tip, which the estimate does not follow),
    ``localisation_error_mm``; ``gait`` of the last plan; and ``text``, one line of all that."""
    from terrain_perception.gait import support_margin
    from terrain_perception.kinematics import com_base, forward, foot_forces
    from terrain_perception.robot_model import LEG_NAMES
    if model is None or not len(d.gt_t) or len(d.joint_t) < 3 or d.true_terrain is None:
        return []
    if fallen is None:
        fallen = fall_mask(d.gt_T, d.true_terrain, model.body_size_m)
    tilt = np.degrees(tilt_rad(d.gt_T))
    t_est, T_est, _ = estimated_path(d)
    out = []
    for a, b in _runs(fallen):
        if d.gt_t[b - 1] - d.gt_t[a] < 0.5:
            continue
        before = np.flatnonzero((d.gt_t >= d.gt_t[a] - 3.0) & (d.gt_t <= d.gt_t[a]))
        tipped = before[tilt[before] > TIP_TILT_DEG]
        k = int(tipped[0]) if len(tipped) else a
        t_fall = float(d.gt_t[k])
        rows = np.flatnonzero((d.joint_t >= t_fall - window_s) & (d.joint_t <= t_fall))
        if len(rows) < 3:
            continue
        t = d.joint_t[rows]
        q = d.joint_q[rows]
        T = interp_poses(d.gt_t, d.gt_T, t)
        feet = np.einsum('nij,nkj->nki', T[:, :3, :3], forward(model, q)) + T[:, None, :3, 3]
        gap = foot_gaps(d.true_terrain, feet, model.foot_radius_m)             # (n, 4)
        on = np.nan_to_num(gap, nan=1.0) < CONTACT_GAP_M
        dt = np.maximum(np.gradient(t), 1e-6)
        still = np.linalg.norm(np.gradient(feet, axis=0), axis=-1) / dt[:, None] < FOOT_STILL_MPS
        com = _transform_each(T, com_base(model, q))
        margin = np.full(len(t), np.nan)
        for i in range(len(t)):
            if on[i].sum() >= 2:
                margin[i] = float(support_margin(com[i, :2], feet[i, on[i], :2]))
        inside = np.flatnonzero(np.nan_to_num(margin, nan=-1.0) > 0.0)
        j = int(inside[-1]) if len(inside) else 0
        j1 = min(j + 1, len(t) - 1)          # the support just lost (or the window's start)
        legs = lambda m: '+'.join(LEG_NAMES[i] for i in range(4) if m[i]) or 'none'  # noqa
        r = {'t_s': round(t_fall, 3), 'x_m': round(float(d.gt_T[k, 0, 3]), 4),
             'swinging': legs(~on[j1] & ~still[j1]),
             'com_left_support_t_s': round(float(t[j]), 3) if len(inside) else None,
             'support': legs(on[j]) if len(inside) else None,
             'support_after': legs(on[j1]) if len(inside) else None}
        k1 = int(np.searchsorted(t, t[j] - 1.0))
        r['margin_mm'] = (round(float(margin[k1]) * 1000, 1) if np.isfinite(margin[k1])
                          else None)
        # stance feet off the ground: standing still, not touching, before the COM left
        hang = {}
        tau = getattr(d, 'joint_tau', None)
        has_tau = tau is not None and len(tau) == len(d.joint_t)
        for leg in range(4):
            free = (still[:j + 1, leg] & ~on[:j + 1, leg]
                    & np.isfinite(gap[:j + 1, leg]))
            best = max(_runs(free), key=lambda ab: ab[1] - ab[0], default=None)
            if best is None or t[best[1] - 1] - t[best[0]] < 0.1:
                continue
            s0, s1 = best
            load = None
            if has_tau:
                f = foot_forces(model, q[s0:s1], tau[rows][s0:s1])[:, leg]       # base frame
                fz = np.einsum('nj,nj->n', T[s0:s1, 2, :3], f)                  # world z
                load = round(float(np.nanmean(fz)), 1) if np.isfinite(fz).any() else None
            hang[LEG_NAMES[leg]] = {'s': round(float(t[s1 - 1] - t[s0]), 2),
                                    'from_t_s': round(float(t[s0]), 2),
                                    'gap_mm': round(float(np.nanmax(gap[s0:s1, leg])) * 1e3, 1),
                                    'estimated_load_n': load}
        r['hanging'] = hang
        # Torque-estimated vertical loads above the robot's weight in the last 0.5 s: a swing
        # foot that met the ground hard (landing early on ground higher than believed), or a
        # stance foot the tipping body fell onto.
        r['hard_contacts'] = {}
        if has_tau:
            last = np.flatnonzero(t >= t_fall - 0.5)
            f = foot_forces(model, q[last], tau[rows][last])
            fz = np.einsum('nj,nkj->nk', T[last, 2, :3], f)
            weight = model.total_mass_kg * 9.81
            for leg in range(4):
                if np.nanmax(fz[:, leg], initial=-np.inf) > weight:
                    i = int(np.nanargmax(fz[:, leg]))
                    # how fast the foot came down just before (a landing) [m/s]
                    before = np.flatnonzero((t >= t[last[i]] - 0.05) & (t <= t[last[i]]))
                    vz = np.gradient(feet[:, leg, 2], t)[before]
                    r['hard_contacts'][LEG_NAMES[leg]] = {
                        'n': round(float(fz[i, leg]), 1), 't_s': round(float(t[last[i]]), 2),
                        'descent_mps': round(float(max(-vz.min(), 0.0)), 3)}
        # The estimate against the truth before the tipping (the estimate does not tip with
        # the robot): at the COM's last moment inside, at most 0.5 s before the tip.
        jb = min(j, max(int(np.searchsorted(t, t_fall - 0.5)) - 1, 0))
        r['belief_t_s'] = round(float(t[jb]), 3)
        if len(t_est):
            Tb = interp_poses(t_est, T_est, t[jb:jb + 1])[0]
            fb = forward(model, q[jb]) @ Tb[:3, :3].T + Tb[:3, 3]
            off = fb - feet[jb]
            r['belief_offset_mm'] = {
                LEG_NAMES[i]: [round(float(np.linalg.norm(off[i, :2])) * 1000, 1),
                               round(float(off[i, 2]) * 1000, 1)] for i in range(4)}
            r['localisation_error_mm'] = round(float(np.linalg.norm(Tb[:3, 3] - T[jb, :3, 3]))
                                               * 1000, 1)
        else:
            r['belief_offset_mm'], r['localisation_error_mm'] = None, None
        plans = [p for p in d.plans
                 if p.get('t_recv', p['stamp']) <= t_fall and len(p['steps'])]
        r['gait'] = plans[-1].get('gait') if plans else None
        text = [f'fell at t = {t_fall:.2f} s, x = {r["x_m"]:.3f} m, swinging {r["swinging"]}']
        if r['com_left_support_t_s'] is not None:
            text.append(f'COM last inside the feet on the ground ({r["support"]}) at t = '
                        f'{r["com_left_support_t_s"]:.2f} s ({t_fall - t[j]:.2f} s before; '
                        f'next sample on the ground: {r["support_after"]}), margin 1 s earlier '
                        f'{r["margin_mm"]} mm')
        else:
            text.append(f'COM outside the feet on the ground for the whole {window_s:.0f} s')
        text.append('hanging stance feet: ' + (', '.join(
            f'{leg} {h["s"]:.2f} s from t = {h["from_t_s"]:.2f} (gap up to {h["gap_mm"]:.0f} mm'
            + (f', estimated load {h["estimated_load_n"]:.1f} N)'
               if h['estimated_load_n'] is not None else ')')
            for leg, h in hang.items()) or 'none'))
        text.append(f'feet loaded beyond the robot\'s weight ({model.total_mass_kg * 9.81:.0f} '
                    f'N, torque estimate) in the last 0.5 s: ' + (', '.join(
                        f'{leg} {h["n"]:.0f} N at t = {h["t_s"]:.2f} after descending at '
                        f'up to {h["descent_mps"]:.2f} m/s'
                        for leg, h in r['hard_contacts'].items()) or 'none'))
        if r['belief_offset_mm'] is not None:
            text.append(f'belief - truth per foot at t = {r["belief_t_s"]:.2f} [mm] (x-y, z): '
                        + ', '.join(
                f'{leg} {v[0]:.0f}, {v[1]:+.0f}' for leg, v in r['belief_offset_mm'].items())
                + f'; localisation error {r["localisation_error_mm"]:.0f} mm')
        r['text'] = '; '.join(text)
        out.append(r)
    return out


# ---------------------------------------------------------------------------------------------
# figures


def _extent(g: GridMap):
    x0, y0 = g.origin_xy
    lx, ly = g.length_xy
    return [x0, x0 + lx, y0, y0 + ly]


def _show(ax, g: Optional[GridMap], layer: str, title: str, vmin=None, vmax=None,
          cmap='terrain', why: str = ''):
    if g is None or layer not in g.layers:
        ax.text(0.5, 0.5, f'no data\n{why}', ha='center', va='center', transform=ax.transAxes,
                fontsize=10, color='0.3', wrap=True)
        ax.set_title(title + ' (missing)')
        return None
    im = ax.imshow(g[layer].T, origin='lower', extent=_extent(g), cmap=cmap, vmin=vmin,
                   vmax=vmax, interpolation='nearest', aspect='equal')
    ax.set_title(title)
    ax.set_xlabel('x [m]')
    ax.set_ylabel('y [m]')
    return im


def _course_lines(ax, c: CourseInfo) -> None:
    for x, ls in ((c.rough_x0_m, ':'), (c.rough_x1_m, ':'), (c.finish_x_m, '--')):
        ax.axvline(x, color='k', lw=0.8, ls=ls)


def _crop(ax, d: RunData) -> None:
    """View: the course region the robot walked plus the map's extent, y within +-0.5 m."""
    xs = [d.course.start_x_m - 0.35, d.course.finish_x_m + 0.3]
    if len(d.gt_t):
        xs += [float(d.gt_T[:, 0, 3].min()) - 0.35, float(d.gt_T[:, 0, 3].max()) + 0.6]
    ax.set_xlim(min(xs), max(xs))
    ax.set_ylim(-0.5, 0.5)


def fig_heightmaps(d: RunData, path: Path, why: Dict[str, str]) -> List[str]:
    """True vs perceived vs filled heights on one colour scale; returns missing panels."""
    import matplotlib.pyplot as plt
    missing = []
    t = d.true_terrain
    vmax = float(np.nanmax(t['elevation'])) if t is not None else None
    fig, axes = plt.subplots(3, 1, figsize=(11, 10), constrained_layout=True)
    im = _show(axes[0], t, 'elevation', 'true terrain (/ground_truth/terrain)', 0.0, vmax,
               why=why.get('true', ''))
    _show(axes[1], d.map_fine, 'elevation', 'perceived: /map/fine (observed cells only)',
          0.0, vmax, why=why.get('fine', ''))
    _show(axes[2], d.map_filled, 'elevation', 'filled: /map/filled (Fill-Terrain)', 0.0, vmax,
          why=why.get('filled', ''))
    for name, g in (('true', t), ('perceived', d.map_fine), ('filled', d.map_filled)):
        if g is None:
            missing.append(name)
    if d.map_filled is not None and 'filled' in d.map_filled.layers:
        f = d.map_filled['filled'] > 0.5
        axes[2].contour(*np.meshgrid(*d.map_filled.cell_centers(), indexing='ij'), f,
                        levels=[0.5], colors='m', linewidths=0.6)
        axes[2].set_title(axes[2].get_title() + '; magenta: filled-cell border')
    if len(d.gt_t):
        for ax in axes:
            ax.plot(d.gt_T[:, 0, 3], d.gt_T[:, 1, 3], 'k-', lw=1.0, label='true base path')
    for ax in axes:
        _course_lines(ax, d.course)
        _crop(ax, d)
    if im is not None:
        fig.colorbar(im, ax=axes, label='height [m]', shrink=0.6)
    fig.suptitle(f'{d.robot} on {d.course.name} (seed {d.course.seed}): heights  '
                 '(dotted: rough section, dashed: finish line)')
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return missing


def fig_footsteps(d: RunData, path: Path, executed: np.ndarray, cost_cfg: CostConfig,
                  why: Dict[str, str]) -> List[str]:
    """The cost map with planned (small) and executed (large) footholds per leg."""
    import matplotlib.pyplot as plt
    missing = []
    fig, ax = plt.subplots(figsize=(12, 5), constrained_layout=True)
    g, title = d.map_filled, 'cost layer of /map/filled'
    if g is None or 'cost' not in g.layers:
        missing.append('perceived cost map')
        g = true_cost_grid(d.true_terrain, cost_cfg) if d.true_terrain is not None else None
        title = ('TRUE cost (no /map/filled cost layer: ' + why.get('filled', 'missing') + ')'
                 if g is not None else 'cost')
    # One colour scale for perceived and true cost: the true rocks' 99th percentile (a few
    # wild cells of a perceived map would wash everything else out).
    ref = (true_cost_grid(d.true_terrain, cost_cfg)['cost'] if d.true_terrain is not None
           else (g['cost'] if g is not None else np.ones(1)))
    vmax = float(np.nanpercentile(ref, 99)) if np.isfinite(ref).any() else 1.0
    vmax = vmax if vmax > 0 else 1.0
    im = _show(ax, g, 'cost', title, 0.0, vmax, cmap='viridis', why=why.get('filled', ''))
    if im is not None:
        fig.colorbar(im, ax=ax, label='foothold cost [-]', shrink=0.8)
    planned = planned_footholds(d.plans)
    if not len(planned):
        missing.append('planned footsteps')
    if not len(executed):
        missing.append('executed footsteps')
    for leg in range(4):
        p = planned[planned[:, 0] == leg]
        if len(p):
            ax.scatter(p[:, 1], p[:, 2], s=30, marker='x', color=LEG_COLOURS[leg], alpha=0.9,
                       lw=1.3, label=f'planned {LEG_NAMES[leg]}')
        e = executed[executed[:, 0] == leg] if len(executed) else executed
        if len(e):
            ax.scatter(e[:, 1], e[:, 2], s=40, marker='o', facecolors='none',
                       edgecolors=LEG_COLOURS[leg], lw=1.5, label=f'executed {LEG_NAMES[leg]}')
    if len(d.gt_t):
        ax.plot(d.gt_T[:, 0, 3], d.gt_T[:, 1, 3], 'w-', lw=0.8, label='true base path')
    _course_lines(ax, d.course)
    _crop(ax, d)
    ax.set_ylim(-0.3, 0.3)
    if missing:
        ax.text(0.01, 0.02, 'missing: ' + ', '.join(missing), transform=ax.transAxes,
                color='r', fontsize=9, va='bottom')
    ax.legend(loc='upper left', fontsize=7, ncol=4)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return missing


def fig_path(d: RunData, path: Path, why: Dict[str, str]) -> List[str]:
    """Paper 000 Fig. 10: the map with the true and the estimated path; ICP corrections (the
    jumps of the estimate) marked; below, the position error over time."""
    import matplotlib.pyplot as plt
    missing = []
    t_est, T_est, label = estimated_path(d)
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(11, 8), constrained_layout=True,
                                  gridspec_kw={'height_ratios': [2, 1]})
    bg = next((g for g in (d.map_filled, d.map_fine, d.true_terrain) if g is not None), None)
    if bg is not None:
        top = (float(np.nanmax(d.true_terrain['elevation'])) if d.true_terrain is not None
               else 0.06)
        ax.imshow(bg['elevation'].T, origin='lower', extent=_extent(bg), cmap='gray',
                  interpolation='nearest', aspect='equal', alpha=0.8, vmin=0.0,
                  vmax=max(top, 0.01))
    if len(d.gt_t):
        ax.plot(d.gt_T[:, 0, 3], d.gt_T[:, 1, 3], 'g-', lw=1.5, label='true path')
    else:
        missing.append('true path')
    if len(t_est):
        ax.plot(T_est[:, 0, 3], T_est[:, 1, 3], 'b.-', ms=2, lw=0.8, label=f'estimate: {label}')
    else:
        missing.append('estimated path')
    if len(d.corr_t) and len(d.dr_t):
        # Where the estimate jumps: before (previous anchor) -> after (new anchor).
        for k, tc in enumerate(d.corr_t):
            Tdr = interp_poses(d.dr_t, d.dr_T, np.array([tc]))[0]
            before = (d.corr_T[k - 1] if k > 0 else np.eye(4)) @ Tdr
            after = d.corr_T[k] @ Tdr
            ax.plot([before[0, 3], after[0, 3]], [before[1, 3], after[1, 3]], 'r-', lw=1.5)
            ax.plot(after[0, 3], after[1, 3], 'r+', ms=8,
                    label='ICP correction' if k == 0 else None)
    elif len(d.icp_t):
        ax.plot(d.icp_T[:, 0, 3], d.icp_T[:, 1, 3], 'r+', ms=8, label='ICP pose')
    else:
        missing.append('ICP corrections')
    _course_lines(ax, d.course)
    xs = [d.course.start_x_m - 0.2, d.course.finish_x_m + 0.2]
    if len(d.gt_t):
        xs += [d.gt_T[:, 0, 3].min() - 0.2, d.gt_T[:, 0, 3].max() + 0.2]
    ax.set_xlim(min(xs), max(xs))
    ax.set_ylim(-0.3, 0.3)
    ax.set_xlabel('x [m]')
    ax.set_ylabel('y [m]')
    ax.set_title('true vs estimated base path (paper 000 Fig. 10 style); '
                 'red: ICP corrections' + ('' if not missing else
                                           '  [missing: ' + ', '.join(missing) + ']'))
    ax.legend(loc='upper left', fontsize=8)
    if len(t_est) and len(d.gt_t):
        err = np.linalg.norm(T_est[:, :3, 3] - interp_poses(d.gt_t, d.gt_T, t_est)[:, :3, 3],
                             axis=1)
        ax2.plot(t_est, err * 1000.0, 'b-', lw=1, label=label)
        if len(d.icp_t):
            e2 = np.linalg.norm(d.icp_T[:, :3, 3]
                                - interp_poses(d.gt_t, d.gt_T, d.icp_t)[:, :3, 3], axis=1)
            ax2.plot(d.icp_t, e2 * 1000.0, 'r+', label='ICP pose')
        for tc in d.corr_t:
            ax2.axvline(tc, color='r', lw=0.4, alpha=0.5)
        ax2.legend(fontsize=8)
    else:
        ax2.text(0.5, 0.5, 'no estimate to compare\n' + why.get('estimate', ''),
                 ha='center', va='center', transform=ax2.transAxes, color='0.3')
    ax2.set_xlabel('simulated time [s]')
    ax2.set_ylabel('position error [mm]')
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return missing


def write_report(d: RunData, run_dir: Path, model=None,
                 cost_cfg: CostConfig = CostConfig()) -> dict:
    """Write ``summary.json`` and the figures into ``run_dir``; return the summary."""
    import matplotlib
    matplotlib.use('Agg')
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    summary = compute_summary(d, model, cost_cfg)
    why = {'true': 'no /ground_truth/terrain received',
           'fine': summary['missing'].get('map_rmse_observed_m', 'no /map/fine received'),
           'filled': 'no /map/filled received',
           'estimate': summary['missing'].get('final_localisation_error_m', '')}
    node_why = _node_reasons(d.nodes)
    for k, node in (('fine', 'icp_mapper'), ('filled', 'terrain_fill'),
                    ('estimate', 'walking_controller')):
        if node in node_why:
            why[k] = f'{why[k]} ({node}: {node_why[node]})'
    executed = (executed_footholds(d.joint_t, d.joint_q, d.gt_t, d.gt_T, model)
                if model is not None else np.zeros((0, 4)))
    figures = {}
    for name, fn in (('heightmaps.png', lambda p: fig_heightmaps(d, p, why)),
                     ('footsteps.png', lambda p: fig_footsteps(d, p, executed, cost_cfg, why)),
                     ('path.png', lambda p: fig_path(d, p, why))):
        p = run_dir / name
        try:
            miss = fn(p)
            figures[name] = {'file': str(p), 'missing_panels': miss}
        except Exception as exc:  # a figure failing must not lose the summary
            figures[name] = {'file': None, 'error': f'{type(exc).__name__}: {exc}'}
    summary['figures'] = figures
    maps = {}
    for name, g in (('map_fine.npz', d.map_fine), ('map_filled.npz', d.map_filled)):
        if g is not None:
            maps[name] = str(g.save(run_dir / name))
    summary['maps'] = maps
    (run_dir / 'summary.json').write_text(json.dumps(summary, indent=2, default=_jsonable))
    return summary


def _node_reasons(nodes: Dict[str, dict]) -> Dict[str, str]:
    return {name: (n.get('reason') or n.get('state', '')) for name, n in nodes.items()
            if n.get('state') != 'ran'}


def _jsonable(v):
    if isinstance(v, np.bool_):
        return bool(v)
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.floating,)):
        return float(v)
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, Path):
        return str(v)
    raise TypeError(f'not JSON-serialisable: {type(v).__name__}')


def format_summary(s: dict) -> str:
    """A short human-readable summary (what ``terrain-demo`` prints at the end)."""
    def f(key, fmt='{:.3f}', unit=''):
        v = s.get(key)
        if v is None:
            return f'n/a ({s["missing"].get(key, "missing")})'
        return fmt.format(v) + unit
    lines = [
        f'robot {s["robot"]} on {s["course"]} seed {s["seed"]}: '
        f'{"CROSSED" if s.get("crossed") else "NOT crossed"} '
        f'(ended: {s["end_reason"]})',
        f'  distance       {f("distance_m", "{:.3f}", " m")} of '
        f'{s.get("distance_to_cross_m", float("nan")):.2f} m; falls {s.get("falls")}',
        f'  sim time       {s["sim_time_s"]:.1f} s in {s["wall_time_s"]:.0f} s wall '
        f'(RTF {s["real_time_factor"]})',
        f'  localisation   final error {f("final_localisation_error_m", "{:.4f}", " m")}, '
        f'heading {f("final_heading_error_deg", "{:.1f}", " deg")} '
        f'(max {f("max_heading_error_deg", "{:.1f}", " deg")}); '
        f'{s.get("icp_corrections", 0)} ICP corrections',
        f'  map RMSE       {f("map_rmse_observed_m", "{:.4f}", " m")} on '
        f'{s.get("map_observed_cells", 0)} observed cells (median |error| '
        f'{f("map_abs_err_median_m", "{:.4f}", " m")}, '
        f'{100 * (s.get("map_cells_off_by_5cm") or 0):.1f}% off by > 5 cm)',
        f'  footholds      mean true cost {f("mean_true_foothold_cost", "{:.4f}")} '
        f'({s.get("foothold_cost_source", "-")}); plans {s.get("plans_ok")}/'
        f'{s.get("plans_received")} with steps; believed vs true at touchdown '
        f'{f("foothold_belief_error_m_mean", "{:.4f}", " m")} mean'
        + (f', {s["foothold_belief_error_m_p95"]:.4f} m p95'
           if s.get('foothold_belief_error_m_p95') is not None else ''),
        f'  latency        capture-to-plan median '
        f'{f("capture_to_plan_ms_median", "{:.0f}", " ms")}'
        + (' (' + ', '.join(f'{k} {v["median"]:.0f}'
                            for k, v in s['latency_stages_ms'].items()) + ')'
           if s.get('latency_stages_ms') else ''),
    ]
    icp = (s.get('node_counters') or {}).get('icp_mapper')
    if icp:
        def n(key):
            return icp.get(f'mapper_{key}', 0)
        lines.append(
            f'  ICP decisions  {n("accepted")} accepted, refused: '
            f'{n("rejected_correction") + n("rejected_rotation")} by the drift guard, '
            f'{n("rejected_fitness") + n("rejected_rmse") + n("rejected_level")} as misfits; '
            f'{n("accepted_confirmed")} confirmed by repeated captures, '
            f'{n("accepted_after_disturbance")} after a free fall, '
            f'{n("model_restarted")} model restarts')
    mc = s.get('machine_cpu_pct') or {}
    if mc:
        lines.append(f'  machine        {mc["busy"]:.0f}% busy, {mc["steal"]:.1f}% stolen by the '
                     'host (all CPUs, over the run)')
    cpu = s.get('node_cpu_s') or {}
    if cpu and s.get('wall_time_s'):
        lines.append('  node CPU       ' + ', '.join(
            f'{k} {100 * v / s["wall_time_s"]:.0f}%' for k, v in cpu.items())
            + ' of a core')
    for fa in s.get('fall_analysis') or []:
        lines.append(f'  fall           {fa["text"]}')
    bad = {k: v for k, v in s.get('nodes', {}).items() if v.get('state') != 'ran'}
    if not s.get('nodes'):
        lines.append('  nodes          no node information')
    elif bad:
        lines.append('  nodes NOT ok:  ' + '; '.join(
            f'{k}: {v.get("state")}{" - " + v["reason"] if v.get("reason") else ""}'
            for k, v in bad.items()))
    else:
        lines.append('  nodes          all ran to the end')
    for name, fig in s.get('figures', {}).items():
        if fig.get('file') is None:
            lines.append(f'  figure {name}: NOT written ({fig.get("error")})')
        elif fig.get('missing_panels'):
            lines.append(f'  figure {name}: missing {", ".join(fig["missing_panels"])}')
    return '\n'.join(lines)
