"""Synthetic rolling-shutter data with exact ground truth: the paper's Sec. 7.1 scene and a
rendered corridor (pure numpy and OpenCV, no ROS)."""
