"""Processes for the CLI-tool tests: a publisher of known messages and a receiver that saves
what it got. Run as ``python tools_fixture.py pub N`` / ``python tools_fixture.py recv OUT N``.

The messages are deterministic functions of their index, so a test can compare content
(serialized bytes), not just counts.
"""

from __future__ import annotations

import pickle
import sys
import time

import numpy as np

TOPICS = {
    '/stereo/left/image_rect': 'sensor_msgs/msg/Image',
    '/imu/data': 'sensor_msgs/msg/Imu',
    '/joint_states': 'sensor_msgs/msg/JointState',
    '/map/fine': 'terrain_msgs/msg/TerrainGrid',
    '/footstep_plan': 'terrain_msgs/msg/FootstepPlan',
}


def make_messages(i: int) -> dict:
    from geometry_msgs.msg import Point
    from sensor_msgs.msg import Imu, JointState
    from terrain_msgs.msg import Footstep, FootstepPlan

    from terrain_perception.grid import GridMap
    from terrain_ros import conversions as cv
    rng = np.random.default_rng(i)
    stamp = 100.0 + 0.05 * i
    img = cv.numpy_to_image(rng.integers(0, 255, (24, 32, 3), dtype=np.uint8), 'rgb8',
                            'camera_optical', stamp)
    imu = Imu()
    imu.header = cv.make_header('imu', stamp)
    imu.linear_acceleration.z = 9.81 + float(rng.normal())
    imu.orientation.w = 1.0
    js = JointState(name=[f'j{k}' for k in range(12)], position=rng.normal(size=12).tolist())
    js.header = cv.make_header('', stamp)
    elev = rng.normal(size=(6, 5)).astype(np.float32)
    elev[0, 0] = np.nan
    grid = cv.grid_to_msg(GridMap.from_layers(0.01, (0.0, 0.0), {'elevation': elev},
                                              stamp_s=stamp))
    plan = FootstepPlan(status_text=f'plan {i}', gait_mode=FootstepPlan.GAIT_WALK,
                        footsteps=[Footstep(leg=k, step_index=k,
                                            position=Point(x=float(i), y=0.1 * k))
                                   for k in range(4)])
    plan.header = cv.make_header('map', stamp)
    return {'/stereo/left/image_rect': img, '/imu/data': imu, '/joint_states': js,
            '/map/fine': grid, '/footstep_plan': plan}


def _qos(topic: str):
    from terrain_ros.qos import LATCHED_QOS, RELIABLE_QOS
    if topic == '/map/fine':
        return LATCHED_QOS
    from rclpy.qos import QoSProfile
    return QoSProfile(depth=100) if topic else RELIABLE_QOS


def publish(n: int) -> None:
    import rclpy
    from terrain_ros.tools.common import message_class
    rclpy.init()
    node = rclpy.create_node('fixture_pub')
    pubs = {t: node.create_publisher(message_class(ty), t, _qos(t)) for t, ty in TOPICS.items()}
    deadline = time.monotonic() + 20.0
    while any(p.get_subscription_count() == 0 for p in pubs.values()):
        if time.monotonic() > deadline:
            sys.exit('fixture_pub: no subscriber appeared')
        time.sleep(0.05)
    time.sleep(0.5)
    for i in range(n):
        for t, msg in make_messages(i).items():
            pubs[t].publish(msg)
        time.sleep(0.05)
    time.sleep(1.0)
    node.destroy_node()
    rclpy.shutdown()


def receive(out: str, n: int, timeout_s: float = 30.0) -> None:
    import rclpy
    from rclpy.serialization import serialize_message
    from terrain_ros.tools.common import message_class
    rclpy.init()
    node = rclpy.create_node('fixture_recv')
    got = {t: [] for t in TOPICS}
    for t, ty in TOPICS.items():
        node.create_subscription(message_class(ty), t,
                                 lambda m, t=t: got[t].append(serialize_message(m)), _qos(t))
    print('ready', flush=True)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and any(len(v) < n for v in got.values()):
        rclpy.spin_once(node, timeout_sec=0.05)
    with open(out, 'wb') as f:
        pickle.dump(got, f)
    node.destroy_node()
    rclpy.shutdown()


if __name__ == '__main__':
    if sys.argv[1] == 'pub':
        publish(int(sys.argv[2]))
    else:
        receive(sys.argv[2], int(sys.argv[3]))
