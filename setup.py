"""Build script of rsvo_ros (ament_python: colcon-buildable and pip-installable)."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE_NAME = "rsvo_ros"

setup(
    name=PACKAGE_NAME,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    package_data={"rsvo_ros.ros": ["fastdds_large_images.xml", "rsvo_node.yaml",
                                   "rsvo_upright.yaml", "rsvo.rviz"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE_NAME}"]),
        (f"share/{PACKAGE_NAME}", ["package.xml"]),
        (f"share/{PACKAGE_NAME}/launch", glob("launch_scripts/*.launch.py")),
        (f"share/{PACKAGE_NAME}/config", ["rsvo_ros/ros/fastdds_large_images.xml",
                                          "rsvo_ros/ros/rsvo_node.yaml",
                                          "rsvo_ros/ros/rsvo_upright.yaml"]),
        (f"share/{PACKAGE_NAME}/rviz", ["rsvo_ros/ros/rsvo.rviz"]),
    ],
    install_requires=["setuptools"],
    extras_require={"test": ["pytest", "pytest-timeout", "pytest-xdist", "ruff"]},
    zip_safe=True,
    maintainer="rsvo_ros developers",
    maintainer_email="rsvo@example.com",
    description="Monocular visual odometry for rolling-shutter cameras (ROS 2 Jazzy).",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "rsvo_node = rsvo_ros.ros.node:main",
            "rsvo_replay = rsvo_ros.tools.replay:main",
            "rsvo_synth = rsvo_ros.tools.synth_bag:main",
            "rsvo_bench = rsvo_ros.tools.bench:main",
            "rsvo_play = rsvo_ros.ros.play:main",
            "rsvo_calibrate = rsvo_ros.tools.calibrate:main",
        ],
    },
)
