"""footstep_planner node in process: maps, pose and goal in -> plans out (content checked against
the core planner); cloud + IMU -> contact patches on the true ground; every bad input gives an
explanatory empty plan and the node keeps running."""

import dataclasses

import numpy as np
import pytest
from geometry_msgs.msg import Point, PoseStamped
from nav_msgs.msg import OccupancyGrid, Path
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import Imu, PointCloud2
from terrain_msgs.msg import ContactPatchArray, Footstep, FootstepPlan, Stance, TerrainGrid

from conftest import spin_until
from footstep_planner_node.node import FootstepPlannerNode
from terrain_perception import features
from terrain_perception.controller import check_footsteps
from terrain_perception import footsteps as fs
from terrain_perception.camera import PinholeCamera
from terrain_perception.gait import nominal_feet_world
from terrain_perception.grid import GridMap
from terrain_perception.raycast import raycast_points
from terrain_perception.robot_model import load_robot_model
from terrain_perception.transforms import R_to_quat
from terrain_ros.conversions import grid_to_msg, matrix_to_pose, xyz_to_cloud
from terrain_ros.qos import LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS

ROBOT = load_robot_model('littledog')
QUADRUPED_PATCHES = {'patches.fixation_down_m': 0.195, 'patches.fixation_forward_m': 0.16,
                     'patches.roi_radius_m': 0.15, 'patches.patch_radius_m': 0.02,
                     'patches.kappa_min_per_m': -68.0, 'patches.kappa_max_per_m': 98.5,
                     'patches.max_residual_m': 0.002, 'patches.bilateral_sigma_depth_m': 0.01}


def _grid(h, stamp=1.0, cost=True):
    g = GridMap(0.01, (-0.75, -0.75), h.shape, {'elevation': h.astype(np.float32)},
                stamp_s=stamp)
    if cost:
        g['cost'] = features.cost_map(h, 0.01)
    return g


def _stance_msg(feet, next_leg, sec, steps_done=0, error=''):
    """A terrain_msgs/Stance in ``map`` with ``feet`` (4, 3) stamped ``sec``."""
    msg = Stance()
    msg.header.frame_id = 'map'
    msg.header.stamp.sec = sec
    msg.feet = [Point(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in feet]
    msg.next_leg = next_leg
    msg.steps_done, msg.last_error = steps_done, error
    return msg


def _pose_T(x=0.0, y=0.0):
    T = np.eye(4)
    T[:3, 3] = [x, y, ROBOT.standing_height_m]
    return T


class Harness:
    def __init__(self, ctx, executor, patch_listener=True, **params):
        overrides = [Parameter(k, value=v) for k, v in params.items()]
        self.node = FootstepPlannerNode(context=ctx, parameter_overrides=overrides)
        self.io = Node('planner_test_io', context=ctx)
        self.ex = executor
        executor.add_node(self.node)
        executor.add_node(self.io)
        self.plans, self.patches, self.costs = [], [], []
        self.pub_map = self.io.create_publisher(TerrainGrid, '/map/filled', LATCHED_QOS)
        self.pub_pose = self.io.create_publisher(PoseStamped, '/icp/pose', RELIABLE_QOS)
        self.pub_goal = self.io.create_publisher(PoseStamped, '/goal_pose', RELIABLE_QOS)
        self.pub_cloud = self.io.create_publisher(PointCloud2, '/stereo/points', SENSOR_QOS)
        self.pub_imu = self.io.create_publisher(Imu, '/imu/data', SENSOR_QOS)
        self.io.create_subscription(FootstepPlan, '/footstep_plan', self.plans.append,
                                    LATCHED_QOS)
        if patch_listener:
            self.io.create_subscription(ContactPatchArray, '/contact_patches',
                                        self.patches.append, RELIABLE_QOS)
        self.io.create_subscription(OccupancyGrid, '/map/cost_grid', self.costs.append,
                                    LATCHED_QOS)
        assert spin_until(executor, lambda: self.node.count_publishers('/map/filled') > 0
                          and self.pub_pose.get_subscription_count() > 0
                          and self.node.pub_plan.get_subscription_count() > 0, 5.0)

    def pose(self, T, sec=0):
        m = PoseStamped()
        m.header.frame_id = 'map'
        m.header.stamp.sec = sec
        m.pose = matrix_to_pose(T)
        n = len(self.node.counters.counts)
        self.pub_pose.publish(m)
        assert spin_until(self.ex, lambda: self.node.T_map_base is not None
                          and np.allclose(self.node.T_map_base, T)
                          or len(self.node.counters.counts) > n, 5.0)

    def send_map(self, msg, sec=None):
        """Publish a map and return the plan made on it (maps in a test carry unique stamps)."""
        self._stamp = getattr(self, '_stamp', 0) + 1
        sec = 1000 + self._stamp if sec is None else sec
        msg.header.stamp.sec = sec
        k = len(self.plans)
        self.pub_map.publish(msg)
        assert spin_until(self.ex, lambda: any(p.header.stamp.sec == sec
                                               for p in self.plans[k:]), 5.0)
        return [p for p in self.plans[k:] if p.header.stamp.sec == sec][-1]


def test_map_pose_goal_give_the_core_plan_and_a_cost_grid(ros_context, executor):
    h = Harness(ros_context, executor)
    h.pose(_pose_T())
    flat = _grid(np.zeros((150, 150)))
    plan = h.send_map(grid_to_msg(flat))
    assert plan.status == FootstepPlan.STATUS_OK, plan.status_text
    # LittleDog's profile allows only the crawl (gait.trot: false)
    assert plan.gait_mode == FootstepPlan.GAIT_WALK and plan.header.frame_id == 'map'
    assert 'walks only' in plan.status_text
    assert plan.body_move_per_period == pytest.approx(ROBOT.body_move_per_period_m)
    want = fs.plan_footsteps(flat, ROBOT, _pose_T())
    got = np.array([[f.position.x, f.position.y, f.position.z] for f in plan.footsteps])
    np.testing.assert_allclose(got, [s.position for s in want.footsteps], atol=1e-6)
    assert [f.leg for f in plan.footsteps] == [s.leg for s in want.footsteps]
    assert spin_until(executor, lambda: len(h.costs) > 0, 5.0)
    cg = h.costs[-1]
    assert (cg.info.width, cg.info.height) == (150, 150) and set(cg.data) == {0}
    # An obstacle ahead: walk, footholds off the obstacle's rim, goal honoured.
    hh = np.zeros((150, 150))
    hh[88:102, 75:90] = 0.03
    rough = _grid(hh, stamp=2.0)
    goal = PoseStamped()
    goal.header.frame_id = 'map'
    goal.pose.position.x, goal.pose.position.y = 0.5, 0.1
    h.pub_goal.publish(goal)
    assert spin_until(executor, lambda: h.node.goal_xy is not None, 5.0)
    plan = h.send_map(grid_to_msg(rough))
    assert plan.status == FootstepPlan.STATUS_OK and plan.gait_mode == FootstepPlan.GAIT_WALK
    want = fs.plan_footsteps(rough, ROBOT, _pose_T(), np.array([0.5, 0.1]))
    got = np.array([[f.position.x, f.position.y, f.position.z] for f in plan.footsteps])
    np.testing.assert_allclose(got, [s.position for s in want.footsteps], atol=1e-6)
    legs = [f.leg for f in plan.footsteps]
    k = fs.CRAWL_ORDER.index(legs[0])                      # crawl order LH, LF, RH, RF (cyclic)
    assert legs == [fs.CRAWL_ORDER[(k + i) % 4] for i in range(len(legs))] and len(legs) == 4
    assert all(f.cost < 0.1 for f in plan.footsteps)
    assert spin_until(executor, lambda: len(h.costs) > 1, 5.0)
    assert max(h.costs[-1].data) == 100
    # The same goal re-sent (the demo re-sends it every 2 s for late joiners): no replan.
    n_plans = len(h.plans)
    for _ in range(3):
        h.pub_goal.publish(goal)
    assert spin_until(executor, lambda: h.node.goals_repeated == 3, 5.0)
    executor.spin_once(timeout_sec=0.2)
    assert len(h.plans) == n_plans
    # A goal moved by more than goal_tolerance_m replans at once, towards it.
    goal.pose.position.y = -0.1
    h.pub_goal.publish(goal)
    assert spin_until(executor, lambda: len(h.plans) > n_plans, 5.0)
    want = fs.plan_footsteps(rough, ROBOT, _pose_T(), np.array([0.5, -0.1]))
    got = np.array([[f.position.x, f.position.y, f.position.z] for f in h.plans[-1].footsteps])
    np.testing.assert_allclose(got, [s.position for s in want.footsteps], atol=1e-6)



def test_the_body_path_round_a_tall_rock_is_published(ros_context, executor):
    # An 11 cm block on the way to the goal (LittleDog's belly is 11.5 cm up): the plan
    # steers round it along the core's body path, published as a nav_msgs/Path at the map's
    # height; on open ground the path is the straight line to the goal.
    h = Harness(ros_context, executor)
    paths = []
    h.io.create_subscription(Path, '/footstep_plan/body_path', paths.append, RELIABLE_QOS)
    assert spin_until(executor, lambda: h.node.pub_body_path.get_subscription_count() > 0, 5.0)
    h.pose(_pose_T())
    goal = PoseStamped()
    goal.header.frame_id = 'map'
    goal.pose.position.x = 0.7
    h.pub_goal.publish(goal)
    assert spin_until(executor, lambda: h.node.goal_xy is not None, 5.0)
    hh = np.zeros((150, 150))
    hh[105:125, 60:85] = 0.11                    # x 0.30..0.50, y -0.15..0.10
    rock = _grid(hh)
    plan = h.send_map(grid_to_msg(rock))
    assert plan.status == FootstepPlan.STATUS_OK, plan.status_text
    assert spin_until(executor, lambda: len(paths) > 0, 5.0)
    got = np.array([[p.pose.position.x, p.pose.position.y] for p in paths[-1].poses])
    want = fs.FootstepPlanner(ROBOT, fs.PlannerConfig())
    assert want.set_map(rock) is None
    want.plan(_pose_T(), np.array([0.7, 0.0]))
    np.testing.assert_allclose(got, want.body_path.points, atol=1e-9)
    assert paths[-1].header.frame_id == 'map' and got[:, 1].max() > 0.15   # round the left
    assert all(p.pose.position.z == pytest.approx(0.0) for p in paths[-1].poses)
    k = len(paths)
    h.send_map(grid_to_msg(_grid(np.zeros((150, 150)), stamp=2.0)))
    assert spin_until(executor, lambda: len(paths) > k, 5.0)
    np.testing.assert_allclose([[p.pose.position.x, p.pose.position.y]
                                for p in paths[-1].poses], [[0.0, 0.0], [0.7, 0.0]], atol=1e-9)


def _stance_scene(ros_context, executor, **params):
    """A planner node at the pose with an obstacle ahead (walk gait), a publisher of the
    controller's stance and the nominal feet there: ``(harness, heights, publisher, feet)``."""
    h = Harness(ros_context, executor, **params)
    h.pose(_pose_T())
    hh = np.zeros((150, 150))
    hh[88:102, 75:90] = 0.03                                # walk gait (obstacle ahead)
    pub = h.io.create_publisher(Stance, '/walking/stance', LATCHED_QOS)
    feet = np.array(nominal_feet_world(ROBOT, _pose_T()), dtype=float)
    return h, hh, pub, feet


def test_plans_start_from_the_controllers_stance(ros_context, executor):
    # The controller says where its feet will stand and which leg is next: the plan starts
    # there (not from the nominal stance), and a malformed stance is refused and counted.
    h, hh, pub, feet = _stance_scene(ros_context, executor, check_steps=0)   # dry-run all
    feet[0, 0] += 0.03                                      # LF already a step ahead
    pub.publish(_stance_msg(feet, Footstep.LEG_RH, 1001))
    assert spin_until(executor, lambda: h.node.stance is not None, 5.0)
    plan = h.send_map(grid_to_msg(_grid(hh)), sec=1001)
    assert plan.status == FootstepPlan.STATUS_OK, plan.status_text
    want = fs.plan_footsteps(_grid(hh), ROBOT, _pose_T(), feet=feet, first_leg=Footstep.LEG_RH)
    # published: the prefix that the controller's dry run from that stance accepts (here the
    # shank check stops it at LH: LF's shank would dip 2 mm into the box's map cells)
    legs = np.array([s.leg for s in want.footsteps])
    n, _ = check_footsteps(ROBOT, h.node.walking_cfg, feet, legs,
                           np.array([s.position for s in want.footsteps]), 'walk',
                           _grid(hh), T_body=_pose_T())
    assert n >= 1
    assert [f.leg for f in plan.footsteps] == list(legs[:n])
    assert plan.footsteps[0].leg == Footstep.LEG_RH
    got = np.array([[f.position.x, f.position.y, f.position.z] for f in plan.footsteps])
    np.testing.assert_allclose(got, [s.position for s in want.footsteps[:n]], atol=1e-6)
    bad = Stance()
    bad.feet = [Point(x=float('nan'))] * 4
    pub.publish(bad)
    assert spin_until(executor, lambda: h.node.counters.counts.get('bad_stance', 0) > 0, 5.0)
    assert h.node.stance[1] == Footstep.LEG_RH                 # the good one is kept


def test_the_dry_run_checks_only_the_plans_first_steps(ros_context, executor, monkeypatch):
    # check_steps: the dry run covers the steps the controller starts before the next plan
    # (about one per plan); the rest stand as planned (the controller refuses a bad one
    # itself), and a refusal among the checked ones still cuts the plan there.
    import footstep_planner_node.node as node_mod
    given, accept = [], {'n': 99}

    def fake(robot, cfg, feet, legs, positions, *a, **k):
        given.append(len(legs))
        n = min(accept['n'], len(legs))
        return n, ('' if n == len(legs) else 'fake refusal')
    monkeypatch.setattr(node_mod, 'check_footsteps', fake)
    h, hh, pub, feet = _stance_scene(ros_context, executor, check_steps=2)
    pub.publish(_stance_msg(feet, Footstep.LEG_RH, 1001))
    assert spin_until(executor, lambda: h.node.stance is not None, 5.0)
    want = fs.plan_footsteps(_grid(hh), ROBOT, _pose_T(), feet=feet, first_leg=Footstep.LEG_RH)
    assert len(want.footsteps) == 4
    plan = h.send_map(grid_to_msg(_grid(hh)), sec=1001)
    assert given == [2] and len(plan.footsteps) == 4, plan.status_text
    accept['n'] = 1                                  # the second step refused: cut after one
    plan = h.send_map(grid_to_msg(_grid(hh)), sec=1001)
    assert given[-1] == 2 and len(plan.footsteps) == 1 and 'fake refusal' in plan.status_text
    h.node.node_cfg = dataclasses.replace(h.node.node_cfg, check_steps=0)   # every step
    accept['n'] = 99
    plan = h.send_map(grid_to_msg(_grid(hh)), sec=1001)
    assert given[-1] == 4 and len(plan.footsteps) == 4


def test_a_step_the_controller_refused_is_not_offered_again(ros_context, executor):
    # The dry run of the controller's checks cannot know everything the running controller
    # does, so it can accept a step the controller then refuses; re-sending that step plan
    # after plan was run X's 50 s livelock. After the refusal the plan from the same stance
    # starts differently; once the controller has stepped, the memory is cleared.
    h, hh, pub, feet = _stance_scene(ros_context, executor)

    def stance(done, error=''):
        n = h.node.counters.counts.get('step_refused_by_controller', 0)
        # stamped at the maps' time (stance_max_age_s)
        pub.publish(_stance_msg(feet, Footstep.LEG_RH, 1001, done, error))
        assert spin_until(executor, lambda: h.node.stance_steps_done == done
                          and (not error or h.node.counters.counts.get(
                              'step_refused_by_controller', 0) > n), 5.0)

    def first(plan):
        assert plan.status == FootstepPlan.STATUS_OK, plan.status_text
        f = plan.footsteps[0]
        return f.leg, np.array([f.position.x, f.position.y])

    stance(5)
    leg1, p1 = first(h.send_map(grid_to_msg(_grid(hh))))
    assert leg1 == Footstep.LEG_RH
    leg, p = first(h.send_map(grid_to_msg(_grid(hh))))      # deterministic: the same step
    assert leg == leg1 and np.allclose(p, p1)
    stance(5, "body shift leaves the legs' reach: pose 30 leg RH: target beyond the leg length")
    leg, p = first(h.send_map(grid_to_msg(_grid(hh))))
    assert leg != leg1 or np.linalg.norm(p - p1) > h.node.refused.tolerance_m, (leg, p, p1)
    assert h.node.counters.counts.get('plan_changed_by_controller_check', 0) > 0
    stance(6)                                               # it stepped: forgotten
    leg, p = first(h.send_map(grid_to_msg(_grid(hh))))
    assert leg == leg1 and np.allclose(p, p1)


def test_bad_inputs_give_explanatory_empty_plans(ros_context, executor):
    h = Harness(ros_context, executor)
    flat = _grid(np.zeros((150, 150)))
    plan = h.send_map(grid_to_msg(flat))                    # no pose yet
    assert plan.status == FootstepPlan.STATUS_BAD_INPUT and 'pose' in plan.status_text
    h.pose(_pose_T())
    nocost = _grid(np.zeros((150, 150)), cost=False)
    plan = h.send_map(grid_to_msg(nocost))
    assert plan.status == FootstepPlan.STATUS_BAD_MAP and "'cost'" in plan.status_text
    empty = _grid(np.full((150, 150), np.nan), cost=False)
    empty['cost'] = np.full((150, 150), np.nan, np.float32)
    plan = h.send_map(grid_to_msg(empty))
    assert plan.status == FootstepPlan.STATUS_BAD_MAP and 'empty' in plan.status_text
    broken = grid_to_msg(flat)
    broken.data[0].data = broken.data[0].data[:10]          # wrong size: malformed message
    plan = h.send_map(broken)
    assert plan.status == FootstepPlan.STATUS_BAD_MAP and 'values' in plan.status_text
    h.pose(_pose_T(3.0, 0.0))                               # robot off the map
    plan = h.send_map(grid_to_msg(flat))
    assert plan.status == FootstepPlan.STATUS_ROBOT_OUTSIDE_MAP
    h.pose(_pose_T())
    goal = PoseStamped()
    goal.pose.position.x = 5.0                              # beyond the local map
    h.pub_goal.publish(goal)
    assert spin_until(executor, lambda: h.node.goal_xy is not None, 5.0)
    island = np.full((150, 150), np.nan)
    island[0:10, 0:10] = 0.0                 # known only in a corner no leg reaches: stuck
    plan = h.send_map(grid_to_msg(_grid(island)))
    assert plan.status == FootstepPlan.STATUS_NO_FOOTHOLD
    assert 'cannot be reached' in plan.status_text
    bad_pose = PoseStamped()
    bad_pose.pose.orientation.w = 0.0                       # zero quaternion: refused, counted
    h.pub_pose.publish(bad_pose)
    assert spin_until(executor, lambda: h.node.counters['bad_pose'] == 1, 5.0)
    for p in h.plans:
        if p.status != FootstepPlan.STATUS_OK:
            assert len(p.footsteps) == 0 and p.status_text
    assert h.node.counters['bad_map'] >= 3
    # Still alive and planning.
    plan = h.send_map(grid_to_msg(flat))
    assert plan.status == FootstepPlan.STATUS_OK


@pytest.mark.parametrize('mode', ['on_pose', 'on_arrival'])
def test_cloud_and_imu_give_contact_patches_on_the_ground(ros_context, executor, mode):
    # patches_on_pose (default): a cloud's patches are found on its arrival (beside the ICP)
    # and wait for the mapper's pose of its stamp; off: placed at the latest pose at once.
    on_pose = mode == 'on_pose'
    params = dict(QUADRUPED_PATCHES)
    params['planner.horizon_steps'] = 8       # patches are two steps ahead (the fixation point)
    params['patches_on_pose'] = on_pose
    h = Harness(ros_context, executor, **params)
    T_map_base = _pose_T(0.0, 0.0)
    h.pose(T_map_base)
    terrain, pts, imu = _kerb_view(T_map_base)              # a 4 cm kerb in view
    T_map_cam = T_map_base @ ROBOT.T_base_camera
    cloud = xyz_to_cloud(pts, 'camera_optical', 10.0)
    h.pub_cloud.publish(cloud)                               # before any IMU: counted, dropped
    assert spin_until(executor, lambda: h.node.counters['no_imu'] == 1, 5.0)
    assert h.node._patches_pending is None
    h.pub_imu.publish(imu)
    assert spin_until(executor, lambda: h.node.imu is not None, 5.0)
    h.pub_cloud.publish(cloud)
    if on_pose:
        # found on arrival, in the camera frame, kept for the pose
        assert spin_until(executor, lambda: h.node._patches_pending is not None, 5.0)
        assert len(h.node._patches_pending[0]) >= 50 and h.node.patches_map is None
        assert not spin_until(executor, lambda: len(h.patches) > 0, 0.5)   # waits
        h.pose(T_map_base, sec=9)                            # an older pose: still waits
        assert not spin_until(executor, lambda: len(h.patches) > 0, 0.3)
        assert h.node._patches_pending is not None
        h.pub_cloud.publish(cloud)                           # replaced before its pose came
        assert spin_until(executor, lambda: h.node.counters['cloud_without_pose'] == 1, 5.0)
        h.pose(T_map_base, sec=10)
    assert spin_until(executor, lambda: len(h.patches) > 0, 10.0)
    msg = h.patches[-1]
    assert msg.header.frame_id == 'map' and len(msg.patches) >= 50
    g = np.array([msg.gravity.x, msg.gravity.y, msg.gravity.z])
    np.testing.assert_allclose(g, [0, 0, -1], atol=1e-9)
    fix = np.array([msg.fixation_point.x, msg.fixation_point.y, msg.fixation_point.z])
    assert abs(fix[2] - (T_map_cam[2, 3] - 0.195)) < 1e-6
    for p in msg.patches:
        z = p.pose.position.z
        on_floor, on_kerb = abs(z) < 0.003, abs(z - 0.04) < 0.003
        assert on_floor or on_kerb, z
        assert len(p.boundary) == 12 and p.kx <= p.ky and p.residual <= 0.002
        assert p.support_points >= 12
    # Patches feed the next plan (patch indices refer to this array).
    plan = h.send_map(grid_to_msg(terrain), sec=10)
    assert plan.status == FootstepPlan.STATUS_OK, plan.status_text
    assert any(f.patch_index >= 0 for f in plan.footsteps)
    assert all(-1 <= f.patch_index < len(msg.patches) for f in plan.footsteps)


def _kerb_view(T_map_base, sec=10):
    """Flat ground with a 4 cm kerb 0.18-0.25 m ahead of the origin: its GridMap, the
    half-resolution camera's cloud points from ``T_map_base`` and an IMU message of that
    attitude stamped ``sec``."""
    hh = np.zeros((150, 150))
    hh[93:100, 60:90] = 0.04
    terrain = _grid(hh)
    cam = ROBOT.camera
    half = PinholeCamera(cam.width // 2, cam.height // 2, cam.fx / 2, cam.fy / 2,
                         (cam.width // 2 - 1) / 2.0, (cam.height // 2 - 1) / 2.0)
    pts = raycast_points(terrain, half, T_map_base @ ROBOT.T_base_camera)
    imu = Imu()
    imu.header.stamp.sec = sec
    q = R_to_quat(T_map_base[:3, :3] @ ROBOT.T_base_imu[:3, :3])
    imu.orientation.x, imu.orientation.y, imu.orientation.z, imu.orientation.w = q
    return terrain, pts, imu


def test_patches_are_placed_at_the_captures_pose(ros_context, executor):
    """patches_on_pose: found when the cloud arrives (the latest pose then is the previous
    capture's), placed at the mapper's pose of the cloud's stamp when it comes."""
    params = dict(QUADRUPED_PATCHES)
    h = Harness(ros_context, executor, patch_listener=False, **params)
    T_map_base = _pose_T(-0.05, 0.02)
    h.pose(_pose_T(0.0, 0.0))                        # the previous capture's pose
    _, pts, imu = _kerb_view(T_map_base)
    h.pub_imu.publish(imu)
    assert spin_until(executor, lambda: h.node.imu is not None, 5.0)
    h.pub_cloud.publish(xyz_to_cloud(pts, 'camera_optical', 10.0))
    assert spin_until(executor, lambda: h.node._patches_pending is not None, 5.0)
    assert h.node.patches_map is None
    h.pose(T_map_base, sec=10)                       # this capture's pose
    assert spin_until(executor, lambda: h.node.patches_map is not None, 5.0)
    h.pose(_pose_T(0.3, 0.0), sec=11)                # the body moved on meanwhile
    assert not spin_until(executor, lambda: h.node._patches_pending is not None, 0.2)
    v = h.node.patches_map.vertex
    kerb = np.abs(v[:, 2] - 0.04) < 0.003
    assert len(v) >= 50 and np.all(kerb | (np.abs(v[:, 2]) < 0.003))
    # on the kerb (x 0.18-0.25 m) in the map: placed at the capture's pose, not the latest
    assert kerb.sum() >= 5 and np.all((v[kerb, 0] > 0.17) & (v[kerb, 0] < 0.26))
    assert h.node.patches_stamp == 10.0 and not h.plans


def test_patches_feed_the_plan_without_a_listener_and_no_message_is_built(
        ros_context, executor, monkeypatch):
    # /contact_patches is built only for a subscriber (~20 ms of Python per capture that ran
    # beside the terrain fill); the planner's own use of the patches does not depend on it.
    import footstep_planner_node.node as planner_module
    built = []
    real = planner_module.patches_to_msg
    monkeypatch.setattr(planner_module, 'patches_to_msg',
                        lambda *a, **k: built.append(1) or real(*a, **k))
    params = dict(QUADRUPED_PATCHES)
    params['planner.horizon_steps'] = 8
    params['patches_on_pose'] = False
    h = Harness(ros_context, executor, patch_listener=False, **params)
    T_map_base = _pose_T(0.0, 0.0)
    h.pose(T_map_base)
    terrain, pts, imu = _kerb_view(T_map_base)
    h.pub_imu.publish(imu)
    assert spin_until(executor, lambda: h.node.imu is not None, 5.0)
    assert h.node.pub_patches.get_subscription_count() == 0
    h.pub_cloud.publish(xyz_to_cloud(pts, 'camera_optical', 10.0))
    assert spin_until(executor, lambda: h.node.patches_map is not None, 10.0)
    assert len(h.node.patches_map) >= 50 and not built
    plan = h.send_map(grid_to_msg(terrain), sec=10)
    assert plan.status == FootstepPlan.STATUS_OK, plan.status_text
    assert any(f.patch_index >= 0 for f in plan.footsteps)
    assert not built


def test_the_dry_run_reads_the_controllers_yaml(ros_context, executor, tmp_path):
    # walking_config_file: a parameter changed in the controller's YAML changes the planner's
    # dry run too (the launch profiles pass config/walking_controller.yaml); a bad file is
    # refused at start with its name
    from terrain_ros.env import config_path
    y = tmp_path / 'walking.yaml'
    y.write_text(config_path('walking_controller.yaml').read_text().replace(
        'belly_clearance_m: 0.012', 'belly_clearance_m: 0.03'))
    h = Harness(ros_context, executor, walking_config_file=str(y))
    assert h.node.walking_cfg.belly_clearance_m == 0.03
    executor.remove_node(h.node)
    h.node.destroy_node()
    with pytest.raises(ValueError, match='walking_config_file'):
        FootstepPlannerNode(context=ros_context, parameter_overrides=[
            Parameter('walking_config_file', value=str(tmp_path / 'missing.yaml'))])
