"""ROS 2 launch file for a full ROS install: `ros2 launch rsvo_ros rsvo.launch.py`.

Starts rsvo_node with its defaults; override with launch arguments, e.g.
`ros2 launch rsvo_ros rsvo.launch.py model:=gs line_delay:=3e-5 image:=/cam/image_raw`.
(launch is not on PyPI; the venv workflow starts `rsvo_node` directly.)
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    args = [
        DeclareLaunchArgument("model", default_value="rs", description="rs | gs | mvo"),
        DeclareLaunchArgument("line_delay", default_value="0.0",
                              description="seconds per image row"),
        DeclareLaunchArgument("image", default_value="/camera/image_raw"),
        DeclareLaunchArgument("camera_info", default_value="/camera/camera_info"),
        DeclareLaunchArgument("image_transport", default_value="raw",
                              description="raw | compressed (image/compressed, JPEG or PNG)"),
    ]
    node = Node(
        package="rsvo_ros",
        executable="rsvo_node",
        name="rsvo_node",
        output="screen",
        parameters=[{
            "model": LaunchConfiguration("model"),
            "line_delay": LaunchConfiguration("line_delay"),
            "image_topic": LaunchConfiguration("image"),
            "camera_info_topic": LaunchConfiguration("camera_info"),
            "image_transport": LaunchConfiguration("image_transport"),
        }],
    )
    return LaunchDescription([*args, node])
