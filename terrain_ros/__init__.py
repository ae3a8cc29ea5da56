"""ROS 2 glue shared by the project's nodes and tools.

Importing this package applies the project's safe environment defaults (see ``env.py``) before
any rclpy context is created: discovery stays on this host unless the user widened it.
"""

from terrain_ros.env import apply_safe_defaults

apply_safe_defaults()
