"""``python -m terrain_ros.tools.icp_replay BAG [--param NAME:=VALUE ...] [--json OUT]``: the ICP
mapper node's inputs from a ``terrain-demo`` bag, replayed into its callbacks in one process
(no DDS, no spinning), each alignment compared with the bag's ``/ground_truth/odom``.

The node is built with ``config/icp_mapper.yaml``, the bag's robot (as ``pipeline_profile``
infers it: the stereo baseline, else ``summary.json``; ``--param robot:=NAME`` overrides) and
the ``--param`` overrides, and gets, in
bag order, ``/odom/dead_reckoning``, ``/joint_states``, ``/imu/data``, ``/stereo/points_coarse``
and ``/stereo/points``, exactly as its subscriptions would. Printed (and written as JSON):
captures, accepted, yaw error RMS / max / final [deg] and position error RMS / max / final [m]
of ``T_map_base`` against the ground truth nearest in time, the counters, and, when the bag has
``/ground_truth/terrain``, the final fine map (as the node publishes it) against the true
terrain: height RMSE on observed cells and how many cells stand more than 5 cm above or below
it (``map_*``; phantom cells from stereo mismatches show up in ``map_cells_above_5cm``).

``--slip T:DX,DY`` injects a slip dead reckoning did not see: from bag time ``T`` [s] on, the
odometry the node receives is moved by ``(-DX, -DY)`` [m] in the odometry frame, as if the body
had slid by ``(DX, DY)`` under the legs (the camera clouds and the ground truth are the
bag's). The offset grows linearly over ``SLIP_RAMP_S`` (a slide; a step would be refused by
the node's odometry gate as a jump). The IMU is untouched, so no free fall is reported: it
tests the mapper's recovery without the disturbance exception. The figures then also give the
position error after ``T`` (``pos_err_m_rms_after_slip``; ``captures_to_recover``: counted
from the first capture after ``T``, the capture from which the error stays under
``RECOVERED_M`` to the end of the bag, None if the last one is over it).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from terrain_ros.env import CONFIG_DIR
from terrain_ros.tools.common import ToolError, fail

PROG = 'icp_replay'
INPUTS = {'/odom/dead_reckoning': 'nav_msgs/msg/Odometry',
          '/joint_states': 'sensor_msgs/msg/JointState',
          '/imu/data': 'sensor_msgs/msg/Imu',
          '/stereo/points_coarse': 'sensor_msgs/msg/PointCloud2',
          '/stereo/points': 'sensor_msgs/msg/PointCloud2'}
TRUTH = '/ground_truth/odom'
TERRAIN = '/ground_truth/terrain'
SLIP_RAMP_S = 0.25
RECOVERED_M = 0.02


def _yaw(T: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(T[1, 0], T[0, 0])))


def parse_slip(text: str) -> tuple:
    """``'T:DX,DY'`` -> ``(T, DX, DY)``; ToolError naming the problem otherwise."""
    try:
        t, d = text.split(':', 1)
        dx, dy = (float(v) for v in d.split(','))
        out = (float(t), dx, dy)
    except ValueError:
        raise ToolError(f'--slip {text!r}: expected T:DX,DY (seconds, metres)') from None
    if not all(np.isfinite(out)):
        raise ToolError(f'--slip {text!r}: values must be finite')
    return out


def replay(bag: Path, params: list, slip: tuple = None, window_s: float = None) -> dict:
    import rclpy
    from rclpy.serialization import deserialize_message
    from terrain_ros.conversions import pose_to_matrix, stamp_to_sec
    from terrain_ros.tools.bag import open_reader
    from terrain_ros.tools.common import message_class
    try:
        reader = open_reader(str(bag))
    except Exception as exc:  # noqa: BLE001 - any reader failure is one message
        raise ToolError(f'cannot open bag {str(bag)!r}: {exc}') from None
    topics = {c.topic for c in reader.connections}
    for need in ('/stereo/points', '/odom/dead_reckoning', TRUTH):
        if need not in topics:
            raise ToolError(f'bag {str(bag)!r} has no {need} (a terrain-demo bag has)')
    ros = ['--ros-args', '--params-file', str(CONFIG_DIR / 'icp_mapper.yaml')]
    robot = None
    if not any(p.split(':=', 1)[0] == 'robot' for p in params):
        # The camera mount places the clouds: the bag's robot, not the config file's default
        # (a FROG-I bag through LittleDog's mount put the map 25 cm low).
        from terrain_ros.tools.pipeline_profile import choose_robot
        robot, _ = choose_robot(None, reader, bag)
        ros += ['-p', f'robot:={robot}']
    for p in params:
        ros += ['-p', p]
    rclpy.init(args=[PROG, *ros])
    try:
        from icp_mapper_node.node import IcpMapperNode
        node = IcpMapperNode()
        update, log, corr = node.mapper.update, [], []

        def logged(cloud, T_odom_base, t, **kw):
            res = update(cloud, T_odom_base, t, **kw)
            log.append((t, res.accepted, res.T_map_base.copy()))
            corr.append((t, res.T_map_odom.copy(), res.n_degenerate))
            return res
        node.mapper.update = logged
        on_odom = node._on_odom
        if slip is not None:
            def on_odom(msg, _cb=node._on_odom):
                share = np.clip((stamp_to_sec(msg.header.stamp) - slip[0]) / SLIP_RAMP_S,
                                0.0, 1.0)
                msg.pose.pose.position.x -= share * slip[1]
                msg.pose.pose.position.y -= share * slip[2]
                _cb(msg)
        callbacks = {'/odom/dead_reckoning': on_odom,
                     '/joint_states': node._on_joint_state, '/imu/data': node._on_imu,
                     '/stereo/points_coarse': node._on_coarse, '/stereo/points': node._on_cloud}
        gt_t, gt_T, terrain, dr = [], [], None, []
        conns = [c for c in reader.connections if c.topic in INPUTS or c.topic in
                 (TRUTH, TERRAIN)]
        for c, _, raw in reader.messages(connections=conns):
            if c.topic == TERRAIN:
                terrain = deserialize_message(bytes(raw),
                                              message_class('terrain_msgs/msg/TerrainGrid'))
                continue
            if c.topic == TRUTH:
                m = deserialize_message(bytes(raw), message_class('nav_msgs/msg/Odometry'))
                gt_t.append(stamp_to_sec(m.header.stamp))
                gt_T.append(pose_to_matrix(m.pose.pose))
                continue
            m = deserialize_message(bytes(raw), message_class(INPUTS[c.topic]))
            callbacks[c.topic](m)
            if c.topic == '/odom/dead_reckoning' and window_s is not None:
                try:    # after the callback: with --slip, the odometry the node was given
                    dr.append((stamp_to_sec(m.header.stamp), pose_to_matrix(m.pose.pose)))
                except ValueError:
                    pass
        counters = dict(node.mapper.counters)
        fine = node.mapper.fine_grid(node.node_cfg.map_frame) if log else None
        node.destroy_node()
    finally:
        rclpy.try_shutdown()
        reader.close()
    if not log or not gt_t:
        raise ToolError(f'bag {str(bag)!r}: no alignment or no ground truth to compare')
    gt_t = np.asarray(gt_t)
    yaw_err, pos_err = [], []
    for t, _, T in log:
        G = gt_T[int(np.argmin(np.abs(gt_t - t)))]
        yaw_err.append(abs((_yaw(T) - _yaw(G) + 180.0) % 360.0 - 180.0))
        pos_err.append(float(np.hypot(*(T[:2, 3] - G[:2, 3]))))
    y, p = np.asarray(yaw_err), np.asarray(pos_err)
    extra = {} if slip is None else _after_slip(slip, [t for t, _, _ in log], p)
    if window_s is not None:
        extra['drift'] = _drift(gt_t, gt_T, dr, corr, window_s)
    nd = np.asarray([n for _, _, n in corr])
    extra['captures_with_degenerate_direction'] = int(np.sum(nd > 0))
    return {**extra, 'captures': len(log), 'accepted': int(sum(a for _, a, _ in log)),
            'yaw_err_deg_rms': float(np.sqrt(np.mean(y ** 2))), 'yaw_err_deg_max': float(y.max()),
            'yaw_err_deg_final': float(y[-1]),
            'pos_err_m_rms': float(np.sqrt(np.mean(p ** 2))), 'pos_err_m_max': float(p.max()),
            'pos_err_m_final': float(p[-1]), 'counters': counters, 'params': list(params),
            'robot': robot, 'series': {'t_s': [float(t) for t, _, _ in log],
                                       'yaw_err_deg': [float(v) for v in y],
                                       'pos_err_m': [float(v) for v in p],
                                       'accepted': [bool(a) for _, a, _ in log],
                                       'n_degenerate': [int(n) for _, _, n in corr]},
            **_map_figures(fine, terrain)}


def _after_slip(slip: tuple, t: list, pos_err: np.ndarray) -> dict:
    after = np.asarray(t) >= slip[0]
    if not after.any():
        raise ToolError(f'--slip at {slip[0]:.1f} s: no capture after it '
                        f'(the bag\'s captures end at {t[-1]:.1f} s)')
    p = pos_err[after]
    over = np.flatnonzero(p >= RECOVERED_M)
    recover = 1 if over.size == 0 else (None if over[-1] == len(p) - 1 else int(over[-1]) + 2)
    return {'slip': list(slip), 'captures_after_slip': int(after.sum()),
            'pos_err_m_rms_after_slip': float(np.sqrt(np.mean(p ** 2))),
            'captures_to_recover': recover, 'recovered_m': RECOVERED_M}


def _drift(gt_t, gt_T, dr: list, corr: list, window_s: float) -> list:
    """The replayed estimate's error, window by window (``terrain_ros.report.drift_windows``):
    the bag's dead reckoning re-anchored by the replayed corrections at their captures' stamps."""
    from terrain_ros.report import CourseInfo, RunData, drift_windows
    d = RunData(course=CourseInfo('', 0, 0.0, 0.0, 0.0, 0.0), robot='')
    d.gt_t, d.gt_T = np.asarray(gt_t, float), np.asarray(gt_T, float).reshape(-1, 4, 4)
    if dr:
        d.dr_t = np.asarray([t for t, _ in dr])
        d.dr_T = np.asarray([T for _, T in dr])
    d.corr_t = np.asarray([t for t, _, _ in corr])
    d.corr_T = np.asarray([T for _, T, _ in corr]).reshape(-1, 4, 4)
    return drift_windows(d, window_s)


def _map_figures(fine, terrain_msg) -> dict:
    """The final fine map against the bag's true terrain (empty without it)."""
    if fine is None or terrain_msg is None:
        return {}
    from terrain_ros.conversions import msg_to_grid
    from terrain_ros.report import map_errors, observed_mask
    err = map_errors(fine, msg_to_grid(terrain_msg), observed_mask(fine))
    if err.size == 0:
        return {'map_cells': 0}
    return {'map_cells': int(err.size), 'map_rmse_m': float(np.sqrt(np.mean(err ** 2))),
            'map_cells_above_5cm': int(np.sum(err > 0.05)),
            'map_cells_below_5cm': int(np.sum(err < -0.05))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    ap.add_argument('bag', type=Path, help='rosbag2 directory of a terrain-demo run')
    ap.add_argument('--param', action='append', default=[], metavar='NAME:=VALUE',
                    help='icp_mapper parameter override (repeatable)')
    ap.add_argument('--json', type=Path, default=None, help='write the figures here')
    ap.add_argument('--window', type=float, default=None, metavar='S',
                    help='also print where the estimate (dead reckoning re-anchored by the '
                         'replayed corrections) gained its error, every S simulated seconds '
                         '(as terrain_ros.tools.drift does for the recorded run)')
    ap.add_argument('--slip', default=None, metavar='T:DX,DY',
                    help='from bag time T [s] on, move the dead reckoning by (-DX, -DY) [m]: '
                         'a slip the legs did not see')
    args = ap.parse_args(argv)
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    try:
        for p in args.param:
            if ':=' not in p:
                raise ToolError(f'--param {p!r}: expected NAME:=VALUE')
        slip = None if args.slip is None else parse_slip(args.slip)
        if args.window is not None and not (np.isfinite(args.window) and args.window > 0):
            raise ToolError(f'--window {args.window}: must be a positive number of seconds')
        out = replay(args.bag, args.param, slip, args.window)
    except ValueError as exc:     # a parameter the node refused (name, type, range)
        return fail(PROG, str(exc))
    except ToolError as exc:
        return fail(PROG, str(exc))
    print(f'{out["captures"]} captures, {out["accepted"]} accepted; yaw error RMS '
          f'{out["yaw_err_deg_rms"]:.2f} max {out["yaw_err_deg_max"]:.2f} final '
          f'{out["yaw_err_deg_final"]:.2f} deg; position error RMS '
          f'{100 * out["pos_err_m_rms"]:.2f} max {100 * out["pos_err_m_max"]:.2f} final '
          f'{100 * out["pos_err_m_final"]:.2f} cm')
    if 'slip' in out:
        rec = out['captures_to_recover']
        print(f'after the slip at {out["slip"][0]:.1f} s: {out["captures_after_slip"]} captures, '
              f'position error RMS {100 * out["pos_err_m_rms_after_slip"]:.2f} cm, '
              + (f'under {100 * RECOVERED_M:.0f} cm from capture {rec} on' if rec
                 else f'still over {100 * RECOVERED_M:.0f} cm at the end'))
    if out.get('map_cells'):
        print(f'final fine map: {out["map_cells"]} observed cells, height RMSE '
              f'{1000 * out["map_rmse_m"]:.1f} mm, {out["map_cells_above_5cm"]} cells > 5 cm '
              f'above the terrain, {out["map_cells_below_5cm"]} > 5 cm below')
    print(f'{out["captures_with_degenerate_direction"]} captures kept a direction at the prior')
    if out.get('drift'):
        from terrain_ros.tools.drift import format_rows
        print(format_rows(out['drift']))
    if args.json is not None:
        args.json.write_text(json.dumps(out, indent=2, default=float))
    return 0


if __name__ == '__main__':
    sys.exit(main())
