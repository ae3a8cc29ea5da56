"""walking_controller in process: joint states + a footstep plan in, joint trajectories that
hold the stance and then walk it, dead reckoning and capture requests out; bad input counted."""

import numpy as np
from geometry_msgs.msg import Point
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import Header
from terrain_msgs.msg import Footstep, FootstepPlan
from trajectory_msgs.msg import JointTrajectory

from conftest import spin_until
from terrain_perception import gait as G
from terrain_perception import kinematics as K
from terrain_perception.robot_model import load_robot_model
from terrain_perception.transforms import make_T
from terrain_ros.conversions import make_header, pose_to_matrix
from terrain_ros.qos import LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS
from walking_controller_node.node import WalkingControllerNode

MODEL = load_robot_model('littledog')


def _plan(legs, pos, frame='map', gait=FootstepPlan.GAIT_WALK, status=FootstepPlan.STATUS_OK):
    msg = FootstepPlan(header=make_header(frame, 0.0), gait_mode=gait, status=status)
    for k, (leg, p) in enumerate(zip(legs, pos)):
        msg.footsteps.append(Footstep(leg=int(leg), position=Point(x=float(p[0]), y=float(p[1]),
                                                                   z=float(p[2])),
                                      step_index=k, patch_index=-1))
    return msg


def test_node_holds_stance_then_walks_the_plan(ros_context, executor):
    node = WalkingControllerNode(context=ros_context, parameter_overrides=[
        Parameter('initial_x_m', value=0.4), Parameter('control_rate_hz', value=50.0)])
    io = Node('walking_test_io', context=ros_context)
    executor.add_node(node)
    executor.add_node(io)
    got = {'cmd': [], 'odom': [], 'cap': []}
    io.create_subscription(JointTrajectory, '/joint_commands', got['cmd'].append, RELIABLE_QOS)
    io.create_subscription(Odometry, '/odom/dead_reckoning', got['odom'].append, RELIABLE_QOS)
    io.create_subscription(Header, '/capture_request', got['cap'].append, RELIABLE_QOS)
    pub_js = io.create_publisher(JointState, '/joint_states', SENSOR_QOS)
    pub_plan = io.create_publisher(FootstepPlan, '/footstep_plan', LATCHED_QOS)

    q = K.standing_joint_angles(MODEL).reshape(12)
    order = np.random.default_rng(0).permutation(12)          # names in any order
    js = JointState(name=[MODEL.joint_names[i] for i in order], position=q[order].tolist(),
                    velocity=[0.0] * 12)

    def publish_js():
        pub_js.publish(js)
        return len(got['cmd']) >= 5 and len(got['odom']) >= 5

    assert spin_until(executor, publish_js, 10.0)
    cmd = got['cmd'][-1]
    assert list(cmd.joint_names) == list(MODEL.joint_names)
    assert len(cmd.points) == 51
    np.testing.assert_allclose(cmd.points[0].positions, q, atol=1e-9)   # holds the stance
    T = pose_to_matrix(got['odom'][-1].pose.pose)
    np.testing.assert_allclose(T[:3, 3], [0.4, 0.0, MODEL.standing_height_m], atol=1e-9)
    assert got['odom'][-1].header.frame_id == 'odom'
    # Standing still: capture requests (paper 000: the controller asks for pictures).
    assert spin_until(executor, lambda: publish_js() and len(got['cap']) >= 1, 5.0)

    # Bad inputs are counted and change nothing.
    def publish_bad_js():
        pub_js.publish(JointState(name=['LF_knee'], position=[0.1]))
        return True

    legs, pos = G.straight_footsteps(MODEL, make_T(t=[0.4, 0.0, MODEL.standing_height_m]), 0.3)
    bad = pos.copy()
    bad[2, 0] = np.nan
    pub_plan.publish(_plan(legs, bad))
    ok = spin_until(executor, lambda: publish_bad_js() and node.counters['bad_plan'] == 1
                    and node.counters['joint_state_missing_joint'] >= 1, 5.0)
    assert ok, dict(node.counters.counts)
    assert node.controller.pending_steps == 0

    # A good plan in the map frame: the body starts moving forward along it.
    n_cmd = len(got['cmd'])
    pub_plan.publish(_plan(legs, pos))
    assert spin_until(executor, lambda: publish_js() and node.controller.status == 'walking',
                      5.0)
    assert spin_until(executor, lambda: publish_js() and
                      pose_to_matrix(got['odom'][-1].pose.pose)[0, 3] > 0.405, 5.0)
    moving = [c for c in got['cmd'][n_cmd:]
              if np.abs(np.array(c.points[0].positions) - q).max() > 1e-3]
    assert moving, 'joint commands never left the stance'
    # Every published point is within the joint limits (the bridge refuses others).
    for c in got['cmd']:
        P = np.array([p.positions for p in c.points])
        assert np.all(P >= MODEL.joint_lower - 1e-12) and np.all(P <= MODEL.joint_upper + 1e-12)
    # A plan with a failed status clears the pending steps.
    pub_plan.publish(_plan([], np.zeros((0, 3)), status=FootstepPlan.STATUS_NO_MAP))
    assert spin_until(executor, lambda: publish_js() and node.controller.pending_steps == 0,
                      5.0)
