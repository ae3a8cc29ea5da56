"""python -m terrain_ros.tools.plan_replay on a small closed-loop-like bag: a footstep planner
node (config/footstep_planner.yaml, as the launch profiles start it) fed over DDS with a
stance, pose, goal, camera cloud + IMU (its own contact patches) and maps of a kerb; its
published patches and plans recorded with the inputs in arrival order. The tool replays the
bag and must find every plan of its window again, and plans that differ under a changed step
length; refused input is one error line."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest
import yaml

from conftest import spin_until
from test_pipeline_profile import write_bag
from test_planner_node import ROBOT, Harness, _grid, _pose_T, _stance_msg
from terrain_ros.env import config_path

pytestmark = pytest.mark.graph      # a node over DDS in process, the tool as a process

TOOL = 'terrain_ros.tools.plan_replay'
SECS = (10, 11, 12, 13)         # map (= plan, pose, cloud) stamps [s]
FROM, SPAN = 10.5, 2.0          # the window holds the maps of 11 and 12 s
GOAL_XY = (1.0, 0.02)


def _tool(*args):
    return subprocess.run([sys.executable, '-m', TOOL, *map(str, args)],
                          capture_output=True, text=True, timeout=180)


def _one_error_line(res) -> str:
    assert res.returncode == 1, res.stdout + res.stderr
    lines = [ln for ln in res.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith('plan_replay: error: '), res.stderr
    return lines[0]


def _record_run(bag) -> list:
    """Run the planner node on the inputs; write them and its outputs in arrival order.
    Returns the recorded plans as ``(stamp, FootstepPlan)``."""
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import Imu
    from terrain_msgs.msg import Stance

    from terrain_perception.camera import PinholeCamera
    from terrain_perception.gait import nominal_feet_world
    from terrain_perception.raycast import raycast_points
    from terrain_perception.transforms import R_to_quat
    from terrain_ros.conversions import grid_to_msg, matrix_to_pose, xyz_to_cloud
    from terrain_ros.env import params_files
    from terrain_ros.qos import LATCHED_QOS

    ctx = Context()
    args = ['--ros-args']
    for f in params_files('footstep_planner.yaml', 'littledog'):
        args += ['--params-file', str(f)]
    rclpy.init(context=ctx, args=args, domain_id=int(os.environ['ROS_DOMAIN_ID']))
    ex = SingleThreadedExecutor(context=ctx)
    log, plans = [], []

    def rec(topic, msg):
        log.append((100.0 + 0.01 * len(log), topic, msg))
    try:
        h = Harness(ctx, ex, robot='littledog',
                    walking_config_file=str(config_path('walking_controller.yaml')))
        pub_stance = h.io.create_publisher(Stance, '/walking/stance', LATCHED_QOS)
        hh = np.zeros((150, 150))
        hh[93:100, 60:90] = 0.04                  # a 4 cm kerb 18-25 cm ahead
        terrain = _grid(hh)
        cam = ROBOT.camera
        half = PinholeCamera(cam.width // 2, cam.height // 2, cam.fx / 2, cam.fy / 2,
                             (cam.width // 2 - 1) / 2.0, (cam.height // 2 - 1) / 2.0)
        goal = PoseStamped()
        goal.header.frame_id = 'map'
        goal.pose.position.x, goal.pose.position.y = GOAL_XY
        h.pub_goal.publish(goal)
        rec('/goal_pose', goal)
        assert spin_until(ex, lambda: h.node.goal_xy is not None, 5.0)
        feet = np.array(nominal_feet_world(ROBOT, _pose_T()), dtype=float)

        def send_pose(T, sec):
            pose = PoseStamped()
            pose.header.frame_id = 'map'
            pose.header.stamp.sec = sec
            pose.pose = matrix_to_pose(T)
            h.pub_pose.publish(pose)
            rec('/icp/pose', pose)
        send_pose(_pose_T(), SECS[0] - 1)       # known before the first cloud: it waits
        assert spin_until(ex, lambda: h.node.T_map_base is not None, 5.0)
        for k, sec in enumerate(SECS):
            T = _pose_T(0.004 * k, 0.002 * k)
            stance = _stance_msg(feet, k % 4, sec, steps_done=k)
            pub_stance.publish(stance)
            rec('/walking/stance', stance)
            assert spin_until(ex, lambda: h.node.stance is not None
                              and h.node.stance[2] == sec, 5.0)
            imu = Imu()
            imu.header.stamp.sec = sec
            q = R_to_quat(T[:3, :3] @ ROBOT.T_base_imu[:3, :3])
            imu.orientation.x, imu.orientation.y, imu.orientation.z, imu.orientation.w = q
            h.pub_imu.publish(imu)
            assert spin_until(ex, lambda: h.node.imu is not None
                              and h.node.imu[0] == sec, 5.0)
            h.pub_cloud.publish(xyz_to_cloud(
                raycast_points(terrain, half, T @ ROBOT.T_base_camera), 'camera_optical',
                float(sec)))
            assert spin_until(ex, lambda: h.node._patches_pending is not None, 5.0)
            n = len(h.patches)
            send_pose(T, sec)                       # the cloud's pose: its patches come
            assert spin_until(ex, lambda: len(h.patches) > n, 10.0)
            rec('/contact_patches', h.patches[-1])
            grid_msg = grid_to_msg(terrain)
            plan = h.send_map(grid_msg, sec=sec)
            rec('/map/filled', grid_msg)
            rec('/footstep_plan', plan)
            plans.append((float(sec), plan))
    finally:
        for node in list(ex.get_nodes()):
            ex.remove_node(node)
            node.destroy_node()
        ex.shutdown()
        rclpy.try_shutdown(context=ctx)
    write_bag(bag, log)
    return plans


@pytest.fixture(scope='module')
def loop_bag(tmp_path_factory):
    bag = tmp_path_factory.mktemp('plan_replay') / 'bag'
    return bag, _record_run(bag)


def test_recorded_plans_are_found_again_and_a_changed_step_length_differs(loop_bag, tmp_path):
    from terrain_msgs.msg import FootstepPlan
    bag, plans = loop_bag
    for _, p in plans:      # real plans that used the node's patches, not empty agreements
        assert p.status == FootstepPlan.STATUS_OK and len(p.footsteps) == 4, p.status_text
    assert any(f.patch_index >= 0 for _, p in plans for f in p.footsteps)
    assert len({tuple((f.leg, round(f.position.x, 4), round(f.position.y, 4))
                      for f in p.footsteps) for _, p in plans}) == len(plans)

    out = tmp_path / 'same.json'
    res = _tool(bag, '--from', FROM, '--span', SPAN, '--json', out)
    assert res.returncode == 0, res.stdout + res.stderr
    d = json.loads(out.read_text())
    window = [(t, p) for t, p in plans if FROM <= t <= FROM + SPAN]
    assert [p['stamp'] for p in d['plans']] == [t for t, _ in window]
    assert d['compared'] == d['agree'] == len(window) == 2
    assert d['robot'] == 'littledog' and d['params'] == []
    # the node's configuration is the launch profiles': the YAML's values (several differ from
    # the code's defaults: distance_weight_gain, safety_surface...) and the controller's file
    yml = yaml.safe_load(config_path('footstep_planner.yaml').read_text())
    yml = yml['footstep_planner']['ros__parameters']
    for group in ('planner', 'cost'):
        for key, value in yml[group].items():
            assert d['config'][group][key] == value, (group, key)
    assert d['config']['node']['walking_config_file'] == str(
        config_path('walking_controller.yaml'))
    for got, (t, want) in zip(d['plans'], window):
        assert got['agree'] and got['bag_stamp'] == t
        assert [s['leg'] for s in got['ours']] == [f.leg for f in want.footsteps]
        np.testing.assert_allclose([[s['x'], s['y'], s['z']] for s in got['ours']],
                                   [[f.position.x, f.position.y, f.position.z]
                                    for f in want.footsteps], atol=1e-9)
    kinds = [ln.split()[1] for ln in res.stdout.splitlines() if re.match(r' *\d+\.\d{3} ', ln)]
    assert kinds == ['ours', 'bag', 'ours', 'bag']
    assert res.stdout.count('[agrees]') == 2
    assert '2 plans in [10.500, 12.500] s compared, 2 agree' in res.stdout
    assert '11.000 ours n=4 ' in res.stdout and '13.000' not in res.stdout

    # the profile's A is 0.10 m per period; a shorter step moves every foothold
    out = tmp_path / 'short.json'
    res = _tool(bag, '--from', FROM, '--span', SPAN, '--json', out,
                '--param', 'planner.body_move_per_period_m:=0.06')
    assert res.returncode == 0, res.stdout + res.stderr
    d = json.loads(out.read_text())
    assert d['compared'] == 2 and d['agree'] == 0
    assert d['params'] == ['planner.body_move_per_period_m:=0.06']
    assert '2 plans in [10.500, 12.500] s compared, 0 agree' in res.stdout
    assert res.stdout.count('DIFFERS from bag') == 2


def test_the_robots_overlay_is_loaded_after_the_shared_file(loop_bag, tmp_path):
    bag, _ = loop_bag
    overlay = yaml.safe_load(config_path('footstep_planner.frog.yaml').read_text())
    overlay = overlay['footstep_planner']['ros__parameters']['planner']
    out = tmp_path / 'frog.json'
    res = _tool(bag, '--from', 12.5, '--span', 0.0, '--param', 'robot:=frog', '--json', out)
    assert res.returncode == 0, res.stdout + res.stderr
    d = json.loads(out.read_text())
    assert d['robot'] == 'frog' and d['config']['node']['robot'] == 'frog'
    for key, value in overlay.items():
        assert d['config']['planner'][key] == value, key
    res = _tool(bag, '--from', 12.5, '--span', 0.0, '--json', out)
    d = json.loads(out.read_text())
    assert any(d['config']['planner'][key] != value for key, value in overlay.items())


def test_dump_prints_the_planners_last_map(loop_bag):
    bag, _ = loop_bag
    res = _tool(bag, '--from', 12.5, '--span', 0.0, '--dump', '0.101,0.301,-0.02,0.02')
    assert res.returncode == 0, res.stdout + res.stderr
    text = res.stdout
    assert 'elevation [cm]' in text and 'cost [x100]' in text and 'allowed' in text
    rows = text.split('elevation [cm]\n', 1)[1].splitlines()
    assert rows[0].split() == [str(x) for x in range(10, 31, 2)]      # columns x [cm]
    assert [r.split()[0] for r in rows[1:4]] == ['+0.02', '+0.00', '-0.02']
    # the kerb (4 cm) spans x = 0.18-0.25 m, the floor is at 0; the test's map has no
    # observed, filled or upper-bound layer
    assert rows[2].split()[1:] == ['0'] * 4 + ['4'] * 4 + ['0'] * 3
    assert text.count('(the map has no such layer)') == 3


def test_refused_input_is_one_error_line(loop_bag, tmp_path):
    bag, _ = loop_bag
    assert 'does not exist' in _one_error_line(_tool(tmp_path / 'nope', '--from', 0))
    assert "expected NAME:=VALUE" in _one_error_line(
        _tool(bag, '--from', FROM, '--param', 'planner.body_move_per_period_m=0.06'))
    line = _one_error_line(_tool(bag, '--from', FROM, '--param', 'planner.step_length:=0.1'))
    assert "no parameter 'planner.step_length'" in line
    line = _one_error_line(_tool(bag, '--from', FROM, '--param',
                                 'planner.body_move_per_period_m:=-1.0'))
    assert 'planner.body_move_per_period_m' in line and 'out of range' in line
    assert "after the bag's last plan (13.000 s)" in _one_error_line(
        _tool(bag, '--from', 20))
    assert 'X0,X1,Y0,Y1' in _one_error_line(_tool(bag, '--from', FROM, '--dump', '1,2'))
    from terrain_msgs.msg import FootstepPlan
    plan_only = tmp_path / 'plan_only'
    write_bag(plan_only, [(1.0, '/footstep_plan', FootstepPlan())])
    assert 'has no /map/filled' in _one_error_line(_tool(plan_only, '--from', 0))
