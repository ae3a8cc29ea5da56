"""stereo_node: the ROS 2 wrapper of terrain_perception.stereo and .ground_plane."""
