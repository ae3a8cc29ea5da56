"""``python -m terrain_ros.tools.drift BAG [--window S] [--json OUT]``: where a ``terrain-demo``
run's localisation error came from, read from its bag, window by window.

The robot's estimate is the one the report draws (``terrain_ros.report.estimated_path``:
``/odom/dead_reckoning`` re-anchored by the latest ``/icp/correction``, each correction applied
from the simulated time the recorder received it, read off ``/clock``). Against
``/ground_truth/odom``, every ``--window`` seconds (default 10) it prints the error along and
across the true heading, its change split into what dead reckoning added and what the ICP
corrections added (``terrain_ros.report.drift_windows``), and the odometry's scale (its
displacement over the true one). Nothing is replayed: it runs in seconds on a bag of any length.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from terrain_ros.tools.common import ToolError, fail

PROG = 'drift'
TOPICS = {'/ground_truth/odom': 'nav_msgs/msg/Odometry',
          '/odom/dead_reckoning': 'nav_msgs/msg/Odometry',
          '/icp/correction': 'geometry_msgs/msg/PoseStamped',
          '/clock': 'rosgraph_msgs/msg/Clock'}


def read_run(bag: Path):
    """A :class:`terrain_ros.report.RunData` with the bag's ground truth, dead reckoning and
    corrections (the corrections at their receipt on the simulated clock)."""
    from rclpy.serialization import deserialize_message
    from terrain_ros.conversions import pose_to_matrix, stamp_to_sec
    from terrain_ros.report import CourseInfo, RunData
    from terrain_ros.tools.bag import open_reader
    from terrain_ros.tools.common import message_class
    try:
        reader = open_reader(str(bag))
    except Exception as exc:  # noqa: BLE001 - any reader failure is one message
        raise ToolError(f'cannot open bag {str(bag)!r}: {exc}') from None
    try:
        topics = {c.topic for c in reader.connections}
        for need in ('/ground_truth/odom', '/odom/dead_reckoning'):
            if need not in topics:
                raise ToolError(f'bag {str(bag)!r} has no {need} (a terrain-demo bag has)')
        series = {k: ([], []) for k in TOPICS}
        clock_log, clock_sim, skipped = [], [], 0
        conns = [c for c in reader.connections if c.topic in TOPICS]
        for c, log_ns, raw in reader.messages(connections=conns):
            try:
                m = deserialize_message(bytes(raw), message_class(TOPICS[c.topic]))
                if c.topic == '/clock':
                    clock_log.append(log_ns)
                    clock_sim.append(stamp_to_sec(m.clock))
                    continue
                pose = m.pose.pose if hasattr(m.pose, 'pose') else m.pose
                T = pose_to_matrix(pose)
            except (ValueError, TypeError, AttributeError):
                skipped += 1
                continue
            t = log_ns if c.topic == '/icp/correction' else stamp_to_sec(m.header.stamp)
            series[c.topic][0].append(t)
            series[c.topic][1].append(T)
    finally:
        reader.close()

    def arr(topic):
        t, T = series[topic]
        t = np.asarray(t, np.float64)
        T = np.asarray(T, np.float64).reshape(-1, 4, 4)
        order = np.argsort(t, kind='stable')
        return t[order], T[order]
    d = RunData(course=CourseInfo('', 0, 0.0, 0.0, 0.0, 0.0), robot='')
    d.gt_t, d.gt_T = arr('/ground_truth/odom')
    d.dr_t, d.dr_T = arr('/odom/dead_reckoning')
    ct, cT = arr('/icp/correction')
    if len(ct):
        if not clock_log:
            raise ToolError(f'bag {str(bag)!r} has corrections but no /clock to time them')
        # Receipt on the simulated clock: the last /clock the recorder had logged by then.
        k = np.searchsorted(np.asarray(clock_log), ct, side='right') - 1
        d.corr_t, d.corr_T = np.asarray(clock_sim)[np.maximum(k, 0)], cT
    if skipped:
        d.notes.append(f'{skipped} messages unusable (invalid pose), skipped')
    return d


def format_rows(rows: list) -> str:
    head = (f'{"t [s]":>13} {"x [m]":>6} | {"error mm: along":>15} {"across":>6} {"z":>6} '
            f'{"yaw deg":>7} | {"dr adds: along":>14} {"across":>6} | {"icp adds: along":>15} '
            f'{"across":>6} | {"dr scale":>8} {"corr":>4}')
    out = [head]
    for r in rows:
        sc = f'{r["dr_scale"]:8.3f}' if r['dr_scale'] is not None else f'{"-":>8}'
        out.append(
            f'{r["t0"]:6.1f}-{r["t1"]:6.1f} {r["x"]:6.2f} | {1e3 * r["err_along"]:15.1f} '
            f'{1e3 * r["err_across"]:6.1f} {1e3 * r["err_z"]:6.1f} {r["yaw_err_deg"]:7.2f} | '
            f'{1e3 * r["dr_along"]:14.1f} {1e3 * r["dr_across"]:6.1f} | '
            f'{1e3 * r["icp_along"]:15.1f} {1e3 * r["icp_across"]:6.1f} | {sc} '
            f'{r["corrections"]:4d}')
    return '\n'.join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    ap.add_argument('bag', type=Path, help='rosbag2 directory of a terrain-demo run')
    ap.add_argument('--window', type=float, default=10.0, help='window length [s simulated]')
    ap.add_argument('--json', type=Path, default=None, help='write the rows here')
    args = ap.parse_args(argv)
    from terrain_ros.report import drift_windows
    try:
        d = read_run(args.bag)
        rows = drift_windows(d, args.window)
    except (ToolError, ValueError) as exc:
        return fail(PROG, str(exc))
    if not rows:
        return fail(PROG, f'bag {str(args.bag)!r}: less than one window of ground truth and '
                          f'dead reckoning together')
    print(format_rows(rows))
    for note in d.notes:
        print(note)
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == '__main__':
    sys.exit(main())
