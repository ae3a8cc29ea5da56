"""icp_mapper node in-process: localisation and map content against ground truth, bad input."""

import numpy as np
import pytest
from conftest import spin_until
from geometry_msgs.msg import PoseArray, PoseStamped
from nav_msgs.msg import Odometry
from rclpy.parameter import Parameter
from sensor_msgs.msg import PointCloud2, PointField
from terrain_msgs.msg import TerrainGrid

from icp_mapper_node.node import IcpMapperNode
from terrain_perception import raycast as rc
from terrain_perception.camera import PinholeCamera
from terrain_perception.grid import ELEVATION, OBSERVED, GridMap
from terrain_perception.robot_model import load_robot_model
from terrain_perception.transforms import make_T, rpy_to_R
from terrain_perception.mapping import IcpMapper
from terrain_ros.conversions import (cloud_to_xyz, msg_to_grid, odometry, pose_to_matrix,
                                     sec_to_stamp, xyz_to_cloud)
from terrain_ros.qos import LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS

CAM = PinholeCamera.from_fov(160, 120, 50.0)


@pytest.fixture(scope='module')
def world():
    rng = np.random.default_rng(7)
    g = GridMap.empty(0.005, (-0.5, -1.0), (500, 400))
    xs, ys = g.cell_centers()
    X, Y = np.meshgrid(xs, ys, indexing='ij')
    H = np.zeros_like(X)
    for _ in range(120):
        cx, cy = rng.uniform(-0.5, 2.0), rng.uniform(-1.0, 1.0)
        s, h = rng.uniform(0.03, 0.08), rng.uniform(-0.03, 0.04)
        H += h * np.exp(-((X - cx) ** 2 + (Y - cy) ** 2) / (2 * s * s))
    g[ELEVATION] = H
    return g, rc.HeightFieldScene(g), np.asarray(load_robot_model('littledog').T_base_camera)


class Harness:
    """Publishes odometry and clouds, records the node's outputs."""

    def __init__(self, ros_context, executor, **params):
        params = {'robot': 'littledog', 'fine_size_m': 2.0, 'diagnostics_period_s': 0.2,
                  **params}
        self.node = IcpMapperNode(context=ros_context, parameter_overrides=[
            Parameter(k, value=v) for k, v in params.items()])
        self.io = rclpy_node('icp_test_io', ros_context)
        executor.add_node(self.node)
        executor.add_node(self.io)
        self.ex = executor
        self.pub_odom = self.io.create_publisher(Odometry, '/odom/dead_reckoning', RELIABLE_QOS)
        self.pub_cloud = self.io.create_publisher(PointCloud2, '/stereo/points', SENSOR_QOS)
        self.poses, self.fine, self.corr, self.capt = [], [], [], []
        self.io.create_subscription(PoseStamped, '/icp/pose', self.poses.append, RELIABLE_QOS)
        self.io.create_subscription(TerrainGrid, '/map/fine', self.fine.append, LATCHED_QOS)
        self.io.create_subscription(PoseStamped, '/icp/correction', self.corr.append,
                                    LATCHED_QOS)
        self.io.create_subscription(PoseArray, '/map/capture_poses', self.capt.append,
                                    LATCHED_QOS)
        spin_until(executor, lambda: self.pub_cloud.get_subscription_count() > 0
                   and self.pub_odom.get_subscription_count() > 0, 5.0)

    def odom(self, t, T):
        self.pub_odom.publish(odometry(T, 'odom', 'base_link', sec_to_stamp(t)))

    def cloud(self, msg):
        self.pub_cloud.publish(msg)


def rclpy_node(name, context):
    from rclpy.node import Node
    return Node(name, context=context)


def truth_pose(k):
    return make_T(rpy_to_R(0.0, 0.0, 0.02 * k), [0.05 * k, 0.01 * k, 0.2])


def cloud_msg(scene, T_map_base, T_bc, t):
    pts = CAM.depth_to_points(scene.depth_image(CAM, T_map_base @ T_bc))
    return xyz_to_cloud(pts, 'camera_optical', sec_to_stamp(t))


def run_walk(h, scene, T_bc, n=4):
    """n captures; dead reckoning 3 % long and 0.3 deg off per step."""
    T_dr = truth_pose(0)
    for k in range(n):
        T = truth_pose(k)
        if k > 0:
            d = np.linalg.inv(truth_pose(k - 1)) @ T
            d[:2, 3] *= 1.03
            T_dr = T_dr @ d @ make_T(rpy_to_R(0, 0, np.radians(0.3)))
        t = 1.0 + k
        h.odom(t - 0.05, T_dr)
        h.odom(t + 0.05, T_dr)
        spin_until(h.ex, lambda: len(h.node.odom) >= 2 * (k + 1), 3.0)
        n_before = len(h.poses)
        h.cloud(cloud_msg(scene, T, T_bc, t))
        assert spin_until(h.ex, lambda: len(h.poses) > n_before, 10.0), 'no /icp/pose'
    return T


def test_node_localises_and_maps_against_ground_truth(ros_context, executor, world):
    g, scene, T_bc = world
    h = Harness(ros_context, executor)
    T_last = run_walk(h, scene, T_bc)
    assert spin_until(executor, lambda: len(h.fine) >= 4 and len(h.capt) >= 4, 5.0)
    est = pose_to_matrix(h.poses[-1].pose)
    assert np.linalg.norm(est[:3, 3] - T_last[:3, 3]) < 2e-3
    assert h.node.mapper.counters['accepted'] == 3
    # the correction maps dead reckoning onto the estimate
    assert h.corr[-1].header.frame_id == 'map'
    grid = msg_to_grid(h.fine[-1])
    obs = grid[OBSERVED] > 0
    xs, ys = grid.cell_centers()
    X, Y = np.meshgrid(xs, ys, indexing='ij')
    truth = rc.interpolate_height(g, np.stack([X, Y], -1))
    ok = obs & np.isfinite(truth)
    assert ok.sum() > 3000
    rmse = np.sqrt(np.mean((grid[ELEVATION][ok] - truth[ok]) ** 2))
    assert rmse < 1e-3, f'map RMSE {rmse * 1e3:.2f} mm'
    assert {'min', 'max', 'count', 'last_seen', 'variance'} <= set(grid.layers)
    assert len(h.capt[-1].poses) == 4
    cam_last = pose_to_matrix(h.capt[-1].poses[-1])
    assert np.linalg.norm(cam_last[:3, 3] - (T_last @ T_bc)[:3, 3]) < 3e-3


def test_the_coarse_model_waits_for_the_captures_plan(ros_context, executor, world):
    """With ``model_after_plan`` the coarse model's part of a capture's fusion and /map/coarse
    wait until a /footstep_plan of that capture's stamp (not an older one) arrives, or the
    wall-clock limit passes without one; the model is the same as done at once."""
    from terrain_msgs.msg import FootstepPlan
    from terrain_ros.conversions import stamp_to_sec
    g, scene, T_bc = world
    h = Harness(ros_context, executor, model_after_plan=True, model_wait_max_s=10.0,
                coarse_publish_every=1)
    coarse = []
    h.io.create_subscription(PointCloud2, '/map/coarse', coarse.append, LATCHED_QOS)
    pub_plan = h.io.create_publisher(FootstepPlan, '/footstep_plan', LATCHED_QOS)
    assert spin_until(executor, lambda: pub_plan.get_subscription_count() > 0, 5.0)
    run_walk(h, scene, T_bc, n=1)                    # one capture at t = 1.0
    m = h.node.mapper
    assert spin_until(executor, lambda: len(h.fine) == 1, 5.0)
    assert m.model_pending and not coarse

    def plan(t):
        msg = FootstepPlan()
        msg.header.stamp = sec_to_stamp(t)
        pub_plan.publish(msg)
    plan(0.5)                                        # an older capture's plan
    spin_until(executor, lambda: not m.model_pending, 0.5)
    assert m.model_pending and not coarse
    plan(1.0)
    assert spin_until(executor, lambda: len(coarse) == 1, 5.0)
    assert not m.model_pending and stamp_to_sec(coarse[0].header.stamp) == 1.0
    got = cloud_to_xyz(coarse[0]).reshape(-1, 3)
    # the same model as a mapper that fuses at once
    ref = IcpMapper(h.node.mapper_cfg, T_bc, m.focal_baseline_px_m)
    ref.update(cloud_to_xyz(cloud_msg(scene, truth_pose(0), T_bc, 1.0)), truth_pose(0), 1.0)
    np.testing.assert_allclose(got, ref.coarse_points(), atol=1e-6)
    assert len(got) > 100 and h.node.model_waits_timed_out == 0

    # without a plan the wall-clock limit finishes it
    for n in (h.node, h.io):
        executor.remove_node(n)
        n.destroy_node()
    h2 = Harness(ros_context, executor, model_after_plan=True, model_wait_max_s=0.3,
                 coarse_publish_every=1)
    coarse2 = []
    h2.io.create_subscription(PointCloud2, '/map/coarse', coarse2.append, LATCHED_QOS)
    run_walk(h2, scene, T_bc, n=1)
    assert h2.node.mapper.model_pending
    assert spin_until(executor, lambda: len(coarse2) == 1, 5.0)
    assert h2.node.model_waits_timed_out == 1 and not h2.node.mapper.model_pending


def _cloud_without_z(n=100):
    msg = xyz_to_cloud(np.zeros((n, 3), np.float32), 'camera_optical', sec_to_stamp(50.0))
    msg.fields = [f for f in msg.fields if f.name != 'z']
    return msg


def _int_cloud(n=100):
    msg = xyz_to_cloud(np.ones((n, 3), np.float32), 'camera_optical', sec_to_stamp(50.0))
    for f in msg.fields:
        f.datatype = PointField.INT32
    return msg


def test_node_bad_input_is_counted_and_leaves_the_map_unchanged(ros_context, executor, world):
    g, scene, T_bc = world
    h = Harness(ros_context, executor)
    run_walk(h, scene, T_bc, n=2)
    spin_until(executor, lambda: len(h.fine) >= 2, 5.0)
    m = h.node.mapper
    before = {k: v.copy() for k, v in m.fine.s.items()}
    coarse = m.coarse_points()
    n_fine = len(h.fine)
    good = cloud_msg(scene, truth_pose(2), T_bc, 50.0)
    nan_cloud = xyz_to_cloud(np.full((120, 160, 3), np.nan, np.float32), 'camera_optical',
                             sec_to_stamp(50.0))
    empty = xyz_to_cloud(np.zeros((0, 3), np.float32), 'camera_optical', sec_to_stamp(50.0))
    old = cloud_msg(scene, truth_pose(1), T_bc, 1.5)  # the map already holds t = 2
    cases = [(lambda: h.cloud(empty), 'empty_cloud'),
             (lambda: h.cloud(nan_cloud), 'all_nan_cloud'),
             (lambda: h.cloud(_cloud_without_z()), 'cloud_missing_xyz'),
             (lambda: h.cloud(_int_cloud()), 'cloud_not_float'),
             (lambda: h.cloud(old), 'cloud_older_than_map'),
             (lambda: h.odom(1.0, truth_pose(1)), 'odom_back_in_time'),
             (lambda: h.odom(2.2, make_T(np.eye(3), [3.0, 0.0, 0.2])), 'odom_jump'),
             (lambda: h.cloud(good), 'no_odometry')]  # odometry ends at 2.05 s
    for send, key in cases:
        send()
        assert spin_until(executor, lambda: h.node.counters[key] >= 1, 5.0), key
    for k, v in before.items():
        np.testing.assert_array_equal(m.fine.s[k], v, err_msg=k)
    np.testing.assert_array_equal(m.coarse_points(), coarse)
    executor.spin_once(timeout_sec=0.1)
    assert len(h.fine) == n_fine
    # the node keeps working after all that
    h.odom(2.5, truth_pose(2))
    h.odom(3.5, truth_pose(2))
    spin_until(executor, lambda: h.node.odom.latest[0] == 3.5, 3.0)
    h.cloud(cloud_msg(scene, truth_pose(2), T_bc, 3.0))
    assert spin_until(executor, lambda: len(h.fine) > n_fine, 10.0)


def test_a_failed_model_update_is_counted_and_the_node_goes_on(ros_context, executor, world):
    """An error in one capture's coarse-model update (stones-15cm blind seed 104: a tumbling
    camera left no point for the model, numpy raised, the node died and was respawned with
    an empty map) is counted and logged; the next capture is mapped as usual."""
    g, scene, T_bc = world
    h = Harness(ros_context, executor)
    run_walk(h, scene, T_bc, n=2)
    real = h.node.mapper.finish_model
    calls = []

    def broken(build_tree=True):
        calls.append(build_tree)
        if len(calls) == 1:
            h.node.mapper._pending_model = None
            raise ValueError('zero-size array to reduction operation minimum')
        return real(build_tree)

    h.node.mapper.finish_model = broken
    try:
        n_fine = len(h.fine)
        h.odom(2.5, truth_pose(2))
        h.odom(3.5, truth_pose(2))
        spin_until(executor, lambda: h.node.odom.latest[0] == 3.5, 3.0)
        h.cloud(cloud_msg(scene, truth_pose(2), T_bc, 3.0))
        assert spin_until(executor, lambda: h.node.counters['model_update_failed'] >= 1, 10.0)
        assert 'ValueError' in h.node.counters.last_reason['model_update_failed']
        h.odom(4.5, truth_pose(3))
        spin_until(executor, lambda: h.node.odom.latest[0] == 4.5, 3.0)
        h.cloud(cloud_msg(scene, truth_pose(3), T_bc, 4.0))
        assert spin_until(executor, lambda: len(h.fine) >= n_fine + 2, 10.0)
        assert len(h.node.mapper.coarse_points()) > 100
    finally:
        h.node.mapper.finish_model = real


def test_node_does_not_map_the_robots_own_legs(ros_context, executor, world):
    """A cloud that also holds points on the front shanks (as the robot's camera sees them):
    with the legs' joint states the node maps the terrain only; the same capture without
    joint states puts the legs into the map as spikes (what the filter prevents)."""
    from sensor_msgs.msg import JointState
    from terrain_perception import kinematics as K
    g, scene, T_bc = world
    m = load_robot_model('littledog')
    q = K.standing_joint_angles(m)
    lp = K.leg_points(m, q)                               # base frame
    t = np.linspace(0.1, 0.9, 15)[:, None]
    legs = np.concatenate([lp[k, 2] + t * (lp[k, 3] - lp[k, 2]) for k in (0, 1)])
    T = truth_pose(0)
    leg_cam = legs @ np.linalg.inv(T_bc)[:3, :3].T + np.linalg.inv(T_bc)[:3, 3]
    terrain = CAM.depth_to_points(scene.depth_image(CAM, T @ T_bc)).reshape(-1, 3)
    pts = np.concatenate([terrain, np.repeat(leg_cam, 20, axis=0)]).astype(np.float32)
    leg_xy = (legs @ T[:3, :3].T + T[:3, 3])[:, :2]
    spikes = {}
    for with_joints in (True, False):
        h = Harness(ros_context, executor)
        pub_js = h.io.create_publisher(JointState, '/joint_states', SENSOR_QOS)
        spin_until(executor, lambda: pub_js.get_subscription_count() > 0, 5.0)
        if with_joints:
            for ts in (0.98, 1.0, 1.02):
                js = JointState(name=list(m.joint_names), position=q.reshape(-1).tolist())
                js.header.stamp = sec_to_stamp(ts)
                pub_js.publish(js)
            assert spin_until(executor, lambda: len(h.node._joints) >= 3, 5.0)
        h.odom(0.95, T)
        h.odom(1.05, T)
        spin_until(executor, lambda: len(h.node.odom) >= 2, 3.0)
        h.cloud(xyz_to_cloud(pts, 'camera_optical', sec_to_stamp(1.0)))
        assert spin_until(executor, lambda: len(h.fine) >= 1, 10.0), 'no /map/fine'
        grid = msg_to_grid(h.fine[-1])
        got = grid.sample(ELEVATION, leg_xy)
        truth = rc.interpolate_height(g, leg_xy)
        # (cells under the legs the camera does not see stay unknown: no spike either)
        spikes[with_joints] = float(np.max(np.nan_to_num(got - truth, nan=0.0)))
        assert (grid[OBSERVED] > 0).sum() > 3000            # the terrain itself was mapped
        executor.remove_node(h.node)
        executor.remove_node(h.io)
        h.node.destroy_node()
        h.io.destroy_node()
    assert spikes[True] < 0.005, spikes
    assert spikes[False] > 0.03, spikes


def test_free_fall_on_the_imu_is_a_disturbance_for_the_mapper(ros_context, executor, world):
    """An IMU sample measuring free fall (specific force ~0) tells the mapper the body moved
    in a way dead reckoning cannot see; a non-finite sample is only counted as bad."""
    from sensor_msgs.msg import Imu
    h = Harness(ros_context, executor)
    m = h.node.mapper

    def imu(t, a):
        msg = Imu()
        msg.header.stamp = sec_to_stamp(t)
        msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z = a
        msg.orientation.w = 1.0
        h.node._on_imu(msg)
    imu(1.0, (0.0, 0.0, 9.81))
    assert m.counters['disturbances'] == 0 and h.node.counters['bad_imu'] == 0
    imu(1.1, (float('nan'), 0.0, 9.81))
    assert m.counters['disturbances'] == 0 and h.node.counters['bad_imu'] == 1
    imu(1.2, (0.1, 0.05, 0.1))
    assert m.counters['disturbances'] == 1 and h.node.counters['bad_imu'] == 2
    assert m._disturbed_at == pytest.approx(1.2)
