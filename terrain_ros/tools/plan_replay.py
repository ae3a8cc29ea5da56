"""``python -m terrain_ros.tools.plan_replay BAG --from T [--span S] [--param NAME:=VALUE ...]
[--dump X0,X1,Y0,Y1] [--json OUT]``: the footstep planner node's inputs from a closed-loop bag,
replayed into its callbacks in one process (no DDS traffic, no spinning), its plans compared
with the ones the bag recorded: a planner parameter tried on the moment a walk went wrong in
seconds, not in a 25-minute loop trial.

The node is built as the launch profiles build it: ``config/footstep_planner.yaml``, the
robot's overlay ``config/footstep_planner.ROBOT.yaml`` if there is one, ``robot:=ROBOT`` (the
bag's, as ``pipeline_profile`` infers it; ``--param robot:=NAME`` overrides),
``walking_config_file:=config/walking_controller.yaml``, then the ``--param`` overrides. It gets
``/walking/stance``, ``/icp/pose``, ``/goal_pose`` and ``/map/filled`` through its own
callbacks, in bag (arrival) order: a stance stamped after a map often reached the planner
before that map did. ``/contact_patches`` has no subscriber in the node (it publishes them):
the recorded patches are set where its detector leaves them (``patches_map`` with the cloud's
stamp), so the detector itself is not replayed. The node's clock (``_now``: the controller's
refusals expire by it) is the newest stamp fed so far. Everything from the bag's start is fed
(the planner keeps state: the goal-less line, the body path, the refused steps); the plans on
the maps stamped in ``[T, T + S]`` are printed, each beside the recorded plan nearest after it
in time (its own map's: plans carry their map's stamp), and counted as agreeing when they
have the same legs in the same order, each position within ``AGREE_M``. The replayed node
publishes nothing (a closed loop on the same domain would take its plans). ``--json`` also
writes the node's resulting configuration (``config``: node, planner and cost parameters).

``--dump X0,X1,Y0,Y1`` prints, after the window, the planner's last map over that box [m]
sampled every ``DUMP_STEP_M``: elevation [cm], cost [x100], the foothold mask (``allowed``:
1 = a candidate), the map's observed / filled layers and its upper bound [cm].
"""

from __future__ import annotations

import argparse
import dataclasses
import difflib
import json
import os
import sys
from pathlib import Path
from typing import Callable, List, Optional, Tuple

import numpy as np

from terrain_ros.env import config_path, params_files
from terrain_ros.tools.common import ToolError, fail

PROG = 'plan_replay'
MAP, PLAN = '/map/filled', '/footstep_plan'
INPUTS = {'/walking/stance': 'terrain_msgs/msg/Stance',
          '/icp/pose': 'geometry_msgs/msg/PoseStamped',
          '/contact_patches': 'terrain_msgs/msg/ContactPatchArray',
          '/goal_pose': 'geometry_msgs/msg/PoseStamped',
          MAP: 'terrain_msgs/msg/TerrainGrid',
          PLAN: 'terrain_msgs/msg/FootstepPlan'}
AGREE_M = 1e-3
DUMP_STEP_M = 0.02
DUMP_MAX_CELLS = 200        # per axis: 4 m at 2 cm, lines of ~800 characters
TAIL_S = 120.0              # the last plan's stamp is looked for in the bag's last 2 min first


def parse_param(text: str) -> str:
    """``NAME:=VALUE`` as ``ros2 run ... -p`` takes it (VALUE in YAML); ToolError otherwise."""
    import yaml
    if ':=' not in text or not text.split(':=', 1)[0]:
        raise ToolError(f'--param {text!r}: expected NAME:=VALUE')
    try:
        yaml.safe_load(text.split(':=', 1)[1])
    except yaml.YAMLError:      # rcl would refuse it with a multi-line log
        raise ToolError(f'--param {text!r}: the value is not valid YAML') from None
    return text


def parse_dump(text: str) -> Tuple[float, float, float, float]:
    """``'X0,X1,Y0,Y1'`` [m] -> a box; ToolError naming the problem otherwise."""
    try:
        x0, x1, y0, y1 = (float(v) for v in text.split(','))
    except ValueError:
        raise ToolError(f'--dump {text!r}: expected X0,X1,Y0,Y1 (metres)') from None
    if not all(np.isfinite([x0, x1, y0, y1])) or x1 <= x0 or y1 <= y0:
        raise ToolError(f'--dump {text!r}: need finite X0 < X1 and Y0 < Y1')
    if max(x1 - x0, y1 - y0) / DUMP_STEP_M + 1 > DUMP_MAX_CELLS:
        raise ToolError(f'--dump {text!r}: at most {DUMP_MAX_CELLS} samples a side '
                        f'({(DUMP_MAX_CELLS - 1) * DUMP_STEP_M:.2f} m at {DUMP_STEP_M} m)')
    return x0, x1, y0, y1


def _sec(key: Tuple[int, int]) -> float:
    return key[0] + 1e-9 * key[1]


def _steps(msg) -> list:
    """The footsteps of a terrain_msgs/FootstepPlan as ``[{leg, x, y, z}]``."""
    return [{'leg': int(f.leg), 'x': f.position.x, 'y': f.position.y, 'z': f.position.z}
            for f in msg.footsteps]


def plans_agree(a: list, b: list, tol_m: float = AGREE_M) -> bool:
    """Same legs in the same order, each position within ``tol_m`` [m] (3-D distance)."""
    return (len(a) == len(b) and all(p['leg'] == q['leg'] for p, q in zip(a, b))
            and all(np.hypot(np.hypot(p['x'] - q['x'], p['y'] - q['y']), p['z'] - q['z'])
                    <= tol_m for p, q in zip(a, b)))


def msg_to_patches(msg):
    """A core PatchSet of a terrain_msgs/ContactPatchArray (the node's ``patches_to_msg``
    inverse; the rims are not read back)."""
    from terrain_perception.patches import PatchSet
    from terrain_ros.conversions import pose_to_matrix
    P = msg.patches
    T = np.array([pose_to_matrix(c.pose) for c in P]).reshape(-1, 4, 4)

    def f(name):
        return np.array([getattr(c, name) for c in P], dtype=np.float64)
    g, x = msg.gravity, msg.fixation_point
    return PatchSet(vertex=T[:, :3, 3].copy(), R=T[:, :3, :3].copy(), kx=f('kx'), ky=f('ky'),
                    radius=f('radius'), residual=f('residual'), don=f('don'), dong=f('dong'),
                    fixation_distance=f('fixation_distance'),
                    support_points=np.array([c.support_points for c in P], dtype=np.int64),
                    gravity=np.array([g.x, g.y, g.z]), fixation=np.array([x.x, x.y, x.z]))


class _Sink:
    """Stands in for a publisher of the replayed node: keeps (or drops) what it would send."""

    def __init__(self, keep: Optional[list] = None) -> None:
        self.keep = keep

    def publish(self, msg) -> None:
        if self.keep is not None:
            self.keep.append(msg)

    def get_subscription_count(self) -> int:
        return 0


def _last_plan_stamp(reader, conn) -> Optional[Tuple[int, int]]:
    from terrain_ros.conversions import peek_stamp
    for start in (reader.end_time - int(TAIL_S * 1e9), None):
        last = None
        for _, _, raw in reader.messages(connections=[conn], start=start):
            last = max(last or (-1, 0), peek_stamp(raw))
        if last is not None:
            return last
    return None


def replay(bag: Path, t_from: float, span: float, params: List[str],
           dump: Optional[tuple] = None, note: Callable[[str], None] = print) -> dict:
    """Replay ``bag``'s planner inputs; see the module docstring. Returns the figures (the
    ``--json`` content) plus ``lines`` (the printed plans, in bag order) and the ``dump``
    text."""
    import rclpy
    from terrain_ros.tools.bag import open_reader
    try:
        reader = open_reader(str(bag))
    except ToolError as exc:
        raise ToolError(f'cannot open bag: {exc}') from None
    try:
        by_topic = {c.topic: c for c in reader.connections if c.topic in INPUTS}
        for need in (MAP, PLAN):
            if need not in by_topic:
                raise ToolError(f'bag {str(bag)!r} has no {need} (a terrain-demo bag has)')
        for topic, c in by_topic.items():
            if c.msgtype != INPUTS[topic]:
                raise ToolError(f'bag {str(bag)!r}: {topic} is {c.msgtype}, the planner '
                                f'takes {INPUTS[topic]}')
        for topic in INPUTS:
            if topic not in by_topic:
                note(f'note: the bag has no {topic}: the replayed planner gets none')
        last = _last_plan_stamp(reader, by_topic[PLAN])
        if last is None:
            raise ToolError(f'bag {str(bag)!r} holds no {PLAN} message')
        if t_from > _sec(last):
            raise ToolError(f'--from {t_from:g} s is after the bag\'s last plan '
                            f'({_sec(last):.3f} s)')
        given = {p.split(':=', 1)[0]: p.split(':=', 1)[1] for p in params}
        if 'robot' in given:
            robot, why = given['robot'], '--param'
        else:
            from terrain_ros.tools.pipeline_profile import choose_robot
            robot, why = choose_robot(None, reader, bag)
        ros = ['--ros-args']
        for f in params_files('footstep_planner.yaml', robot):
            ros += ['--params-file', str(f)]
        ros += ['-p', f'robot:={robot}',
                '-p', f'walking_config_file:={config_path("walking_controller.yaml")}']
        for p in params:
            ros += ['-p', p]
        try:
            rclpy.init(args=[PROG, *ros])
        except Exception as exc:  # noqa: BLE001 - rcl's argument parser raises RCLError
            raise ToolError(f'--param: {exc}') from None
        try:
            return _run(reader, by_topic, t_from, span, params, dump, robot, why)
        finally:
            rclpy.try_shutdown()
    finally:
        reader.close()


def _run(reader, by_topic, t_from, span, params, dump, robot, why) -> dict:
    from rclpy.serialization import deserialize_message
    from footstep_planner_node.node import FootstepPlannerNode
    from terrain_ros.conversions import peek_stamp
    from terrain_ros.tools.common import message_class
    try:
        node = FootstepPlannerNode()
    except ValueError as exc:   # a refused parameter value or an unknown robot
        hint = (' (write a floating-point value with a point: 1.0)'
                if "type 'INTEGER', expecting type 'DOUBLE'" in str(exc) else '')
        raise ToolError(f'{exc}{hint}') from None
    try:
        for p in params:
            name = p.split(':=', 1)[0]
            if not node.has_parameter(name):
                known = node.list_parameters([], 0).names
                close = difflib.get_close_matches(name, known, 1)
                raise ToolError(f'--param {p!r}: the planner has no parameter {name!r}'
                                + (f' (did you mean {close[0]!r}?)' if close else ''))
        published: list = []
        node.pub_plan = _Sink(published)
        for attr in ('pub_plan_markers', 'pub_patches', 'pub_patch_markers', 'pub_cost',
                     'pub_body_path'):
            setattr(node, attr, _Sink())
        clock = [-np.inf]
        node._now = lambda: clock[0]
        classes = {t: message_class(n) for t, n in INPUTS.items()}
        callbacks = {'/walking/stance': node._on_stance, '/icp/pose': node._on_pose,
                     '/goal_pose': node._on_goal}
        end = t_from + span
        ours, bag, events = [], [], []

        def feed(topic, key, t, raw):
            clock[0] = max(clock[0], t)
            msg = deserialize_message(raw, classes[topic])
            if topic == MAP:
                k = len(published)
                node._on_map(msg)
                if t >= t_from and len(published) > k:
                    plan = published[-1]
                    ours.append({'key': key, 'stamp': t, 'ours': _steps(plan),
                                 'ours_status': plan.status_text})
                    events.append(('ours', ours[-1]))
            elif topic == '/contact_patches':
                # where the node's detector keeps them: map-frame patches only (without a
                # pose it publishes them in the camera frame and keeps none)
                frame = node.grid.frame_id if node.grid is not None else 'map'
                if msg.header.frame_id == frame:
                    node.patches_map, node.patches_stamp = msg_to_patches(msg), t
            else:
                callbacks[topic](msg)

        for c, _, raw in reader.messages(connections=list(by_topic.values())):
            raw = bytes(raw)
            key = peek_stamp(raw)
            t = key[0] + 1e-9 * key[1]
            if c.topic == PLAN:
                if t >= t_from:     # earlier ones cannot be after a plan of the window
                    m = deserialize_message(raw, classes[PLAN])
                    bag.append({'key': key, 'stamp': t, 'bag': _steps(m),
                                'bag_status': m.status_text})
                    if t > end:
                        break       # every map of the window has had its plan
                    events.append(('bag', bag[-1]))
            elif c.topic != MAP or t <= end:    # a later map's plan is after the window
                feed(c.topic, key, t, raw)
        dump_text = _dump(node, dump) if dump is not None else None
        counters = dict(node.counters.counts)
        config = {'node': dataclasses.asdict(node.node_cfg),
                  'planner': dataclasses.asdict(node.plan_cfg),
                  'cost': dataclasses.asdict(node.cost_cfg)}
    finally:
        node.destroy_node()
    # each of our plans against the recorded plan nearest after it: its own map's (the same
    # stamp, published first), unless the recording lost that one
    bag.sort(key=lambda b: b['key'])      # stable: a map's own plan before a goal's replan
    for o in ours:
        b = next((b for b in bag if b['key'] >= o['key']), None)
        o.update({'bag': None, 'bag_stamp': None, 'bag_status': None, 'agree': False}
                 if b is None else
                 {'bag': b['bag'], 'bag_stamp': b['stamp'], 'bag_status': b['bag_status'],
                  'agree': plans_agree(o['ours'], b['bag'])})
    plans = [{k: v for k, v in o.items() if k != 'key'} for o in ours]
    compared = [p for p in plans if p['bag'] is not None]
    return {'plans': plans, 'compared': len(compared),
            'agree': sum(p['agree'] for p in compared), 'window_s': [t_from, end],
            'params': list(params), 'robot': robot, 'robot_from': why, 'config': config,
            'counters': counters,
            'lines': [(kind, {k: v for k, v in e.items() if k != 'key'})
                      for kind, e in events],
            'dump': dump_text}


def _dump(node, box) -> str:
    """Text grids of the planner's last map layers over ``box`` (see the module docstring)."""
    from terrain_perception.grid import ELEVATION, FILLED, OBSERVED, UPPER_BOUND
    pl = node.planner
    g = pl.grid
    if g is None:
        return 'dump: the planner has no usable map'
    x0, x1, y0, y1 = box
    xs = x0 + DUMP_STEP_M * np.arange(int(np.floor((x1 - x0) / DUMP_STEP_M + 1e-9)) + 1)
    ys = y0 + DUMP_STEP_M * np.arange(int(np.floor((y1 - y0) / DUMP_STEP_M + 1e-9)) + 1)
    X, Y = np.meshgrid(xs, ys[::-1], indexing='xy')          # rows: y from the top down
    ij = g.world_to_index(np.stack([X, Y], -1))
    on = g.inside(ij)
    ii, jj = np.where(on, ij[..., 0], 0), np.where(on, ij[..., 1], 0)
    layers = [('elevation [cm]', 100.0, g.layers.get(ELEVATION)),
              ('cost [x100]', 100.0, pl.cost),
              ('allowed (foothold candidate)', 1.0, pl.allowed),
              ('observed', 1.0, g.layers.get(OBSERVED)),
              ('filled', 1.0, g.layers.get(FILLED)),
              ('upper bound [cm]', 100.0, g.layers.get(UPPER_BOUND))]
    out = [f'map stamp {g.stamp_s:.3f} s, {g.resolution_m * 100:g} cm cells; columns x [cm], '
           f'rows y [m]; "nan" unknown, blank off the map']
    head = '       ' + ''.join(f'{100 * x:4.0f}' for x in xs)
    for name, scale, arr in layers:
        out.append(name)
        if arr is None:
            out.append('  (the map has no such layer)')
            continue
        v = scale * np.asarray(arr, dtype=np.float64)[ii, jj]
        out.append(head)
        for r, y in enumerate(ys[::-1]):
            out.append(f'{y:+6.2f} ' + ''.join(_cell(v[r, k], on[r, k]) for k in range(len(xs))))
    return '\n'.join(out)


def _cell(v: float, on: bool) -> str:
    if not on:
        return '    '
    if np.isnan(v):
        return ' nan'
    if not -99.5 < v < 999.5:
        return ' big' if v > 0 else '-big'
    return f'{v:4.0f}'


def _fmt_steps(steps: list) -> str:
    from terrain_perception.robot_model import LEG_NAMES
    return ' '.join(f'{LEG_NAMES[s["leg"]]}:({s["x"]:.3f},{s["y"]:+.3f})' for s in steps)


def report_lines(out: dict) -> List[str]:
    """The printed report of :func:`replay`'s figures."""
    lines = []
    for kind, p in out['lines']:
        steps = p[kind]
        status = p[f'{kind}_status']
        if kind == 'ours':
            tag = ('agrees' if p['agree'] else
                   'no bag plan after it' if p['bag'] is None else
                   f'DIFFERS from bag {p["bag_stamp"]:.3f}')
            status = f'[{tag}] {status}'
        lines.append(f'{p["stamp"]:9.3f} {kind:4s} n={len(steps)} {_fmt_steps(steps)}'
                     f'  | {status}')
    t0, t1 = out['window_s']
    lines.append(f'{out["compared"]} plans in [{t0:.3f}, {t1:.3f}] s compared, {out["agree"]} '
                 f'agree with the bag plan nearest after them (same legs in order, positions '
                 f'within {1000 * AGREE_M:g} mm)'
                 + ('' if out['compared'] == len(out['plans']) else
                    f'; {len(out["plans"]) - out["compared"]} without a bag plan after them'))
    if out['dump'] is not None:
        lines.append(out['dump'])
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    ap.add_argument('bag', type=Path, help='rosbag2 directory of a terrain-demo run')
    ap.add_argument('--from', dest='t_from', type=float, required=True, metavar='T',
                    help='first map stamp [s] whose plans are compared (bag time)')
    ap.add_argument('--span', type=float, default=1.0, metavar='S',
                    help='compare the plans of the maps stamped in [T, T + S] (default 1 s)')
    ap.add_argument('--param', action='append', default=[], metavar='NAME:=VALUE',
                    help='footstep_planner parameter override (repeatable), e.g. '
                         'planner.lateral_search_m:=0.05')
    ap.add_argument('--dump', default=None, metavar='X0,X1,Y0,Y1',
                    help='after the window, print the planner\'s map layers over this box [m]')
    ap.add_argument('--json', type=Path, default=None, help='write the figures here')
    args = ap.parse_args(argv)
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    try:
        params = [parse_param(p) for p in args.param]
        if not np.isfinite(args.t_from) or not (np.isfinite(args.span) and args.span >= 0):
            raise ToolError(f'--from {args.t_from:g} --span {args.span:g}: need finite values '
                            f'and a span >= 0')
        dump = None if args.dump is None else parse_dump(args.dump)
        out = replay(args.bag, args.t_from, args.span, params, dump,
                     note=lambda s: print(f'{PROG}: {s}', file=sys.stderr))
    except ToolError as exc:
        return fail(PROG, str(exc))
    print(f'robot {out["robot"]} ({out["robot_from"]}); parameters: '
          + (' '.join(out['params']) or 'the config files\''))
    for line in report_lines(out):
        print(line)
    if args.json is not None:
        keep = {k: v for k, v in out.items() if k not in ('lines', 'dump')}
        args.json.write_text(json.dumps(keep, indent=2, default=float))
    return 0


if __name__ == '__main__':
    sys.exit(main())
