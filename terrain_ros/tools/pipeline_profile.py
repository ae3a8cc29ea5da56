"""Per-node, per-capture CPU profile of the perception pipeline on a recorded bag.

    python -m terrain_ros.tools.pipeline_profile BAG [--captures N] [--warmup K]
        [--robot littledog|frog] [--library-height M] [--json PATH] [--profile STAGE]
        [--profile-out PATH]

``BAG`` is a rosbag2 directory (mcap or sqlite3) as ``terrain-demo`` records into
``<run-dir>/bag`` (a run directory holding ``bag/`` is accepted too).

What it does
------------
The stereo node, ICP mapper, terrain fill and footstep planner are created in this one process
from the project's parameter files (``config/<node>.yaml``), not spun, and the bag's recorded
*inputs* of each node are handed to that node's subscription callbacks in bag order (log time),
deserialised with ``rclpy.serialization`` like the executor does. Every node gets what the
recorded graph gave it (the ICP mapper the recorded ``/stereo/points``, the fill node the
recorded ``/map/fine``...), so each node's figures are independent of the others' and
repeatable run to run. Each callback is timed with ``time.process_time()``: the CPU of every
thread of this process (OpenMP/BLAS workers included), which is what a node costs on a loaded
2-core machine; deserialising the message is part of its callback's time.

Settings as the demo's launch file (``config/launch/sim.yaml``) has them, the stereo node
without a rate limit; the fill node's generated library is cached in
``<repo>/build/cache/fill_library`` and loaded before the replay (not timed). A sink
subscription on ``/map/fine``, ``/map/filled`` and ``/footstep_plan`` makes publishers that
convert only for subscribers do that work, as the next node's subscription does in the graph.
Marker topics get no sink (only viewers and the demo's recorder subscribe to them): their
conversion is not counted; nor are the stereo node's disparity image and RANSAC ground plane,
which it computes only for a subscriber (none in the closed loop's graph; a recorder makes the
node fit the plane, ~13 ms per frame after the clouds are out). Its clouds have the mapper's
and the planner's subscriptions in this process.

Stages (per capture = per left-image stamp; the row's capture is the header stamp of the
message the stage worked on):

    stereo     the image callback that completed a pair, which processes it (no rate limit
               here): disparity, clouds, ground plane
    icp        icp_mapper's /stereo/points callback up to publishing: self filter, ICP, the
               fine map's fusion, map publishing
    icp_model  the coarse model's fusion and index and /map/coarse after publishing (only the
               next capture's ICP needs them; off the chain: the node runs them right
               after, or with ``model_after_plan`` once the capture's plan is out; here
               right after ``icp``)
    fill       terrain_fill's update: whichever callback (/map/fine, /map/capture_poses, or the
               emulated ``process_period_s`` timer) actually ran it
    plan_map   footstep_planner's /map/filled callback: map conversion, cost, replan
    patches    footstep_planner's /stereo/points callback: the cloud's deserialisation and
               its contact patches (placed at the capture's pose in the /icp/pose callback,
               ``plan_pose``, with ``patches_on_pose``)
    plan_goal  footstep_planner's /goal_pose callback (replans on a new goal; per call)

and the small callbacks (odometry, IMU, joint states, stance, pose, camera info, the image
callbacks that did not complete a pair, fill inputs that did not run an update) as totals.
The critical chain is stereo -> icp -> fill -> plan_map: the sum of its medians is the CPU a
capture needs from image to plan with no contention (the loop's wall latency adds queueing).

Reading the figures: a stage's calls are those the recorded graph gave it. The stereo stage runs
on every recorded pair (also pairs the recorded node dropped as stale); the ICP mapper on every
recorded cloud; the fill node on every recorded fine map (only fused captures have one, and the
recorded fill node may have skipped some that it is given here); the planner on the filled maps
the recorded fill node published. So ``calls`` can be below the number of captures, and "per
capture with all four stages" covers the captures the recorded graph carried to a plan. The
process's other threads (DDS, library pools still spinning after a call) are charged to
whatever callback is running; that is why the small callbacks are shown only as totals.

The first ``--warmup`` captures (default 1) are replayed but not counted: their calls load the
patch kernels, build the stereo pipeline and start the maps. ``--captures N`` counts N captures
after them; the replay then continues with everything but new images until the recorded
``/map/filled`` moved past the last counted capture, so the chain's late stages of that capture
are counted too.

The robot profile (camera mount, legs) is ``--robot``, else the one whose stereo baseline
matches the bag's right ``camera_info`` (both profiles use the same joint names, so
``/joint_states`` cannot tell them apart), else the ``robot`` in ``summary.json`` beside the bag,
else littledog. ``--library-height`` defaults to what ``terrain-demo`` uses for the run's course
(``summary.json``; 0.06 m for rocks-6cm or when unknown).

Thread pools: the tool does not touch ``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS``,
``MKL_NUM_THREADS`` or ``OPENCV_FOR_THREADS_NUM``; it runs with the environment it was given and prints (and writes to the
JSON) their values. ``terrain-launch`` sets them to 1 for node processes
(``terrain_ros.env.node_env``); to profile as the nodes run, set them the same way. ``terrain-bench
pipeline`` runs both settings.

Output: a table (stage, calls, CPU ms per call median and p90, total, share of all counted CPU),
CPU per capture and the chain. ``--profile STAGE`` adds cProfile's top 25 (cumulative) for that
stage; only that stage is profiled and its timings include the profiler's overhead.
``--profile-out PATH`` also writes that stage's combined stats (``python -m pstats PATH``,
then ``sort tottime`` / ``stats 30``, or ``snakeviz PATH``).
``--json PATH`` writes the figures (keys: ``stages`` with ``calls``, ``median_ms``, ``p90_ms``,
``total_ms``, ``share``, ``kind``; ``chain``, ``chain_cpu_ms_median_sum``,
``chain_cpu_ms_per_capture_median``, ``cpu_ms_per_capture``, ``per_capture``, ``threads``,
``node_counters``, ...). Errors (no such bag, a bag without the needed topics, an unknown robot):
one line on stderr, exit code 2.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import os
import pstats
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np

from terrain_ros.env import (CONFIG_DIR, NODE_THREAD_DEFAULTS, apply_safe_defaults,
                             params_files)
from terrain_ros.tools.bag import open_reader
from terrain_ros.tools.common import ToolError

PROG = 'pipeline_profile'
REPO = CONFIG_DIR.parent
LIBRARY_CACHE = REPO / 'build' / 'cache' / 'fill_library'
PARAM_FILES = ('stereo_node.yaml', 'icp_mapper.yaml', 'terrain_fill.yaml',
               'footstep_planner.yaml')

CHAIN = ('stereo', 'icp', 'fill', 'plan_map')
STAGES = CHAIN + ('icp_model', 'patches', 'plan_goal')
SMALL = ('stereo_input', 'camera_info', 'icp_odom', 'icp_imu', 'icp_joints', 'icp_coarse',
         'fill_input', 'fill_stance', 'plan_imu', 'plan_pose', 'plan_stance')
# Stages whose calls belong to one capture (the stamp of the message they work on).
PER_CAPTURE = ('stereo', 'icp', 'icp_model', 'fill', 'plan_map', 'patches')

# Topics without which a stage would silently do nothing (or something else).
REQUIRED_TOPICS = {
    '/stereo/left/image_rect': 'sensor_msgs/msg/Image',
    '/stereo/right/image_rect': 'sensor_msgs/msg/Image',
    '/stereo/left/camera_info': 'sensor_msgs/msg/CameraInfo',
    '/stereo/right/camera_info': 'sensor_msgs/msg/CameraInfo',
    '/stereo/points': 'sensor_msgs/msg/PointCloud2',
    '/odom/dead_reckoning': 'nav_msgs/msg/Odometry',
    '/imu/data': 'sensor_msgs/msg/Imu',
    '/map/fine': 'terrain_msgs/msg/TerrainGrid',
    '/map/capture_poses': 'geometry_msgs/msg/PoseArray',
    '/map/filled': 'terrain_msgs/msg/TerrainGrid',
    '/icp/pose': 'geometry_msgs/msg/PoseStamped',
}
# Used when present (the graph runs without them, with less work or other defaults).
OPTIONAL_TOPICS = {
    '/stereo/points_coarse': 'sensor_msgs/msg/PointCloud2',
    '/joint_states': 'sensor_msgs/msg/JointState',
    '/walking/stance': 'terrain_msgs/msg/Stance',
    '/goal_pose': 'geometry_msgs/msg/PoseStamped',
}
# Topics stamped with the capture they come from (skipped past the last counted capture).
CAPTURE_TOPICS = ('/stereo/points', '/stereo/points_coarse', '/map/fine', '/map/capture_poses',
                  '/map/filled', '/icp/pose')
IMAGE_TOPICS = ('/stereo/left/image_rect', '/stereo/right/image_rect')
TAIL_LIMIT_S = 30.0     # bag seconds the replay goes on after the last counted capture at most

Stamp = Tuple[int, int]


class ProfileError(ToolError):
    """A user-facing failure: one line on stderr, exit code 2."""


# ---------------------------------------------------------------------------------------------
# arguments, bag checks, robot


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=f'python -m terrain_ros.tools.{PROG}',
                                description=__doc__.split('\n')[0])
    p.add_argument('bag', type=Path, help='rosbag2 directory (or a run directory holding bag/)')
    p.add_argument('--captures', type=int, default=0,
                   help='captures (left images) to count after the warm-up (default 0 = all)')
    p.add_argument('--warmup', type=int, default=1,
                   help='first captures replayed but not counted (default 1)')
    p.add_argument('--robot', default=None,
                   help='robot profile (littledog | frog; default: from the bag, see above)')
    p.add_argument('--library-height', type=float, default=None, metavar='M',
                   help='height range of the generated fill library [m] (default: the demo\'s '
                        'for the run\'s course, 0.06 for rocks-6cm)')
    p.add_argument('--json', type=Path, default=None, help='write the figures here')
    p.add_argument('--profile', default=None, metavar='STAGE',
                   help=f'print cProfile\'s top 25 cumulative for one stage ({", ".join(STAGES)})')
    p.add_argument('--profile-out', type=Path, default=None, metavar='PATH',
                   help='with --profile: also write that stage\'s combined cProfile stats here '
                        '(pstats format: python -m pstats PATH, snakeviz PATH)')
    return p


def _bag_dir(path: Path) -> Path:
    if not path.exists():
        raise ProfileError(f'bag {str(path)!r} does not exist')
    if path.is_dir() and not (path / 'metadata.yaml').is_file() \
            and (path / 'bag' / 'metadata.yaml').is_file():
        return path / 'bag'
    if path.is_dir() and not (path / 'metadata.yaml').is_file():
        raise ProfileError(f'{str(path)!r} is not a rosbag2 directory (no metadata.yaml)')
    return path


def check_topics(connections) -> Dict[str, str]:
    """{topic: type} of the bag's topics; ProfileError naming every missing or mistyped one."""
    have: Dict[str, str] = {}
    for c in connections:
        have.setdefault(c.topic, c.msgtype)
    missing = [t for t in REQUIRED_TOPICS if t not in have]
    expected = {**REQUIRED_TOPICS, **OPTIONAL_TOPICS}
    wrong = [f'{t} is {have[t]}, not {ty}' for t, ty in expected.items()
             if t in have and have[t] != ty]
    if missing:
        raise ProfileError(f'the bag lacks topic(s) the replay needs: {", ".join(missing)}'
                           + (f'; and {"; ".join(wrong)}' if wrong else ''))
    if wrong:
        raise ProfileError(f'the bag has topic(s) of an unexpected type: {"; ".join(wrong)}')
    return have


def _run_summary(bag: Path) -> dict:
    f = bag.parent / 'summary.json'
    try:
        return json.loads(f.read_text()) if f.is_file() else {}
    except (OSError, ValueError):
        return {}


def _bag_baseline(reader) -> Optional[float]:
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import CameraInfo
    conns = [c for c in reader.connections if c.topic == '/stereo/right/camera_info']
    if not conns:       # rosbags reads every topic for connections=[]
        return None
    for _, _, data in reader.messages(connections=conns):
        P = np.asarray(deserialize_message(bytes(data), CameraInfo).p, float).reshape(3, 4)
        if P[0, 0] > 0 and np.isfinite(P[0, 3]):
            return float(-P[0, 3] / P[0, 0])
        return None
    return None


def choose_robot(requested: Optional[str], reader, bag: Path) -> Tuple[str, str]:
    """(robot profile, where it came from); ProfileError for an unknown one."""
    from terrain_perception.robot_model import available_robots, load_robot_model
    known = available_robots()
    if requested is not None and requested not in known:
        raise ProfileError(f'unknown robot {requested!r} (known: {", ".join(known)})')
    inferred, why = None, ''
    baseline = _bag_baseline(reader)
    if baseline is not None:
        for name in known:
            b = load_robot_model(name).baseline_m
            if abs(baseline - b) <= 0.05 * b:
                inferred, why = name, f'stereo baseline {baseline:.3f} m in camera_info'
                break
    if inferred is None:
        s = _run_summary(bag).get('robot')
        if s in known:
            inferred, why = s, 'summary.json beside the bag'
    if requested is not None:
        if inferred is not None and inferred != requested:
            print(f'{PROG}: note: the bag looks like {inferred}\'s ({why}); profiling with '
                  f'--robot {requested} as asked', file=sys.stderr)
        return requested, '--robot'
    if inferred is not None:
        return inferred, why
    return 'littledog', 'default (not inferable from the bag)'


def choose_library_height(requested: Optional[float], bag: Path) -> Tuple[float, str]:
    if requested is not None:
        if not 0.005 <= requested <= 1.0:
            raise ProfileError(f'--library-height {requested} is outside [0.005, 1.0] m')
        return float(requested), '--library-height'
    from terrain_ros.tools.demo import fill_library_height
    course = _run_summary(bag).get('course')
    if course:   # terrain-demo's rule; None = the launch file's default, 0.06 m
        return fill_library_height(course) or 0.06, f'course {course} (summary.json)'
    return 0.06, 'default (rocks-6cm)'


def thread_settings() -> Dict[str, Optional[str]]:
    """The thread-pool variables of this process (None = unset: the library's default)."""
    return {k: os.environ.get(k) for k in NODE_THREAD_DEFAULTS}


# ---------------------------------------------------------------------------------------------
# the replay


class Replay:
    """The four nodes in one private context, fed from a bag; CPU per callback."""

    def __init__(self, robot: str, library_height_m: float, profile_stage: Optional[str]):
        import rclpy
        from rclpy.context import Context
        from rclpy.parameter import Parameter
        from terrain_msgs.msg import FootstepPlan, TerrainGrid

        from footstep_planner_node.node import FootstepPlannerNode
        from icp_mapper_node.node import IcpMapperNode
        from stereo_node.node import StereoNode
        from terrain_fill_node.node import TerrainFillNode
        from terrain_ros.qos import LATCHED_QOS

        self.ctx = Context()
        args = ['--ros-args']
        for f in PARAM_FILES:
            for path in params_files(f, robot):     # + the robot's overlay, as launched
                args += ['--params-file', str(path)]
        rclpy.init(args=args, context=self.ctx)
        self.nodes: list = []
        try:
            P = Parameter
            # Every recorded pair is processed (no rate limit between the replayed pairs);
            # outputs only for the subscribers the loop's graph has (_wait_for_sink)
            self.S = self._add(StereoNode(context=self.ctx, parameter_overrides=[
                P('max_rate_hz', value=1000.0), P('robot', value=robot)]))
            self.M = self._add(IcpMapperNode(context=self.ctx, parameter_overrides=[
                P('robot', value=robot)]))
            self.F = self._add(TerrainFillNode(context=self.ctx, parameter_overrides=[
                P('library_cache_dir', value=str(LIBRARY_CACHE)),
                P('library_height_range_m', value=float(library_height_m))]))
            self.P = self._add(FootstepPlannerNode(context=self.ctx, parameter_overrides=[
                P('robot', value=robot)]))
            self.sink = self._add(rclpy.create_node('pipeline_profile_sink', context=self.ctx,
                                                    start_parameter_services=False))
        except BaseException:
            self.close()
            raise
        for topic, typ in (('/map/fine', TerrainGrid), ('/map/filled', TerrainGrid),
                           ('/footstep_plan', FootstepPlan)):
            self.sink.create_subscription(typ, topic, lambda _m: None, LATCHED_QOS)
        self.sink_matched = self._wait_for_sink(5.0)
        # stage -> [(stamp of the capture or None, CPU s)]
        self.cpu: Dict[str, List[Tuple[Optional[Stamp], float]]] = {k: [] for k in
                                                                   STAGES + SMALL}
        self.profile_stage = profile_stage
        self.profiles: List[Tuple[Optional[Stamp], cProfile.Profile]] = []
        self.counting = False
        self.library_load_s: Optional[float] = None

    def _add(self, node):
        self.nodes.append(node)
        return node

    def _wait_for_sink(self, timeout_s: float) -> bool:
        pubs = (self.S.pub_points, self.S.pub_coarse, self.M.pub_fine, self.F.pub,
                self.P.pub_plan)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if all(p.get_subscription_count() > 0 for p in pubs):
                return True
            time.sleep(0.02)
        return False

    def close(self) -> None:
        import rclpy
        for n in reversed(self.nodes):
            n.destroy_node()
        self.nodes = []
        rclpy.try_shutdown(context=self.ctx)

    def preload_library(self) -> None:
        """Load (or generate into the cache) the fill library at the fine map's resolution."""
        c0 = time.process_time()
        self.F._ensure_filler(float(self.M.mapper_cfg.fine_resolution_m))
        self.library_load_s = time.process_time() - c0

    def call(self, candidates: Tuple[str, ...], fn, classify) -> None:
        """Run ``fn()`` timed; ``classify()`` then names its stage and capture stamp."""
        prof = (cProfile.Profile() if self.counting and self.profile_stage in candidates
                else None)
        c0 = time.process_time()
        if prof is not None:
            prof.enable()
        try:
            fn()
        finally:
            if prof is not None:
                prof.disable()
            dt = time.process_time() - c0
        stage, stamp = classify()
        if self.counting:
            self.cpu[stage].append((stamp, dt))
            if prof is not None and stage == self.profile_stage:
                self.profiles.append((stamp, prof))

    def simple(self, stage: str, fn, raw: bytes, typ, stamp: Optional[Stamp] = None) -> None:
        """Deserialise + one callback, all of it ``stage``."""
        from rclpy.serialization import deserialize_message
        self.call((stage,), lambda: fn(deserialize_message(raw, typ)), lambda: (stage, stamp))

    def node_counters(self) -> dict:
        S, M, F, P = self.S, self.M, self.F, self.P
        return {
            'stereo': {'frames_processed': S.frames_processed, **dict(S.counters.counts)},
            'icp_mapper': {'captures': M.captures,
                           **{f'mapper_{k}': int(v) for k, v in M.mapper.counters.items()},
                           **dict(M.counters.counts)},
            'terrain_fill': {'updates_published': F.published, 'skipped': F.skipped,
                             **dict(F.counters.counts)},
            'footstep_planner': {'goals_repeated': P.goals_repeated, **dict(P.counters.counts)},
        }


def _message_types() -> Dict[str, type]:
    from geometry_msgs.msg import PoseArray, PoseStamped
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import CameraInfo, Image, Imu, JointState, PointCloud2
    from terrain_msgs.msg import Stance, TerrainGrid
    return {'/stereo/left/image_rect': Image, '/stereo/right/image_rect': Image,
            '/stereo/left/camera_info': CameraInfo, '/stereo/right/camera_info': CameraInfo,
            '/stereo/points': PointCloud2, '/stereo/points_coarse': PointCloud2,
            '/odom/dead_reckoning': Odometry, '/imu/data': Imu, '/joint_states': JointState,
            '/map/fine': TerrainGrid, '/map/capture_poses': PoseArray,
            '/map/filled': TerrainGrid, '/icp/pose': PoseStamped,
            '/walking/stance': Stance, '/goal_pose': PoseStamped}


def run_profile(bag: Path, reader, robot: Tuple[str, str], library_height: Tuple[float, str],
                captures: int, warmup: int, profile_stage: Optional[str],
                profile_out: Optional[Path] = None) -> dict:
    """Replay ``reader``'s bag through the four nodes; the figures of :func:`summarise`.
    ``profile_out``: where to dump the profiled stage's combined cProfile stats."""
    from rclpy.serialization import deserialize_message
    from terrain_ros.conversions import peek_stamp, stamp_key
    types = _message_types()
    wall0, load0 = time.monotonic(), os.getloadavg()
    R = Replay(robot[0], library_height[0], profile_stage)
    try:
        R.preload_library()
        S, M, F, P = R.S, R.M, R.F, R.P
        capture_of: Dict[Stamp, int] = {}      # left-image stamp -> capture index (0-based)
        last = warmup + captures - 1 if captures > 0 else None   # last counted capture
        last_stamp: Optional[Stamp] = None
        tail_start_ns: Optional[int] = None
        fill_dirty_since: Optional[int] = None
        period_ns = int(F.node_cfg.process_period_s * 1e9)
        replay_end = 'end of the bag'
        n_left = 0

        def fill(fn, raw: Optional[bytes], topic: Optional[str]) -> None:
            """A fill callback (or the timer): 'fill' when it ran the update."""
            if topic == '/map/fine':
                key = peek_stamp(raw)
            elif F._grid_msg is not None:
                key = stamp_key(F._grid_msg.header.stamp)
            else:
                key = peek_stamp(raw) if raw is not None else None
            before = (F.published, F.counters['bad_grid'])
            work = (lambda: fn(deserialize_message(raw, types[topic]))) if topic else fn
            R.call(('fill',), work, lambda: (
                ('fill', key) if (F.published, F.counters['bad_grid']) != before
                else ('fill_input', None)))

        def image(side: str, raw: bytes) -> None:
            box = {'pair': False}

            def work():
                msg = deserialize_message(raw, types['/stereo/left/image_rect'])
                taken = S.pairs_taken
                S._on_image(side, msg)            # a completed pair is processed in it
                if S._pending is not None:        # (or waits for the rate timer: run it now)
                    S._on_timer()
                box['pair'] = S.pairs_taken != taken
            stamp = peek_stamp(raw)
            R.call(('stereo',), work, lambda: ('stereo', stamp) if box['pair']
                   else ('stereo_input', None))

        conns = [c for c in reader.connections if c.topic in types]
        for conn, t_ns, data in reader.messages(connections=conns):
            topic, raw = conn.topic, bytes(data)
            # the fill node's process_period_s timer: input it could not pair at once
            if fill_dirty_since is not None and F._dirty \
                    and t_ns - fill_dirty_since >= period_ns:
                fill(F._on_timer, None, None)
                fill_dirty_since = t_ns if F._dirty else None   # held poses: one more period
            if topic in IMAGE_TOPICS:
                if tail_start_ns is not None:
                    continue
                if topic == '/stereo/left/image_rect':
                    if last is not None and n_left > last:
                        tail_start_ns = t_ns      # no more images; let the chain catch up
                        continue
                    last_stamp = peek_stamp(raw)
                    capture_of[last_stamp] = n_left
                    if n_left == warmup:
                        R.counting = True
                    n_left += 1
            elif tail_start_ns is not None:
                if t_ns - tail_start_ns > TAIL_LIMIT_S * 1e9:
                    replay_end = f'{TAIL_LIMIT_S:.0f} s of bag time after the last capture'
                    break
                if topic in CAPTURE_TOPICS and peek_stamp(raw) > last_stamp:
                    if topic == '/map/filled':
                        replay_end = '/map/filled moved past the last counted capture'
                        break
                    continue

            if topic == '/stereo/left/image_rect':
                image('left', raw)
            elif topic == '/stereo/right/image_rect':
                image('right', raw)
            elif topic == '/stereo/left/camera_info':
                R.simple('camera_info', lambda m: S._on_info('left', m), raw, types[topic])
            elif topic == '/stereo/right/camera_info':
                R.simple('camera_info', lambda m: S._on_info('right', m), raw, types[topic])
            elif topic == '/stereo/points':        # each node deserialises its own copy
                R.simple('icp', M._align_and_publish, raw, types[topic], peek_stamp(raw))
                R.call(('icp_model',), M._finish_model,
                       lambda: ('icp_model', peek_stamp(raw)))
                if P.node_cfg.find_patches:
                    R.simple('patches', P._on_cloud, raw, types[topic], peek_stamp(raw))
            elif topic == '/stereo/points_coarse':
                if M.node_cfg.use_coarse_cloud:
                    R.simple('icp_coarse', M._on_coarse, raw, types[topic])
            elif topic == '/odom/dead_reckoning':
                R.simple('icp_odom', M._on_odom, raw, types[topic])
            elif topic == '/imu/data':
                if M.mapper_cfg.use_gravity_prior:
                    R.simple('icp_imu', M._on_imu, raw, types[topic])
                R.simple('plan_imu', P._on_imu, raw, types[topic])
            elif topic == '/joint_states':
                if M.node_cfg.self_filter_margin_m >= 0:
                    R.simple('icp_joints', M._on_joint_state, raw, types[topic])
            elif topic == '/map/fine':
                fill(F._on_grid, raw, topic)
            elif topic == '/map/capture_poses':
                fill(F._on_poses, raw, topic)
            elif topic == '/walking/stance':
                R.simple('fill_stance', F._on_stance, raw, types[topic])
                R.simple('plan_stance', P._on_stance, raw, types[topic])
            elif topic == '/icp/pose':
                R.simple('plan_pose', P._on_pose, raw, types[topic])
            elif topic == '/map/filled':
                R.simple('plan_map', P._plan_on_map, raw, types[topic], peek_stamp(raw))
            elif topic == '/goal_pose':
                R.simple('plan_goal', P._on_goal, raw, types[topic])
            if topic in ('/map/fine', '/map/capture_poses'):
                fill_dirty_since = t_ns if F._dirty else None

        end = n_left if last is None else min(n_left, last + 1)
        counted = max(0, end - warmup)
        counted_of = {s: k for s, k in capture_of.items() if warmup <= k < end}
        cpu = R.cpu
        counters = R.node_counters()
        profile_text = None
        if R.profile_stage is not None:
            # the calls the table counts (a per-capture stage: the counted captures' only)
            profs = [p for s, p in R.profiles
                     if R.profile_stage not in PER_CAPTURE or s in counted_of]
            if profs:
                buf = io.StringIO()
                stats = pstats.Stats(profs[0], stream=buf)
                for p in profs[1:]:
                    stats.add(p)
                if profile_out is not None:
                    profile_out.parent.mkdir(parents=True, exist_ok=True)
                    stats.dump_stats(str(profile_out))
                stats.sort_stats('cumulative').print_stats(25)
                profile_text = buf.getvalue()
            else:
                profile_text = f'({R.profile_stage} never ran in the counted captures)'
        extra = {'sink_matched': R.sink_matched,
                 'library_load_cpu_s': round(R.library_load_s, 3)}
    finally:
        R.close()
    return summarise(cpu, counted_of, counted, bag, robot, library_height, warmup, replay_end,
                     counters, profile_stage, profile_text, time.monotonic() - wall0, load0,
                     extra)


# ---------------------------------------------------------------------------------------------
# figures and table


def _stats(values_s: List[float]) -> dict:
    v = np.asarray(values_s, float) * 1e3
    if v.size == 0:
        return {'calls': 0, 'median_ms': None, 'p90_ms': None, 'total_ms': 0.0}
    return {'calls': int(v.size), 'median_ms': round(float(np.median(v)), 2),
            'p90_ms': round(float(np.percentile(v, 90)), 2), 'total_ms': round(float(v.sum()), 1)}


def summarise(cpu, counted_of: Dict[Stamp, int], counted: int, bag, robot, library_height,
              warmup, replay_end, counters, profile_stage, profile_text, wall_s, load0,
              extra) -> dict:
    """The JSON figures from the per-call CPU times (see the module docstring for the keys)."""
    stages: Dict[str, dict] = {}
    per: Dict[int, Dict[str, float]] = {}
    for name in STAGES + SMALL:
        rows = cpu[name]
        if name in PER_CAPTURE:
            # only work on counted captures (not the warm-up's, not stamps without an image)
            rows = [(counted_of[s], dt) for s, dt in rows if s in counted_of]
            for k, dt in rows:
                d = per.setdefault(k, {})
                d[name] = round(d.get(name, 0.0) + dt * 1e3, 2)
        st = _stats([dt for _, dt in rows])
        st['kind'] = 'stage' if name in STAGES else 'small'
        stages[name] = st
    total = sum(s['total_ms'] for s in stages.values())
    for s in stages.values():
        s['share'] = round(s['total_ms'] / total, 4) if total > 0 else None
    meds = [stages[s]['median_ms'] for s in CHAIN]
    full = [sum(d[s] for s in CHAIN) for d in per.values() if all(s in d for s in CHAIN)]
    load1 = os.getloadavg()
    return {
        'bag': str(bag), 'robot': robot[0], 'robot_source': robot[1],
        'library_height_m': library_height[0], 'library_height_source': library_height[1],
        'captures': counted, 'warmup': warmup, 'replay_end': replay_end,
        'threads': thread_settings(), 'cpu_count': os.cpu_count(),
        'compiled_ik': _compiled_ik(),
        'stages': stages, 'total_cpu_ms': round(total, 1),
        'cpu_ms_per_capture': round(total / counted, 1) if counted else None,
        'chain': list(CHAIN),
        'chain_cpu_ms_median_sum': (round(float(sum(meds)), 1)
                                    if all(m is not None for m in meds) else None),
        'chain_captures_complete': len(full),
        'chain_cpu_ms_per_capture_median': round(float(np.median(full)), 1) if full else None,
        'chain_cpu_ms_per_capture_p90': (round(float(np.percentile(full, 90)), 1)
                                         if full else None),
        'per_capture': [{'capture': k, **per[k]} for k in sorted(per)],
        'node_counters': counters, **extra,
        'profile_stage': profile_stage, 'profile_text': profile_text,
        'wall_s': round(wall_s, 1), 'loadavg_1min': [round(load0[0], 2), round(load1[0], 2)],
    }


def _compiled_ik() -> bool:
    from terrain_perception import kinematics
    return kinematics._ik is not None


def _fmt(v, spec='8.1f') -> str:
    width = int(spec.split('.')[0] or 0)
    return f'{v:{spec}}' if v is not None else f'{"-":>{width}}'


def format_table(r: dict) -> str:
    th = ' '.join(f'{k}={v if v is not None else "unset"}' for k, v in r['threads'].items())
    out = [f'pipeline profile of {r["bag"]}',
           f'robot {r["robot"]} ({r["robot_source"]}); fill library height '
           f'{r["library_height_m"]:g} m ({r["library_height_source"]})',
           f'{r["captures"]} captures counted after {r["warmup"]} warm-up; replay ended: '
           f'{r["replay_end"]}; {r["wall_s"]:.0f} s wall, load average (1 min) '
           f'{r["loadavg_1min"][0]} -> {r["loadavg_1min"][1]}',
           f'threads: {th} (unset = the library\'s default); {r["cpu_count"]} CPUs; leg IK '
           f'{"compiled" if r.get("compiled_ik") else "numpy (TERRAIN_IK_NUMBA=0)"}',
           'CPU per call = time.process_time() of this process (all its threads), '
           'deserialisation included']
    if not r['sink_matched']:
        out.append('WARNING: the sink subscription did not match every publisher within 5 s: '
                   'conversions for subscribers may be missing from the figures')
    if r['profile_stage']:
        out.append(f'(cProfile was on for {r["profile_stage"]}: its times include the '
                   'profiler\'s overhead)')
    out.append('')
    out.append(f'{"stage":14s} {"calls":>6s} {"median ms":>10s} {"p90 ms":>9s} '
               f'{"total ms":>10s} {"share":>7s}')
    st = r['stages']

    def row(name):
        s = st[name]
        share = f'{s["share"] * 100:6.1f}%' if s['share'] is not None else f'{"-":>7s}'
        return (f'{name:14s} {s["calls"]:6d} {_fmt(s["median_ms"], "10.1f")} '
                f'{_fmt(s["p90_ms"], "9.1f")} {s["total_ms"]:10.0f} {share}')
    out += [row(n) for n in STAGES]
    small = [n for n in SMALL if st[n]['calls']]
    if small:
        out.append('small callbacks (totals):')
        out += [row(n) for n in small]
    out.append(f'{"all counted":14s} {"":6s} {"":10s} {"":9s} {r["total_cpu_ms"]:10.0f} '
               f'{"100.0%" if r["total_cpu_ms"] else "-":>7s}')
    out.append('')
    out.append(f'CPU per capture (every counted callback / {r["captures"]} captures): '
               f'{_fmt(r["cpu_ms_per_capture"], ".1f")} ms')
    out.append(f'critical chain {" -> ".join(r["chain"])}: sum of the medians '
               f'{_fmt(r["chain_cpu_ms_median_sum"], ".1f")} ms; per capture with all four '
               f'stages (n={r["chain_captures_complete"]}): median '
               f'{_fmt(r["chain_cpu_ms_per_capture_median"], ".1f")} ms, p90 '
               f'{_fmt(r["chain_cpu_ms_per_capture_p90"], ".1f")} ms')
    c = r['node_counters']
    out.append(f'work done: stereo frames {c["stereo"]["frames_processed"]}, ICP captures '
               f'{c["icp_mapper"]["captures"]}, fill updates '
               f'{c["terrain_fill"]["updates_published"]} (every capture, warm-up included)')
    if r['profile_text']:
        out.append('')
        out.append(f'cProfile of {r["profile_stage"]} (top 25, cumulative):')
        out.append(r['profile_text'].rstrip())
    return '\n'.join(out)


# ---------------------------------------------------------------------------------------------


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    apply_safe_defaults()
    try:
        if args.captures < 0 or args.warmup < 0:
            raise ProfileError('--captures and --warmup must be >= 0')
        if args.profile_out is not None and args.profile is None:
            raise ProfileError('--profile-out needs --profile STAGE')
        if args.profile is not None and args.profile not in STAGES:
            raise ProfileError(f'unknown stage {args.profile!r} for --profile '
                               f'(stages: {", ".join(STAGES)})')
        from terrain_perception.robot_model import available_robots
        if args.robot is not None and args.robot not in available_robots():
            raise ProfileError(f'unknown robot {args.robot!r} '
                               f'(known: {", ".join(available_robots())})')
        bag = _bag_dir(args.bag)
        reader = open_reader(bag)
        try:
            check_topics(reader.connections)
            robot = choose_robot(args.robot, reader, bag)
            height = choose_library_height(args.library_height, bag)
            result = run_profile(bag, reader, robot, height, args.captures, args.warmup,
                                 args.profile, args.profile_out)
        finally:
            reader.close()
    except ToolError as exc:          # ProfileError, or terrain-bag's for an unreadable bag
        print(f'{PROG}: error: {exc}', file=sys.stderr)
        return 2
    if result['captures'] == 0:
        print(f'{PROG}: error: no capture was counted (the bag holds {args.warmup} or fewer '
              'left images, or none paired)', file=sys.stderr)
        return 2
    print(format_table(result), flush=True)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2))
        print(f'{PROG}: figures written to {args.json}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
