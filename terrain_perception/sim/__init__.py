"""pybullet simulation: world, robots, sensors (ROS-free)."""
