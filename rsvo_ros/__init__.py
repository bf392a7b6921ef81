"""rsvo_ros: monocular visual odometry for rolling-shutter cameras (Lee & Yoon), ROS 2 Jazzy.

Layers, each importing only the ones listed before it (``test/test_layout.py`` checks this):

- :mod:`rsvo_ros.core`: rotations, the rolling-shutter camera, projections.
- :mod:`rsvo_ros.twoview`: the paper: the RS essential matrix, its compiled kernels, the
  search and :func:`~rsvo_ros.twoview.estimator.estimate_relative_pose` with the GS/MVO
  baselines.
- :mod:`rsvo_ros.odometry`: feature tracking and the odometry pipeline.
- :mod:`rsvo_ros.sim`: synthetic scenes and rolling-shutter renderings with ground truth.
- :mod:`rsvo_ros.ros`: the ROS shells (node, player, recorder, latency probe, bag I/O,
  message conversion): the only place that imports rclpy, rosbags or message packages.
- :mod:`rsvo_ros.tools`: the command-line tools (replay, bench, synthetic bags, comparison).

``rsvo_ros.estimation`` is the stable import path of the two-view API (CONTRACTS.md).
"""

__version__ = "0.1.0"
