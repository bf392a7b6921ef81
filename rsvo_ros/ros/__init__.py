"""The ROS shells: the node, its parameters and message conversion, the bag player, the recorder,
the latency probe and bag I/O. The only layer that imports rclpy, rosbags or message packages;
everything here is a thin shell over :mod:`rsvo_ros.odometry`."""

from rsvo_ros import limit_blas_threads

limit_blas_threads()  # before numpy loads OpenBLAS
