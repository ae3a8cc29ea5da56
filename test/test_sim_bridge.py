"""sim_bridge in process: topics with the right types and content; bad commands refused and
logged while the robot keeps standing; a good command is tracked."""

from __future__ import annotations

import numpy as np
import pytest
from builtin_interfaces.msg import Duration
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.parameter import Parameter
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image, Imu, JointState
from std_msgs.msg import Header
from terrain_msgs.msg import TerrainGrid
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from conftest import spin_until
from sim_bridge.bridge_node import SimBridgeNode
from terrain_perception.grid import ELEVATION
from terrain_perception.kinematics import standing_joint_angles
from terrain_perception.transforms import quat_to_R
from terrain_ros.conversions import (camera_info_to_stereo, image_to_numpy, msg_to_grid,
                                     pose_to_matrix, stamp_to_sec)
from terrain_ros.qos import LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS

TOPICS = {
    '/clock': (Clock, RELIABLE_QOS),
    '/stereo/left/image_rect': (Image, SENSOR_QOS),
    '/stereo/right/image_rect': (Image, SENSOR_QOS),
    '/stereo/left/camera_info': (CameraInfo, SENSOR_QOS),
    '/stereo/right/camera_info': (CameraInfo, SENSOR_QOS),
    '/imu/data': (Imu, SENSOR_QOS),
    '/joint_states': (JointState, SENSOR_QOS),
    '/ground_truth/odom': (Odometry, RELIABLE_QOS),
    '/ground_truth/terrain': (TerrainGrid, LATCHED_QOS),
}


class Harness:
    def __init__(self, ctx, executor, **params):
        base = dict(robot='littledog', course_class='rocks-6cm', course_resolution_m=0.01,
                    image_scale=0.3, shadows=False, camera_rate_hz=4.0)
        base.update(params)
        self.node = SimBridgeNode(context=ctx, parameter_overrides=[
            Parameter(k, value=v) for k, v in base.items()])
        self.logged = []
        logger = self.node.get_logger()
        warn = logger.warning

        def record(msg, *a, **kw):
            self.logged.append(str(msg))
            return warn(msg, *a, **kw)
        logger.warning = record
        self.io = Node('sim_bridge_test_io', context=ctx)
        self.got = {t: [] for t in TOPICS}
        for topic, (typ, qos) in TOPICS.items():
            self.io.create_subscription(typ, topic, self.got[topic].append, qos)
        self.pub_traj = self.io.create_publisher(JointTrajectory, '/joint_commands',
                                                 RELIABLE_QOS)
        self.pub_js = self.io.create_publisher(JointState, '/joint_commands_state',
                                               RELIABLE_QOS)
        self.pub_capture = self.io.create_publisher(Header, '/capture_request', RELIABLE_QOS)
        self.ex = executor
        executor.add_node(self.node)
        executor.add_node(self.io)

    @property
    def t(self):
        return self.node.session.t_s

    def run_until_sim(self, t_s, timeout_s=60.0):
        assert spin_until(self.ex, lambda: self.t >= t_s, timeout_s)


@pytest.fixture
def harness(ros_context, executor):
    return Harness(ros_context, executor)


@pytest.fixture
def flat_harness(ros_context, executor):
    return Harness(ros_context, executor, course_class='flat')


def trajectory(names, positions, times=(0.0,)):
    msg = JointTrajectory(joint_names=list(names))
    for t, q in zip(times, positions):
        sec = int(t)
        msg.points.append(JointTrajectoryPoint(
            positions=[float(v) for v in q],
            time_from_start=Duration(sec=sec, nanosec=int(round((t - sec) * 1e9)))))
    return msg


def test_topics_have_the_right_types_and_content(harness):
    h = harness
    h.run_until_sim(1.0)
    assert spin_until(h.ex, lambda: all(h.got[t] for t in TOPICS), 20.0), \
        [t for t in TOPICS if not h.got[t]]
    model, session = h.node.session.model, h.node.session
    # clock: monotonic sim time, matching the session to within one clock period once the
    # simulation is paused and the messages in flight have arrived
    h.node.timer.cancel()
    period = 1.0 / h.node.cfg.clock_rate_hz
    assert spin_until(h.ex, lambda: stamp_to_sec(h.got['/clock'][-1].clock)
                      >= h.t - period - 1e-6, 10.0)
    clocks = [stamp_to_sec(m.clock) for m in h.got['/clock']]
    assert np.all(np.diff(clocks) > 0) and clocks[-1] == pytest.approx(h.t, abs=period + 1e-6)
    h.node.timer.reset()
    # images: rgb8 of the scaled profile camera, paired stamps, textured
    left, right = h.got['/stereo/left/image_rect'][0], h.got['/stereo/right/image_rect'][0]
    assert left.encoding == 'rgb8' and left.header.frame_id == 'camera_optical'
    assert left.header.stamp == right.header.stamp
    img = image_to_numpy(left)
    assert img.shape == (session.stereo.left.height, session.stereo.left.width, 3)
    assert img.std() > 10.0
    # 4 Hz over >= 1 s of sim time
    assert len(h.got['/stereo/left/image_rect']) >= 4
    stereo = camera_info_to_stereo(h.got['/stereo/left/camera_info'][0],
                                   h.got['/stereo/right/camera_info'][0])
    assert stereo.baseline_m == pytest.approx(model.baseline_m)
    assert stereo.left.fx == pytest.approx(session.stereo.left.fx)
    # IMU at rest: specific force ~ +g along world up
    imu = h.got['/imu/data'][-1]
    acc = np.array([imu.linear_acceleration.x, imu.linear_acceleration.y,
                    imu.linear_acceleration.z])
    assert np.linalg.norm(acc) == pytest.approx(9.81, abs=0.3)
    R_wi = quat_to_R([imu.orientation.x, imu.orientation.y, imu.orientation.z,
                      imu.orientation.w])
    assert np.degrees(np.arccos(np.clip(acc @ (R_wi.T @ [0, 0, 1]) / np.linalg.norm(acc),
                                        -1, 1))) < 2.0
    # joints: the profile's 12 names, near the standing pose
    js = h.got['/joint_states'][-1]
    assert list(js.name) == list(model.joint_names)
    np.testing.assert_allclose(js.position, standing_joint_angles(model).ravel(), atol=0.05)
    # ground truth: odometry at the start pose and standing height, terrain = the course
    T = pose_to_matrix(h.got['/ground_truth/odom'][-1].pose.pose)
    assert T[0, 3] == pytest.approx(0.4, abs=0.02)
    assert T[2, 3] == pytest.approx(model.standing_height_m, abs=0.03)
    grid = msg_to_grid(h.got['/ground_truth/terrain'][0])
    np.testing.assert_array_equal(grid[ELEVATION], session.course[ELEVATION])
    assert grid.origin_xy == pytest.approx(session.course.origin_xy)


def test_bad_commands_are_refused_logged_and_robot_keeps_standing(flat_harness):
    h = flat_harness
    h.run_until_sim(0.2)
    model = h.node.session.model
    names = list(model.joint_names)
    q0 = standing_joint_angles(model).ravel()
    T0 = pose_to_matrix(h.got['/ground_truth/odom'][-1].pose.pose) \
        if h.got['/ground_truth/odom'] else h.node.session.base_state()[0]
    target_before = h.node.session.q_target.copy()

    bad_names = names[:11] + ['tail_joint']
    h.pub_traj.publish(trajectory(bad_names, [q0]))
    nan_q = q0.copy()
    nan_q[4] = np.nan
    h.pub_js.publish(JointState(name=names, position=nan_q.tolist()))
    far_q = q0.copy()
    far_q[2] = model.joint_upper[2] + 0.5
    h.pub_traj.publish(trajectory(names, [q0, far_q], times=(0.0, 0.5)))
    h.pub_traj.publish(JointTrajectory(joint_names=names))          # no points
    h.pub_js.publish(JointState(name=names, position=q0[:6].tolist()))   # short
    c = h.node.counters
    keys = ('rejected_command_unknown_joint', 'rejected_command_not_finite',
            'rejected_command_out_of_limits', 'rejected_command_malformed')
    assert spin_until(h.ex, lambda: sum(c[k] for k in keys) >= 5, 20.0), dict(c.counts)
    assert c['rejected_command_unknown_joint'] == 1 and c['rejected_command_not_finite'] == 1
    assert c['rejected_command_out_of_limits'] == 1 and c['rejected_command_malformed'] == 2
    assert any('tail_joint' in m for m in h.logged)
    assert any('outside its limits' in m for m in h.logged)
    np.testing.assert_array_equal(h.node.session.q_target, target_before)

    h.run_until_sim(h.t + 1.5)
    T1, _, _ = h.node.session.base_state()
    assert np.linalg.norm(T1[:3, 3] - T0[:3, 3]) < 0.01
    assert np.degrees(np.arccos(np.clip(T1[2, 2], -1, 1))) < 2.0


def test_valid_trajectory_is_tracked(flat_harness):
    h = flat_harness
    h.run_until_sim(0.1)
    model = h.node.session.model
    names = list(model.joint_names)
    q0 = standing_joint_angles(model).ravel()
    q1 = q0.copy()
    q1[0] += 0.15                                    # LF hip abduction outwards
    q1[0] = np.clip(q1[0], model.joint_lower[0], model.joint_upper[0])
    # a two-point trajectory over 0.5 s: interpolated, then held
    h.pub_traj.publish(trajectory(names, [q0, q1], times=(0.0, 0.5)))
    assert spin_until(h.ex, lambda: abs(h.node.session.q_target[0] - q0[0]) > 1e-6, 10.0)
    t_cmd = h.t
    h.run_until_sim(t_cmd + 0.25)
    mid = h.node.session.q_target[0]
    assert q0[0] < mid < q1[0]                        # interpolating, not jumping
    h.run_until_sim(t_cmd + 1.2)
    q, _, _ = h.node.session.robot.joint_states()
    assert q[0] == pytest.approx(q1[0], abs=0.03)
    assert h.node.counters.counts.get('rejected_command_malformed', 0) == 0


def test_capture_only_on_request(ros_context, executor):
    h = Harness(ros_context, executor, course_class='flat', periodic_capture=False,
                publish_ground_truth_depth=True)
    from sensor_msgs.msg import Image as ImageMsg
    depth_msgs = []
    h.io.create_subscription(ImageMsg, '/ground_truth/depth', depth_msgs.append, SENSOR_QOS)
    h.run_until_sim(0.5)
    assert spin_until(h.ex, lambda: h.got['/joint_states'], 5.0)
    assert not h.got['/stereo/left/image_rect'] and h.node.captures == 0
    # The request is for a stamp 0.3 s ahead of the simulator's clock now (spinning for the
    # joint states above lets the simulation run on: a fixed 0.8 s could already be past).
    t_req = round(h.node.session.t_s + 0.3, 3)
    stamp = Header()
    stamp.stamp.sec, stamp.stamp.nanosec = int(t_req), int(round((t_req % 1.0) * 1e9))
    h.pub_capture.publish(stamp)
    assert spin_until(h.ex, lambda: h.got['/stereo/left/image_rect'] and depth_msgs, 30.0)
    t_img = stamp_to_sec(h.got['/stereo/left/image_rect'][0].header.stamp)
    assert t_req - 1e-9 <= t_img <= t_req + 2 * h.node.session.dt_s
    h.run_until_sim(t_req + 0.7)
    spin_until(h.ex, lambda: False, 0.3)
    assert h.node.captures == 1 and len(h.got['/stereo/left/image_rect']) == 1
    # the ground-truth depth belongs to the same capture and sees the floor ahead
    depth = image_to_numpy(depth_msgs[0])
    assert depth_msgs[0].header.stamp == h.got['/stereo/left/image_rect'][0].header.stamp
    assert np.nanmin(depth) > 0.05 and np.isfinite(depth).mean() > 0.5


def test_real_time_factor_paces_the_simulation(ros_context, executor):
    import time
    h = Harness(ros_context, executor, course_class='flat', real_time_factor=0.1)
    spin_until(h.ex, lambda: h.t > 0.0, 10.0)
    t0, w0 = h.t, time.monotonic()
    spin_until(h.ex, lambda: False, 3.0)
    sim, wall = h.t - t0, time.monotonic() - w0
    assert 0.0 < sim <= 0.1 * wall + 0.03


@pytest.mark.parametrize('rtf,period,want_s', [(0.2, 0.0, 0.02), (1.0, 0.0, 0.004),
                                               (0.0, 0.0, 0.001), (0.2, 0.005, 0.005)])
def test_physics_timer_period(ros_context, executor, rtf, period, want_s):
    # Each tick costs the executor ~1 ms whether a step is due or not: automatic ticks are two
    # physics steps (2 ms of simulated time at 500 Hz) of wall time under the real-time factor.
    h = Harness(ros_context, executor, course_class='flat', real_time_factor=rtf,
                tick_period_s=period, physics_rate_hz=500.0)
    assert h.node.timer.timer_period_ns == pytest.approx(want_s * 1e9, rel=1e-6)


def test_missing_course_file_is_a_clear_error(ros_context):
    with pytest.raises(ValueError, match='course_file'):
        SimBridgeNode(context=ros_context, parameter_overrides=[
            Parameter('course_file', value='/nonexistent/course.npz')])


@pytest.mark.parametrize('waits', [True, False])
def test_the_world_waits_while_the_simulator_renders(ros_context, executor, waits):
    # A render is the simulator's cost, not the world's: with world_waits_for_render the
    # wall time spent drawing is taken out of the real-time schedule (no catch-up burst of
    # physics and state messages afterwards); without it the simulation catches up.
    import time
    rtf, delay = 0.5, 0.25
    h = Harness(ros_context, executor, course_class='flat', real_time_factor=rtf,
                camera_rate_hz=2.0, world_waits_for_render=waits)
    render, spent = h.node.session.render, []

    def slow_render():
        w = time.monotonic()
        time.sleep(delay)
        cap = render()
        spent.append(time.monotonic() - w)
        return cap
    h.node.session.render = slow_render
    spin_until(h.ex, lambda: h.t > 0.0, 10.0)
    t0, w0, n0 = h.t, time.monotonic(), len(spent)
    spin_until(h.ex, lambda: False, 4.0)
    sim, wall, drawn = h.t - t0, time.monotonic() - w0, sum(spent[n0:])
    assert len(spent) - n0 >= 3 and drawn > 0.7
    paced = rtf * (wall - drawn)     # simulated time the schedule allows outside the renders
    if waits:
        assert sim == pytest.approx(paced, abs=0.06)
    else:
        assert sim > paced + 0.5 * rtf * drawn
