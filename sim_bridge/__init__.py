"""sim_bridge: the pybullet simulator as a ROS 2 node (the project's embedded data source)."""
