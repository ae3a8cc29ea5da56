"""``terrain-demo``: the closed loop in simulation, recorded and reported (``make demo``).

Starts the node graph of ``config/launch/sim.yaml`` (simulator bridge, stereo, ICP mapper,
terrain fill, footstep planner, walking controller: one process each, all on the simulator's
``/clock``), records every topic to an mcap bag, watches the run and writes the report::

    terrain-demo [--robot littledog] [--course rocks-6cm] [--seed 0] [--run-dir DIR]
                 [--max-sim-time 240] [--timeout 840] [--image-scale 1.0] [--no-bag]
                 [--real-time-factor 0.2] [--stall-time 60] [--blind] [--replay BAG]

Run directory (default ``runs/<date>-<robot>-<course>-s<seed>``)::

    summary.json, heightmaps.png, footsteps.png, path.png   the report (terrain_ros.report)
    bag/                                                    rosbag2 (mcap) of every topic
    logs/<node>.log, logs/bag.log                           each process's output
    launch.yaml                                             the launch file as run

The simulator is capped at ``--real-time-factor`` simulated seconds per wall second so that
every node keeps up with the simulated clock on a small machine.

The run ends when the robot has crossed (the true base is past the rough section by the hind
legs' reach, with no fall before nor within 1 s after: ``WalkEnd``), has fallen, has not
advanced 1 cm for ``--stall-time`` simulated seconds, the simulated time reaches
``--max-sim-time``, the wall time reaches ``--timeout``, the simulator stops, or on Ctrl-C (a
second Ctrl-C stops at once). Then the recorder gets SIGINT (so the bag is closed cleanly), the
nodes are stopped, and the report is written from what the demo's monitor received. A node that
is not installed, dies or keeps restarting is named in the summary; metrics and figures it
would have fed are reported as missing, never filled in. Exit code: 0 when the report was
written (with ``--strict``: 1 if the robot did not cross), 2 when the run could not start.

``--replay BAG`` instead plays a recorded bag (with its ``/clock``) through the perception and
planning nodes of ``config/launch/replay.yaml`` and writes the same report.

Discovery stays on this host (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``) unless the
environment says otherwise; set ``ROS_DOMAIN_ID`` to keep parallel runs apart.
"""

from __future__ import annotations

import argparse
import functools
import importlib.metadata
import importlib.util
import os
import signal
import struct
import subprocess
import sys
import threading
import time
from datetime import datetime
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
import yaml

from terrain_ros.env import CONFIG_DIR, safe_env
from terrain_ros.tools.common import ToolError, fail
from terrain_ros.tools.launch import (Launcher, NodeSpec, _die_with_parent, _find_file,
                                      child_setup, load_launch_file)

PROG = 'terrain-demo'
REPO_DIR = CONFIG_DIR.parent
LAUNCH_DIR = CONFIG_DIR / 'launch'


# ---------------------------------------------------------------------------------------------
# options


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split('\n')[0])
    p.add_argument('--robot', default='littledog', help='robot profile (littledog | frog)')
    p.add_argument('--course', default='rocks-6cm',
                   help='course class: rocks-6cm | rocks-12cm | stones-15cm | flat')
    p.add_argument('--seed', type=int, default=0, help='course seed (default 0)')
    p.add_argument('--run-dir', type=Path, default=None,
                   help='output directory (default runs/<date>-<robot>-<course>-s<seed>)')
    p.add_argument('--max-sim-time', type=float, default=240.0,
                   help='stop after this much simulated time [s] (default 240; at the default '
                        'real-time factor the wall-time limit comes first)')
    p.add_argument('--timeout', type=float, default=840.0,
                   help='stop after this much wall time, start-up included [s] (default 840)')
    p.add_argument('--image-scale', type=float, default=1.0,
                   help='camera resolution relative to the robot profile (default 1)')
    p.add_argument('--real-time-factor', type=float, default=0.2,
                   help='cap on simulated seconds per wall second, so the nodes keep up with '
                        'the simulated clock (default 0.2; 0 = as fast as possible)')
    p.add_argument('--stall-time', type=float, default=60.0,
                   help='end the run when the robot has not advanced 1 cm in this much '
                        'simulated time [s] (default 60)')
    p.add_argument('--camera-rate', type=float, default=0.0,
                   help='periodic captures per simulated second (default: the profile\'s)')
    p.add_argument('--launch', type=Path, default=None,
                   help='launch file (default config/launch/sim.yaml, or replay.yaml with '
                        '--replay)')
    p.add_argument('--arg', action='append', default=[], metavar='NAME:=VALUE',
                   help='extra launch argument (repeatable)')
    p.add_argument('--param', action='append', default=[], metavar='NODE:NAME:=VALUE',
                   help='set one node parameter over its config file (repeatable), e.g. '
                        'walking_controller:touchdown_verify_s:=0.0')
    p.add_argument('--replay', type=Path, default=None, metavar='BAG',
                   help='play this bag through the perception/planning nodes instead of '
                        'simulating')
    p.add_argument('--replay-rate', type=float, default=1.0,
                   help='bag playback rate with --replay (default 1)')
    p.add_argument('--no-bag', action='store_true', help='do not record a bag')
    p.add_argument('--recorder-nice', type=int, default=10, choices=range(0, 20),
                   metavar='0-19',
                   help='CPU priority of the bag recorder (default 10: it yields the CPU to '
                        'the nodes while a capture goes through them and catches up after; '
                        'a bag written late is fine, a plan made late is not)')
    p.add_argument('--blind', action='store_true',
                   help='benchmark variant: the planner and controller get a flat map '
                        '(/map/blind, published here on every /map/fine) instead of '
                        '/map/filled')
    p.add_argument('--no-goal', action='store_true',
                   help='do not publish /goal_pose (1 m past the finish line, on the '
                        'course\'s centre line); the planner then goes straight ahead')
    p.add_argument('--progress-period', type=float, default=5.0,
                   help='seconds between progress lines (default 5)')
    p.add_argument('--quiet', action='store_true', help='no progress lines')
    p.add_argument('--strict', action='store_true',
                   help='exit code 1 when the robot did not cross (default: 0 once the report '
                        'is written)')
    return p


# ---------------------------------------------------------------------------------------------
# course geometry


def course_info(course: str, seed: int, robot: str):
    """Start, rough section and finish line (x, ``map``) of a course for a robot."""
    from terrain_perception.robot_model import load_robot_model
    from terrain_perception.terrain import COURSE_CLASSES
    from terrain_ros.report import CourseInfo
    model = load_robot_model(robot)
    cfg = COURSE_CLASSES.get(course)
    approach, rough = (cfg.approach_m, cfg.rough_length_m) if cfg else (1.0, 1.0)
    start = 0.4
    bridge = yaml.safe_load((CONFIG_DIR / 'sim_bridge.yaml').read_text()) or {}
    start = float(bridge.get('sim_bridge', {}).get('ros__parameters', {})
                  .get('start_x_m', start))
    # Crossed = the hind feet (at about the hind hips) are past the rough section.
    hind = float(max(-model.hip_offsets[:, 0].min(), 0.0))
    finish = approach + rough + hind + 2.0 * model.foot_radius_m + 0.03
    return CourseInfo(course, seed, start, approach, approach + rough, finish), model


def fill_library_height(course: str) -> Optional[float]:
    """Height range of the fill library's tiles for a course class: the class's own for the
    taller courses, None for the launch file's default (0.06 m, rocks-6cm)."""
    if course in ('rocks-12cm', 'stones-15cm'):
        from terrain_perception.terrain import COURSE_CLASSES
        return float(COURSE_CLASSES[course].max_height_m)
    return None


def fill_cost_config():
    """The CostConfig the fill node runs with (config/terrain_fill.yaml ``cost.*``)."""
    from terrain_perception.config import make_config
    from terrain_perception.features import CostConfig
    data = yaml.safe_load((CONFIG_DIR / 'terrain_fill.yaml').read_text()) or {}
    params = data.get('terrain_fill', {}).get('ros__parameters', {})
    sub = {k[len('cost.'):]: v for k, v in params.items() if k.startswith('cost.')}
    sub.update(params.get('cost', {}) if isinstance(params.get('cost'), dict) else {})
    return make_config(CostConfig, sub)


# ---------------------------------------------------------------------------------------------
# pre-flight: which nodes can start at all


def _entry_module(executable: str) -> Optional[str]:
    for ep in importlib.metadata.entry_points(group='console_scripts'):
        if ep.name == executable:
            return ep.value.split(':')[0]
    return None


def preflight(launch_file: Path, out_file: Path) -> Dict[str, dict]:
    """Copy the launch file to ``out_file`` without the nodes that cannot start.

    A node whose console script is not installed or whose module does not exist is left out
    (state ``missing`` with the reason); a parameter file that does not exist is dropped from
    its node, which then runs on its built-in defaults (noted). Returns node -> status."""
    data = yaml.safe_load(launch_file.read_text()) or {}
    status: Dict[str, dict] = {}
    keep = []
    bindir = Path(sys.executable).parent
    for n in data.get('nodes') or []:
        name = n.get('name', '?')
        exe = n.get('executable')
        if exe:
            module = _entry_module(exe)
            if not (bindir / exe).exists():
                status[name] = {'state': 'missing', 'reason': f'console script {exe!r} is '
                                                              'not installed'}
                continue
            if module is None or importlib.util.find_spec(module.split('.')[0]) is None \
                    or _find_spec(module) is None:
                status[name] = {'state': 'missing',
                                'reason': f'module {module!r} of {exe!r} does not exist yet'}
                continue
        params = []
        for f in n.get('params') or []:
            f = str(f)
            # an optional file ('NAME.yaml?') is the launcher's to find, or to skip
            if f.endswith('?') or _find_file(f, launch_file.parent, optional=True):
                params.append(f)
            else:
                status.setdefault(name, {})['note'] = (
                    f'parameter file {f!r} not found: node runs on its defaults')
        if n.get('params'):
            n['params'] = params
        keep.append(n)
        status.setdefault(name, {})['state'] = 'pending'
    data['nodes'] = keep
    out_file.write_text(yaml.safe_dump(data, sort_keys=False))
    return status


def _find_spec(module: str):
    try:
        return importlib.util.find_spec(module)
    except (ImportError, ValueError):
        return None


# ---------------------------------------------------------------------------------------------
# processes


class LoggedLauncher(Launcher):
    """terrain-launch's Launcher with each node's output in ``logs/<name>.log`` and a record of
    every process it started (for the report)."""

    def __init__(self, specs: List[NodeSpec], log_dir: Path, grace_s: float = 5.0) -> None:
        super().__init__(specs, grace_s)
        self.log_dir = log_dir
        self.procs: Dict[str, List[subprocess.Popen]] = {s.name: [] for s in specs}
        self._logs = []

    def _start(self, item) -> None:
        log = open(self.log_dir / f'{item.spec.name}.log', 'a', buffering=1)
        log.write(f'--- {datetime.now().isoformat(timespec="seconds")} start: '
                  f'{" ".join(item.spec.command)}\n')
        self._logs.append(log)
        proc = subprocess.Popen(item.spec.command, env=item.spec.env, stdout=log,
                                stderr=subprocess.STDOUT, preexec_fn=child_setup(item.spec))
        item.proc = proc
        self.procs[item.spec.name].append(proc)

    def alive(self, name: str) -> bool:
        ps = self.procs.get(name) or []
        return bool(ps) and ps[-1].poll() is None

    def pid(self, name: str) -> Optional[int]:
        ps = self.procs.get(name) or []
        return ps[-1].pid if ps and ps[-1].poll() is None else None

    def node_states(self) -> Dict[str, dict]:
        """Per node: ``ran`` (one process, alive now), ``restarted`` (alive, but earlier
        processes exited), ``exited`` (not running now), with exit codes and the log's tail."""
        out = {}
        for name, ps in self.procs.items():
            codes = [p.returncode for p in ps if p.poll() is not None]
            alive = bool(ps) and ps[-1].poll() is None
            st = {'starts': len(ps), 'exit_codes': codes}
            if alive and not codes:
                st['state'] = 'ran'
            elif alive:
                st['state'] = 'restarted'
                st['reason'] = (f'exited {len(codes)} time(s) (codes {codes}) and was '
                                f'respawned; last error: {_log_tail(self.log_dir, name)}')
            else:
                st['state'] = 'exited' if ps else 'never started'
                st['reason'] = (f'exit code {codes[-1] if codes else "?"}: '
                                f'{_log_tail(self.log_dir, name)}')
            out[name] = st
        return out

    def close_logs(self) -> None:
        for f in self._logs:
            try:
                f.close()
            except OSError:
                pass


def _log_tail(log_dir: Path, name: str) -> str:
    """The most telling line at the end of a node's log (an error line if there is one)."""
    try:
        lines = [ln.strip() for ln in (log_dir / f'{name}.log').read_text(
            errors='replace').splitlines() if ln.strip() and not ln.startswith('---')]
    except OSError:
        return 'no log'
    tail = lines[-40:]
    for ln in reversed(tail):
        if any(w in ln for w in ('Error', 'error', 'Exception', 'Traceback')):
            return ln[:300]
    return tail[-1][:300] if tail else 'empty log'


def start_recorder(bag_dir: Path, log_dir: Path, env: Dict[str, str],
                   nice: int = 0) -> subprocess.Popen:
    """``terrain-bag record -a -o bag_dir`` in its own process group (logs/bag.log), at CPU
    priority ``nice`` (0-19)."""
    exe = Path(sys.executable).parent / 'terrain-bag'
    log = open(log_dir / 'bag.log', 'w', buffering=1)
    return subprocess.Popen([str(exe), 'record', '-a', '-o', str(bag_dir)], env=env,
                            stdout=log, stderr=subprocess.STDOUT,
                            preexec_fn=functools.partial(_die_with_parent, nice))


def stop_process(proc: subprocess.Popen, sig=signal.SIGINT, wait_s: float = 20.0) -> int:
    """Signal a process group, escalate to SIGTERM and SIGKILL; return the exit code."""
    for s, w in ((sig, wait_s), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
        if proc.poll() is not None:
            break
        try:
            os.killpg(proc.pid, s)
        except ProcessLookupError:
            break
        try:
            proc.wait(timeout=w)
        except subprocess.TimeoutExpired:
            continue
    return proc.wait()


# ---------------------------------------------------------------------------------------------
# the monitor: an in-process node that watches the run and keeps what the report needs


def fast_executor(context):
    """rclpy's EventsExecutor where available, else the single-threaded one
    (:func:`terrain_ros.node.make_executor`, whatever ``TERRAIN_EXECUTOR`` says: a subscriber
    of many topics keeps up far better with it)."""
    from terrain_ros.node import make_executor
    return make_executor(context, 'events')


#: The pipeline's outputs in order; a capture's stamp travels along them (stereo -> ICP mapper
#: -> terrain fill -> footstep planner).
IMAGE_TOPIC = '/stereo/left/image_rect'
STAGE_TOPICS = ('/stereo/points', '/map/fine', '/map/filled', '/footstep_plan')
STAGE_NAMES = ('stereo', 'icp_mapper', 'terrain_fill', 'footstep_planner')
#: the nodes whose ~/diagnostics counters go into summary.json (``node_counters``)
COUNTER_NODES = ('sim_bridge', 'stereo_node', 'icp_mapper', 'terrain_fill', 'footstep_planner',
                 'walking_controller')


def stage_latencies(image_wall: Dict[tuple, float],
                    stage_wall: Dict[str, Dict[tuple, float]]) -> Dict[str, List[float]]:
    """Wall ms each node added per capture: first arrival of the stamp on its output minus on
    its input (the left image for the stereo node), over the captures that reached it."""
    out: Dict[str, List[float]] = {}
    prev = image_wall
    for name, topic in zip(STAGE_NAMES, STAGE_TOPICS):
        cur = stage_wall.get(topic, {})
        out[name] = [1000.0 * (cur[k] - prev[k]) for k in cur if k in prev]
        prev = cur
    return out


# The goal is a point on the course's centre line this far past the finish line [m]. A point
# just past the line (it was 0.1 m) makes the planner turn in towards it over the last steps:
# run AB, 5 cm off the centre line and 20 cm from that point, turned 14 deg, stalled for 22 s
# with its stance narrowed and fell 5 cm before the line; ground-truth walk seed 5 veered 0.5 m
# sideways near its goal and crossed with the goal 1 m ahead.
GOAL_BEYOND_FINISH_M = 1.0


class Monitor:
    """Subscribes the graph's outputs and ground truth (wall clock, no sim time)."""

    def __init__(self, model, finish_x: float, publish_goal: bool,
                 domain_id: Optional[int] = None, blind: bool = False) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.signals import SignalHandlerOptions
        self.model = model
        self.finish_x = finish_x
        self.publish_goal = publish_goal
        self.blind = blind
        self.ctx = Context()
        if domain_id is None:
            domain_id = int(os.environ.get('ROS_DOMAIN_ID', '0') or 0)
        # args=[]: rclpy would otherwise read the tool's own command line, where rcl takes
        # every `--arg NAME:=VALUE` for a (deprecated-syntax) remap rule of the monitor
        rclpy.init(args=[], context=self.ctx, domain_id=domain_id,
                   signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node('terrain_demo_monitor', context=self.ctx,
                                      start_parameter_services=False)
        self.executor = fast_executor(self.ctx)
        self.executor.add_node(self.node)
        self.lock = threading.Lock()
        self.sim_t: Optional[float] = None
        self.first_clock_wall: Optional[float] = None
        self.gt_t: List[float] = []
        self.gt_T: List[np.ndarray] = []
        self.gt_last: Optional[np.ndarray] = None
        self.icp_t, self.icp_T = [], []
        self.dr_t, self.dr_T = [], []
        self.corr_t, self.corr_T = [], []
        self.joint_t, self.joint_q, self.joint_tau = [], [], []
        self.plans: List[dict] = []
        self.terrain_msg = None
        self.fine_msg = None
        self.filled_msg = None
        self.latencies_ms: List[float] = []
        # wall time of the first arrival of each capture's stamp on the images and the
        # pipeline's outputs
        self.stage_wall: Dict[str, Dict[tuple, float]] = {
            t: {} for t in (IMAGE_TOPIC,) + STAGE_TOPICS}
        self.counts: Dict[str, int] = {}
        # each node's latest ~/diagnostics counters (cumulative since the node started)
        self.node_counters: Dict[str, Dict[str, int]] = {}
        self._joint_index = None
        self._running = True
        self._subscribe()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _subscribe(self) -> None:
        from geometry_msgs.msg import PoseStamped
        from nav_msgs.msg import Odometry
        from diagnostic_msgs.msg import DiagnosticArray
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import Image, JointState, PointCloud2
        from std_msgs.msg import Header
        from terrain_msgs.msg import FootstepPlan, TerrainGrid
        from terrain_ros.qos import LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS
        n = self.node

        def sub(cls, topic, cb, qos, raw=False):
            return n.create_subscription(cls, topic, self._safe(cb), qos, raw=raw)
        sub(Clock, '/clock', self._on_clock, RELIABLE_QOS)
        sub(Odometry, '/ground_truth/odom', self._on_gt, RELIABLE_QOS)
        sub(TerrainGrid, '/ground_truth/terrain', lambda m: self._keep('terrain_msg', m,
                                                                       '/ground_truth/terrain'),
            LATCHED_QOS)
        sub(TerrainGrid, '/map/fine', self._on_fine, LATCHED_QOS)
        self.blind_pub = (n.create_publisher(TerrainGrid, '/map/blind', LATCHED_QOS)
                          if self.blind else None)
        sub(TerrainGrid, '/map/filled', self._on_filled, LATCHED_QOS)
        sub(PoseStamped, '/icp/pose', self._on_icp, RELIABLE_QOS)
        sub(PoseStamped, '/icp/correction', self._on_correction, LATCHED_QOS)
        sub(Odometry, '/odom/dead_reckoning', self._on_dr, RELIABLE_QOS)
        sub(FootstepPlan, '/footstep_plan', self._on_plan, LATCHED_QOS)
        sub(JointState, '/joint_states', self._on_joints, SENSOR_QOS)
        sub(Header, '/capture_request', lambda m: self._count('/capture_request'),
            RELIABLE_QOS)
        for name in COUNTER_NODES:
            sub(DiagnosticArray, f'/{name}/diagnostics', self._on_diagnostics, RELIABLE_QOS)
        # Raw (undeserialized) for big messages: only their stamps and counts are needed.
        sub(Image, IMAGE_TOPIC, self._on_image, SENSOR_QOS, raw=True)
        sub(PointCloud2, '/stereo/points', self._on_points, SENSOR_QOS, raw=True)
        self.goal_pub = n.create_publisher(PoseStamped, '/goal_pose', RELIABLE_QOS)
        if self.publish_goal:
            n.create_timer(2.0, self._safe(self._publish_goal))

    def _safe(self, fn):
        """A callback that counts a malformed message (ValueError) instead of raising."""
        def wrapped(*a):
            try:
                fn(*a)
            except ValueError as exc:
                key = 'malformed (ignored by the monitor)'
                self._count(key)
                if self.counts[key] == 1:
                    print(f'[{PROG}] monitor: ignoring a malformed message: {exc}', flush=True)
        return wrapped

    def _spin(self) -> None:
        while self._running and self.ctx.ok():
            try:
                self.executor.spin_once(timeout_sec=0.1)
            except Exception as exc:  # keep watching: one bad callback must not end the run
                if self._running and self.ctx.ok():
                    print(f'[{PROG}] monitor callback failed: {exc}', flush=True)

    def _publish_goal(self) -> None:
        from geometry_msgs.msg import PoseStamped
        from terrain_ros.conversions import sec_to_stamp
        if self.goal_pub.get_subscription_count() == 0 or self.sim_t is None:
            return
        g = PoseStamped()
        g.header.frame_id = 'map'
        g.header.stamp = sec_to_stamp(self.sim_t)
        g.pose.position.x = float(self.finish_x + GOAL_BEYOND_FINISH_M)
        g.pose.orientation.w = 1.0
        self.goal_pub.publish(g)

    def _on_diagnostics(self, msg) -> None:
        for st in msg.status:
            counts = {}
            for kv in st.values:
                try:
                    counts[kv.key] = int(kv.value)
                except ValueError:
                    continue          # a counter is an integer; anything else is not one
            with self.lock:
                self.node_counters[st.name.lstrip('/')] = counts

    def _count(self, topic: str) -> None:
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def _keep(self, attr: str, msg, topic: str) -> None:
        setattr(self, attr, msg)
        self._count(topic)

    def _mark(self, topic: str, key: tuple) -> bool:
        """Note the first arrival of ``key`` on ``topic``; False when it came before."""
        seen = self.stage_wall[topic]
        if key in seen:
            return False
        seen[key] = time.monotonic()
        if len(seen) > 200:
            for k in list(seen)[:100]:
                del seen[k]
        return True

    def _on_points(self, data: bytes) -> None:
        from terrain_ros.conversions import peek_stamp
        self._count('/stereo/points')
        try:
            self._mark('/stereo/points', peek_stamp(data))
        except struct.error:
            pass

    def _on_fine(self, msg) -> None:
        from terrain_ros.conversions import stamp_key
        self._keep('fine_msg', msg, '/map/fine')
        self._mark('/map/fine', stamp_key(msg.header.stamp))
        if self.blind_pub is not None:
            # Blind variant: the same grid and stamp, flat and fully "observed".
            from terrain_perception.grid import GridMap
            from terrain_ros.conversions import grid_to_msg, msg_to_grid
            g = msg_to_grid(msg)
            zeros = np.zeros(g.shape, np.float32)
            flat = GridMap(g.resolution_m, g.origin_xy, g.shape,
                           {'elevation': zeros, 'observed': zeros + 1.0, 'filled': zeros,
                            'cost': zeros}, frame_id=g.frame_id, stamp_s=g.stamp_s)
            self.blind_pub.publish(grid_to_msg(flat))

    def _on_filled(self, msg) -> None:
        from terrain_ros.conversions import stamp_key
        self._keep('filled_msg', msg, '/map/filled')
        self._mark('/map/filled', stamp_key(msg.header.stamp))

    def _on_clock(self, msg) -> None:
        from terrain_ros.conversions import stamp_to_sec
        self.sim_t = stamp_to_sec(msg.clock)
        if self.first_clock_wall is None:
            self.first_clock_wall = time.monotonic()

    def _on_gt(self, msg) -> None:
        from terrain_ros.conversions import pose_to_matrix, stamp_to_sec
        self._count('/ground_truth/odom')
        t = stamp_to_sec(msg.header.stamp)
        T = pose_to_matrix(msg.pose.pose)
        self.gt_last = T
        with self.lock:
            if not self.gt_t or t - self.gt_t[-1] >= 0.02 - 1e-6:
                self.gt_t.append(t)
                self.gt_T.append(T)

    def _on_icp(self, msg) -> None:
        from terrain_ros.conversions import pose_to_matrix, stamp_to_sec
        self._count('/icp/pose')
        try:
            T = pose_to_matrix(msg.pose)
        except ValueError:      # a refused pose must not leave the stamp list one longer
            return
        with self.lock:
            self.icp_t.append(stamp_to_sec(msg.header.stamp))
            self.icp_T.append(T)

    def _on_correction(self, msg) -> None:
        from terrain_ros.conversions import pose_to_matrix
        self._count('/icp/correction')
        try:
            T = pose_to_matrix(msg.pose)
        except ValueError:
            return
        with self.lock:
            # Receipt time on the sim clock: when the estimate jumps.
            self.corr_t.append(self.sim_t if self.sim_t is not None else 0.0)
            self.corr_T.append(T)

    def _on_dr(self, msg) -> None:
        from terrain_ros.conversions import pose_to_matrix, stamp_to_sec
        self._count('/odom/dead_reckoning')
        t = stamp_to_sec(msg.header.stamp)
        try:
            T = pose_to_matrix(msg.pose.pose)
        except ValueError:
            return
        with self.lock:
            if not self.dr_t or t - self.dr_t[-1] >= 0.02 - 1e-6:
                self.dr_t.append(t)
                self.dr_T.append(T)

    def _on_joints(self, msg) -> None:
        from terrain_ros.conversions import stamp_to_sec
        self._count('/joint_states')
        t = stamp_to_sec(msg.header.stamp)
        if self.joint_t and t - self.joint_t[-1] < 0.01 - 1e-6:
            return
        names = list(msg.name)
        try:
            idx = [names.index(j) for j in self.model.joint_names]
        except ValueError:
            return       # not this robot's joints (counted above, ignored for footholds)
        pos = np.asarray(msg.position, dtype=np.float64)
        if pos.size != len(names):
            return
        eff = np.asarray(msg.effort, dtype=np.float64)
        tau = eff[idx].reshape(4, 3) if eff.size == len(names) else np.full((4, 3), np.nan)
        with self.lock:
            self.joint_t.append(t)
            self.joint_q.append(pos[idx].reshape(4, 3))
            self.joint_tau.append(tau)

    def _on_image(self, data: bytes) -> None:
        from terrain_ros.conversions import peek_stamp
        self._count(IMAGE_TOPIC)
        try:
            self._mark(IMAGE_TOPIC, peek_stamp(data))
        except struct.error:
            pass

    def _on_plan(self, msg) -> None:
        from terrain_ros.conversions import stamp_key, stamp_to_sec
        self._count('/footstep_plan')
        now = time.monotonic()
        key = stamp_key(msg.header.stamp)
        # Capture-to-plan: the FIRST plan made on the map of a capture. Later plans with the
        # same stamp (a goal or parameter change replans on the same map) are not latency.
        images = self.stage_wall[IMAGE_TOPIC]
        if self._mark('/footstep_plan', key) and key in images:
            self.latencies_ms.append(1000.0 * (now - images[key]))
        steps = np.array([[f.leg, f.position.x, f.position.y, f.position.z, f.cost]
                          for f in msg.footsteps], dtype=np.float64).reshape(-1, 5)
        observed, map_cost = self._observed_at(steps[:, 1:3])
        with self.lock:
            self.plans.append({'stamp': stamp_to_sec(msg.header.stamp),
                               't_recv': self.sim_t, 'status': int(msg.status),
                               'status_text': str(msg.status_text),
                               'gait': int(msg.gait_mode), 'steps': steps,
                               'observed': observed, 'map_cost': map_cost})

    _filled_cache = (None, None)

    def _observed_at(self, xy: np.ndarray):
        """Per point, in the latest ``/map/filled`` (the map a plan is made on): 1 where the
        cell was observed by a camera, 0 where never observed (filled), and its ``cost``; NaN
        without that map or layer."""
        from terrain_ros.conversions import msg_to_grid
        out = np.full(len(xy), np.nan)
        msg = self.filled_msg
        if msg is None or not len(xy):
            return out, out.copy()
        if self._filled_cache[0] is not msg:
            try:
                self._filled_cache = (msg, msg_to_grid(msg))
            except ValueError:
                self._filled_cache = (msg, None)
        grid = self._filled_cache[1]
        if grid is None:
            return out, out.copy()
        return tuple(grid.sample(k, xy).astype(np.float64) if k in grid.layers else out.copy()
                     for k in ('observed', 'cost'))

    # -- live state ---------------------------------------------------------------------------
    def fallen_now(self) -> bool:
        from terrain_ros.report import fall_mask
        T = self.gt_last
        if T is None:
            return False
        terrain = self.terrain()
        return bool(fall_mask(T[None], terrain, self.model.body_size_m)[0])

    _terrain_cache = (None, None)

    def terrain(self):
        from terrain_ros.conversions import msg_to_grid
        msg = self.terrain_msg
        if msg is None:
            return None
        if self._terrain_cache[0] is not msg:
            try:
                self._terrain_cache = (msg, msg_to_grid(msg))
            except ValueError:
                self._terrain_cache = (msg, None)
        return self._terrain_cache[1]

    def close(self) -> None:
        import rclpy
        self._running = False
        self.thread.join(timeout=5.0)
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)

    def run_data(self, course, robot: str):
        """Everything received, as :class:`terrain_ros.report.RunData`."""
        from terrain_ros.conversions import msg_to_grid
        from terrain_ros.report import RunData

        def arr(ts, Ts):
            return (np.asarray(ts, np.float64),
                    np.asarray(Ts, np.float64).reshape(-1, 4, 4))
        d = RunData(course=course, robot=robot)
        with self.lock:
            d.gt_t, d.gt_T = arr(self.gt_t, self.gt_T)
            d.icp_t, d.icp_T = arr(self.icp_t, self.icp_T)
            d.dr_t, d.dr_T = arr(self.dr_t, self.dr_T)
            d.corr_t, d.corr_T = arr(self.corr_t, self.corr_T)
            d.joint_t = np.asarray(self.joint_t, np.float64)
            d.joint_q = np.asarray(self.joint_q, np.float64).reshape(-1, 4, 3)
            d.joint_tau = np.asarray(self.joint_tau, np.float64).reshape(-1, 4, 3)
            d.plans = list(self.plans)
        for attr, msg in (('true_terrain', self.terrain_msg), ('map_fine', self.fine_msg),
                          ('map_filled', self.filled_msg)):
            if msg is not None:
                try:
                    setattr(d, attr, msg_to_grid(msg))
                except ValueError as exc:
                    d.notes.append(f'{attr}: last message unusable: {exc}')
        d.latencies_ms = list(self.latencies_ms)
        d.latency_stages_ms = stage_latencies(self.stage_wall[IMAGE_TOPIC], self.stage_wall)
        d.counts = dict(self.counts)
        with self.lock:
            d.node_counters = {k: dict(v) for k, v in sorted(self.node_counters.items())}
        return d


# ---------------------------------------------------------------------------------------------
# the run


class _Stop:
    def __init__(self) -> None:
        self.reason: Optional[str] = None
        self.hard = False

    def on_signal(self, signum, _frame) -> None:
        if self.reason is None:
            self.reason = f'interrupted ({signal.Signals(signum).name})'
            print(f'\n[{PROG}] stopping (again to stop at once)...', flush=True)
        else:
            self.hard = True


def _default_run_dir(args) -> Path:
    stamp = datetime.now().strftime('%Y%m%d-%H%M%S')
    tag = 'replay' if args.replay else f'{args.robot}-{args.course}-s{args.seed}'
    return REPO_DIR / 'runs' / f'{stamp}-{tag}'


def run(args) -> int:
    from terrain_ros.report import cpu_ticks, machine_cpu_pct
    wall0 = time.monotonic()
    ticks0 = cpu_ticks()
    run_dir = (args.run_dir or _default_run_dir(args)).resolve()
    if run_dir.exists() and any(run_dir.iterdir()):
        raise ToolError(f'run directory {str(run_dir)!r} exists and is not empty')
    log_dir = run_dir / 'logs'
    log_dir.mkdir(parents=True, exist_ok=True)
    if args.replay is not None and not args.replay.exists():
        raise ToolError(f'bag {str(args.replay)!r} does not exist')
    course, model = course_info(args.course, args.seed, args.robot)
    cost_cfg = fill_cost_config()

    launch_src = args.launch or LAUNCH_DIR / ('replay.yaml' if args.replay else 'sim.yaml')
    launch_run = run_dir / 'launch.yaml'
    status = preflight(launch_src, launch_run)
    declared = (yaml.safe_load(launch_run.read_text()) or {}).get('arguments') or {}
    cli = {'robot': args.robot, 'course': args.course, 'seed': str(args.seed),
           'image_scale': str(args.image_scale), 'camera_rate_hz': str(args.camera_rate),
           'real_time_factor': str(args.real_time_factor)}
    if args.blind:
        cli['planner_map'] = '/map/blind'
    height = fill_library_height(course.name)
    if height is not None:
        cli['library_height_m'] = str(height)
    cli = {k: v for k, v in cli.items() if k in declared}
    for a in args.arg:
        if ':=' not in a:
            raise ToolError(f'--arg {a!r} is not of the form name:=value')
        k, v = a.split(':=', 1)
        cli[k] = v
    if 'start_x' in cli:
        course.start_x_m = float(cli['start_x'])
    specs = load_launch_file(launch_run, cli, args.param) if any(
        s.get('state') == 'pending' for s in status.values()) else []
    env = dict(safe_env(dict(os.environ)))
    print(f'[{PROG}] run directory {run_dir}', flush=True)
    print(f'[{PROG}] ROS_DOMAIN_ID={env.get("ROS_DOMAIN_ID", "0")} discovery '
          f'{env.get("ROS_AUTOMATIC_DISCOVERY_RANGE")}; {args.robot} on {args.course} seed '
          f'{args.seed}; nodes: {", ".join(s.name for s in specs) or "none"}', flush=True)
    for name, st in status.items():
        if st.get('state') == 'missing':
            print(f'[{PROG}] WARNING: {name} cannot start: {st["reason"]}', flush=True)
        elif st.get('note'):
            print(f'[{PROG}] note: {name}: {st["note"]}', flush=True)

    stop = _Stop()
    old = {s: signal.signal(s, stop.on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    monitor = Monitor(model, course.finish_x_m, publish_goal=not args.no_goal,
                      blind=args.blind)
    recorder = None
    if not args.no_bag:
        recorder = start_recorder(run_dir / 'bag', log_dir, env, args.recorder_nice)
        time.sleep(1.0)     # let the recorder discover the latched topics as they appear
    launcher = LoggedLauncher(specs, log_dir)
    launcher_thread = threading.Thread(target=launcher.run, daemon=True)
    launcher_thread.start()
    player = None
    if args.replay is not None:
        player = _start_player(args, log_dir, env)

    end_reason = _watch(args, monitor, launcher, launcher_thread, player, course, stop, wall0)
    print(f'[{PROG}] run ended: {end_reason}', flush=True)

    node_states = launcher.node_states()
    bag_code = None
    if recorder is not None:
        bag_code = stop_process(recorder, signal.SIGINT, 30.0)
    if player is not None:
        stop_process(player, signal.SIGINT, 5.0)
    launcher.stopping = True
    launcher_thread.join(timeout=30.0)
    launcher.close_logs()
    wall = time.monotonic() - wall0
    sim_t = monitor.sim_t or 0.0
    data = monitor.run_data(course, args.robot)
    monitor.close()
    for s, h in old.items():
        signal.signal(s, h)

    for name, st in node_states.items():
        status[name] = {**status.get(name, {}), **st}
    data.nodes = {k: {kk: vv for kk, vv in v.items()} for k, v in status.items()}
    data.sim_time_s, data.wall_time_s, data.end_reason = sim_t, wall, end_reason
    data.machine_cpu_pct = machine_cpu_pct(ticks0, cpu_ticks())
    if args.replay is not None:
        data.notes.append(f'replay of {args.replay}: robot, course and seed are the command '
                          'line\'s (--robot/--course/--seed), not read from the bag')
    if recorder is not None:
        data.notes.append(f'bag: {run_dir / "bag"} (recorder exit code {bag_code}: '
                          f'{_log_tail(log_dir, "bag")})')
    else:
        data.notes.append('bag: not recorded (--no-bag)')
    from terrain_ros.report import format_summary, write_report
    summary = write_report(data, run_dir, model, cost_cfg)
    summary['bag'] = str(run_dir / 'bag') if recorder is not None else None
    summary['bag_closed_cleanly'] = (bag_code == 0) if recorder is not None else None
    summary['command'] = ' '.join([PROG] + sys.argv[1:])
    from terrain_perception.bench.pipeline import code_revision
    summary['code_revision'] = code_revision(REPO_DIR)
    import json
    (run_dir / 'summary.json').write_text(json.dumps(summary, indent=2, default=str))
    print(format_summary(summary), flush=True)
    print(f'[{PROG}] report: {run_dir / "summary.json"} and '
          f'{", ".join(k for k, v in summary["figures"].items() if v.get("file"))} in '
          f'{run_dir}', flush=True)
    if args.strict and not summary.get('crossed'):
        return 1
    return 0


def _start_player(args, log_dir: Path, env) -> subprocess.Popen:
    exe = Path(sys.executable).parent / 'terrain-bag'
    log = open(log_dir / 'player.log', 'w', buffering=1)
    topics = _replay_topics(args.replay)
    # The recorded /clock is replayed as a topic: header stamps and node clocks stay on the
    # simulated time line of the recording.
    cmd = [str(exe), 'play', str(args.replay), '--rate', str(args.replay_rate),
           '--delay', '3.0', '--topics', *topics]
    return subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT,
                            preexec_fn=_die_with_parent)


#: What a replay feeds the perception and planning nodes (their inputs, plus the evaluation
#: and controller topics the report reads); their own outputs are recomputed, not replayed.
REPLAY_TOPICS = (
    '/clock', '/stereo/left/image_rect', '/stereo/right/image_rect',
    '/stereo/left/camera_info', '/stereo/right/camera_info', '/imu/data', '/joint_states',
    '/odom/dead_reckoning', '/capture_request', '/ground_truth/odom', '/ground_truth/terrain',
    '/goal_pose',
)


def _replay_topics(bag: Path) -> List[str]:
    from rosbags.rosbag2 import Reader
    with Reader(bag) as r:
        have = {c.topic for c in r.connections}
    return [t for t in REPLAY_TOPICS if t in have]


class WalkEnd:
    """When a closed-loop walk is over, from the true base x and the fall test over simulated
    time: ``update`` returns ``'crossed'``, ``'fell'`` or a ``'stalled: ...'`` reason, or None
    while the walk goes on.

    Crossed means past ``finish_x`` and not fallen for ``settle_s`` after (the report's
    ``crossing_index`` rule): a robot that topples over the line (run AB: tilted 140 deg,
    carried past the finish by the fall) has not crossed. Fell means fallen for ``fall_s``;
    stalled means no 1 cm of progress for ``stall_s``.
    """

    def __init__(self, finish_x: float, stall_s: float, settle_s: Optional[float] = None,
                 fall_s: float = 2.0) -> None:
        from terrain_ros.report import CROSS_SETTLE_S
        settle_s = CROSS_SETTLE_S if settle_s is None else settle_s
        self.finish_x, self.stall_s = float(finish_x), float(stall_s)
        self.settle_s, self.fall_s = float(settle_s), float(fall_s)
        self.best_x: Optional[float] = None
        self.best_t = 0.0
        self.fallen_since: Optional[float] = None
        self.past_since: Optional[float] = None     # past the finish and upright since

    def update(self, t: float, x: float, fallen: bool) -> Optional[str]:
        if fallen:
            self.past_since = None
            if self.fallen_since is None:
                self.fallen_since = t
            return 'fell' if t - self.fallen_since >= self.fall_s else None
        self.fallen_since = None
        if x >= self.finish_x and self.past_since is None:
            self.past_since = t
        if self.past_since is not None:
            return 'crossed' if t - self.past_since >= self.settle_s else None
        if self.best_x is None or x > self.best_x + 0.01:
            self.best_x, self.best_t = x, t
        elif t - self.best_t >= self.stall_s:
            return (f'stalled: no progress for {self.stall_s:.0f} s of simulated time '
                    f'(x = {x:.3f} m)')
        return None


def _watch(args, monitor: Monitor, launcher: LoggedLauncher, launcher_thread, player, course,
           stop: _Stop, wall0: float) -> str:
    """Wait for an end condition, printing progress; returns why the run ended."""
    next_print = 0.0
    last_sim, last_sim_wall = None, time.monotonic()
    walk_end = WalkEnd(course.finish_x_m, args.stall_time)
    span = max(course.finish_x_m - course.start_x_m, 1e-6)
    while True:
        time.sleep(0.2)
        now = time.monotonic()
        wall = now - wall0
        if stop.reason:
            return stop.reason
        if not launcher_thread.is_alive():
            dead = [n for n, st in launcher.node_states().items() if st['state'] != 'ran']
            return f'launcher stopped (required node exited: {", ".join(dead) or "?"})'
        if player is not None and player.poll() is not None:
            time.sleep(2.0)     # let the last map and plan come through
            return f'bag played to the end (player exit code {player.returncode})'
        if wall >= args.timeout:
            return f'wall-time limit {args.timeout:.0f} s'
        t = monitor.sim_t
        if t is not None:
            if t != last_sim:
                last_sim, last_sim_wall = t, now
            elif now - last_sim_wall > 60.0:
                return 'simulated clock stopped for 60 s'
            if t >= args.max_sim_time:
                return f'simulated-time limit {args.max_sim_time:.0f} s'
        elif wall > 240.0 and player is None:
            return 'no /clock within 240 s of start (simulator did not come up)'
        T = monitor.gt_last
        x = T[0, 3] if T is not None else None
        if x is not None and t is not None and player is None:
            reason = walk_end.update(t, x, monitor.fallen_now())
            if reason:
                return reason
        if not args.quiet and now >= next_print:
            next_print = now + args.progress_period
            rtf = ((t or 0.0) / (now - monitor.first_clock_wall)
                   if monitor.first_clock_wall and now > monitor.first_clock_wall else 0.0)
            up = sum(1 for n in launcher.procs if launcher.alive(n))
            dist = (f'{x - course.start_x_m:+.3f} m of {span:.2f} m '
                    f'({100.0 * (x - course.start_x_m) / span:.0f}%)' if x is not None
                    else 'n/a')
            print(f'[{PROG}] wall {wall:5.0f} s | sim {t or 0.0:6.1f} s | RTF {rtf:.2f} | '
                  f'crossed {dist} | plans {len(monitor.plans)} | '
                  f'maps {monitor.counts.get("/map/fine", 0)} | '
                  f'nodes up {up}/{len(launcher.procs)}', flush=True)


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    if args.max_sim_time <= 0 or args.timeout <= 0:
        return fail(PROG, ToolError('--max-sim-time and --timeout must be positive'))
    safe_env(os.environ)
    try:
        return run(args)
    except ToolError as exc:
        fail(PROG, exc)
        return 2


if __name__ == '__main__':
    sys.exit(main())
