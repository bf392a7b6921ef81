"""rsvo_ros: monocular visual odometry for rolling-shutter cameras (Lee & Yoon), ROS 2 Jazzy.

The numerical core (``rsvo_ros.estimation``, ``rsvo_ros.geometry``) is pure numpy/OpenCV and
imports nothing from ROS; the node and command-line tools are thin shells over it.
"""

__version__ = "0.1.0"
