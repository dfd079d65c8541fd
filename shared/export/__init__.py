"""A run, out in formats other tools read: KITTI label files and ROS 2 bags (`rmmdet export`)."""
