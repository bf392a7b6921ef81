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

import os

__version__ = "0.1.0"


def limit_blas_threads() -> None:
    """One OpenBLAS thread for the package's programs (tools, node, probes), unless the
    environment sets ``OPENBLAS_NUM_THREADS``. Every matrix they hand to BLAS or LAPACK is
    small (3 x 3 to 17 x 17, or batches of them), and OpenBLAS's threads spin for a while after
    each call, taking the cores from the solver's own (numba, OpenCV): in ``rsvo_bench`` the
    MVO baseline's left the RS estimate that follows it 1.12x slower (docs/notebook.md, "The
    estimator's speed"). Takes effect only before numpy is first imported: the programs'
    packages call it on import."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
