"""The QoS profiles the project's topics use (named once, here)."""

from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)

#: Camera images, clouds, IMU, joint states: best effort, keep last 5.
SENSOR_QOS = qos_profile_sensor_data

#: Maps, plans, corrections that late joiners need: reliable, transient local, depth 1.
LATCHED_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)

#: Commands, odometry, events: reliable, volatile, depth 10.
RELIABLE_QOS = QoSProfile(depth=10, history=HistoryPolicy.KEEP_LAST,
                          reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.VOLATILE)
