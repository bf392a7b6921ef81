"""ROS 2 launch file for a full ROS install: `ros2 launch rsvo_ros rsvo.launch.py`.

Starts rsvo_node with its defaults; override with launch arguments, e.g.
`ros2 launch rsvo_ros rsvo.launch.py model:=gs line_delay:=3e-5 image:=/cam/image_raw`.
`upright:=true` loads config/rsvo_upright.yaml (odometry for base_link, x forward and z up);
`rviz:=true` starts rviz2 with rviz/rsvo.rviz (the odometry, path, keyframes, local map, /tf
and the tracks image; it expects the upright odom frame). (launch is not on PyPI; the venv
workflow starts `rsvo_node` directly: README, "RViz".)
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition, UnlessCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

RVIZ_CONFIG = os.path.join("rviz", "rsvo.rviz")
UPRIGHT_PARAMS = os.path.join("config", "rsvo_upright.yaml")


def generate_launch_description():
    share = get_package_share_directory("rsvo_ros")
    args = [
        DeclareLaunchArgument("model", default_value="rs", description="rs | gs | mvo"),
        DeclareLaunchArgument("line_delay", default_value="0.0",
                              description="seconds per image row"),
        DeclareLaunchArgument("image", default_value="/camera/image_raw"),
        DeclareLaunchArgument("camera_info", default_value="/camera/camera_info"),
        DeclareLaunchArgument("image_transport", default_value="raw",
                              description="raw | compressed (image/compressed, JPEG or PNG)"),
        DeclareLaunchArgument("upright", default_value="false",
                              description="odometry for base_link (x forward, z up) instead "
                                          "of the camera's optical frame"),
        DeclareLaunchArgument("rviz", default_value="false",
                              description="start rviz2 with the package's view"),
    ]
    given = {
        "model": LaunchConfiguration("model"),
        "line_delay": LaunchConfiguration("line_delay"),
        "image_topic": LaunchConfiguration("image"),
        "camera_info_topic": LaunchConfiguration("camera_info"),
        "image_transport": LaunchConfiguration("image_transport"),
    }
    upright = LaunchConfiguration("upright")
    nodes = [
        Node(package="rsvo_ros", executable="rsvo_node", name="rsvo_node", output="screen",
             parameters=[given], condition=UnlessCondition(upright)),
        Node(package="rsvo_ros", executable="rsvo_node", name="rsvo_node", output="screen",
             parameters=[os.path.join(share, UPRIGHT_PARAMS), given],
             condition=IfCondition(upright)),
        Node(package="rviz2", executable="rviz2", name="rviz2", output="screen",
             arguments=["-d", os.path.join(share, RVIZ_CONFIG)],
             condition=IfCondition(LaunchConfiguration("rviz"))),
    ]
    return LaunchDescription([*args, *nodes])
