"""Graph test: the two-computer split (split_robot.yaml + split_offboard.yaml) on this host.

Two ``terrain-launch`` processes, as on a robot and an off-board computer, on one domain of
their own (LOCALHOST here; SUBNET across computers, see README "Network"). The loop must close
across them: the off-board mapper builds ``/map/fine`` from the robot's stereo clouds, the
off-board planner's plans reach the robot's controller, and the ICP correction goes back.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.graph

REPO = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
DOMAIN = int(os.environ.get('TERRAIN_GRAPH_DOMAIN_BASE', '60')) + 2

ROBOT_NODES = {'sim_bridge', 'stereo_node', 'walking_controller'}
OFFBOARD_NODES = {'icp_mapper', 'terrain_fill', 'footstep_planner'}


def _launch(name: str, args, log: Path, env) -> subprocess.Popen:
    return subprocess.Popen([str(BIN / 'terrain-launch'), str(REPO / 'config' / 'launch' / name),
                             *args, '--grace', '3'], env=env, stdout=open(log, 'w'),
                            stderr=subprocess.STDOUT, start_new_session=True)


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


@pytest.mark.timeout(420)
def test_split_graph_closes_the_loop_across_two_launchers(tmp_path):
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from geometry_msgs.msg import PoseStamped
    from terrain_msgs.msg import FootstepPlan, TerrainGrid
    from terrain_ros.qos import LATCHED_QOS
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    robot = _launch('split_robot.yaml', ['image_scale:=0.5', 'shadows:=false', 'seed:=2'],
                    tmp_path / 'robot.log', env)
    offboard = _launch('split_offboard.yaml', [], tmp_path / 'offboard.log', env)
    ctx = Context()
    rclpy.init(context=ctx, domain_id=DOMAIN, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('split_probe', context=ctx, start_parameter_services=False)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    got = {}

    def keep(topic):
        return lambda m: got.__setitem__(topic, m)
    node.create_subscription(TerrainGrid, '/map/fine', keep('/map/fine'), LATCHED_QOS)
    node.create_subscription(FootstepPlan, '/footstep_plan', keep('/footstep_plan'),
                             LATCHED_QOS)
    node.create_subscription(PoseStamped, '/icp/correction', keep('/icp/correction'),
                             LATCHED_QOS)
    try:
        deadline = time.monotonic() + 300.0
        while time.monotonic() < deadline and len(got) < 3:
            ex.spin_once(timeout_sec=0.1)
            assert robot.poll() is None, (tmp_path / 'robot.log').read_text()[-3000:]
            assert offboard.poll() is None, (tmp_path / 'offboard.log').read_text()[-3000:]
        assert len(got) == 3, (f'received only {sorted(got)} within 300 s\n'
                               + (tmp_path / 'offboard.log').read_text()[-2000:])
        # Each product came from the other launcher's process than its inputs. An endpoint can
        # be discovered before its node's name (rmw's '_NODE_NAME_UNKNOWN_' until the remote
        # participant's node list arrives; seen once with the machine loaded): wait for names.
        def graph():
            pubs = {t: {i.node_name for i in node.get_publishers_info_by_topic(t)}
                    for t in ('/stereo/points', '/map/fine', '/footstep_plan', '/joint_commands',
                              '/odom/dead_reckoning', '/icp/correction')}
            subs = {t: {i.node_name for i in node.get_subscriptions_info_by_topic(t)}
                    for t in ('/footstep_plan', '/icp/correction')}
            return pubs, subs
        deadline = time.monotonic() + 30.0
        pubs, subs = graph()
        while time.monotonic() < deadline and any(
                '_NODE_NAME_UNKNOWN_' in names for d in (pubs, subs) for names in d.values()):
            ex.spin_once(timeout_sec=0.1)
            pubs, subs = graph()
        assert pubs['/stereo/points'] <= ROBOT_NODES and pubs['/stereo/points'], pubs
        assert pubs['/map/fine'] == {'icp_mapper'}, pubs
        assert pubs['/footstep_plan'] == {'footstep_planner'}, pubs
        assert pubs['/joint_commands'] == {'walking_controller'}, pubs
        assert 'walking_controller' in subs['/footstep_plan'], subs
        assert 'walking_controller' in subs['/icp/correction'], subs
        # The map is built from real clouds: some cells are observed.
        from terrain_ros.conversions import msg_to_grid
        from terrain_ros.report import observed_mask
        assert int(observed_mask(msg_to_grid(got['/map/fine'])).sum()) > 100
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        _stop(offboard)
        _stop(robot)
