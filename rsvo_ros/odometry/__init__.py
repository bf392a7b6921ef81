"""Odometry over video: feature tracking and the pipeline that chains frame pairs (pure numpy and
OpenCV, no ROS). The live node and ``rsvo_replay`` use the same pipeline object."""
