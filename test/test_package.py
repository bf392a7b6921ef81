"""The foundation: package metadata, console scripts, colcon build, and a DDS round trip."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from conftest import REPO_ROOT, colcon_build, ros_domain, ros_test_env

CONSOLE_SCRIPTS = ("rsvo_node", "rsvo_replay", "rsvo_synth", "rsvo_bench", "rsvo_play")


def test_package_xml_declares_what_the_node_needs():
    root = ET.parse(REPO_ROOT / "package.xml").getroot()
    assert root.get("format") == "3"
    assert root.findtext("name") == "rsvo_ros"
    assert root.find("export/build_type").text == "ament_python"
    exec_deps = {e.text for e in root.findall("exec_depend")}
    for dep in ("rclpy", "sensor_msgs", "nav_msgs", "geometry_msgs", "std_msgs",
                "diagnostic_msgs", "python3-numpy", "python3-scipy", "python3-opencv"):
        assert dep in exec_deps, dep
    assert "python3-pytest" in {e.text for e in root.findall("test_depend")}


def test_console_scripts_are_installed():
    bindir = Path(sys.executable).parent
    for name in CONSOLE_SCRIPTS:
        assert (bindir / name).exists() or shutil.which(name), f"{name} is not installed"


def test_colcon_build_installs_a_runnable_rsvo_node(tmp_path):
    """What `ros2 run rsvo_ros rsvo_node` would start: install/rsvo_ros/lib/rsvo_ros/rsvo_node."""
    proc, install = colcon_build(tmp_path)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    node = install / "lib" / "rsvo_ros" / "rsvo_node"
    assert node.is_file() and os.access(node, os.X_OK)
    index = install / "share" / "ament_index" / "resource_index" / "packages"
    assert (index / "rsvo_ros").exists()
    assert (install / "share" / "rsvo_ros" / "package.xml").exists()
    site = next(install.glob("lib/python3*/site-packages"))
    env = dict(os.environ, PYTHONPATH=str(site))
    run = subprocess.run([str(node), "--help"], capture_output=True, text=True, env=env,
                         timeout=60)
    assert run.returncode == 0, run.stderr
    assert "rsvo_node" in run.stdout
    assert "FASTRTPS_DEFAULT_PROFILES_FILE=$(python -m rsvo_ros.ros.dds)" in run.stdout
    # the installed copy is what ran, not the checkout
    where = subprocess.run([sys.executable, "-c", "import rsvo_ros; print(rsvo_ros.__file__)"],
                           capture_output=True, text=True, env=env, cwd=tmp_path)
    assert str(site) in where.stdout
    # the Fast DDS profile for large images: in share/ for ROS users, beside the module for
    # python -m rsvo_ros.ros.dds
    shared = install / "share" / "rsvo_ros" / "config" / "fastdds_large_images.xml"
    assert shared.is_file()
    path = subprocess.run([sys.executable, "-m", "rsvo_ros.ros.dds"], capture_output=True,
                          text=True, env=env, cwd=tmp_path)
    assert path.returncode == 0, path.stderr
    assert path.stdout.strip().startswith(str(site))
    assert Path(path.stdout.strip()).read_bytes() == shared.read_bytes()
    # the parameter file at the defaults, for --params-file
    assert (install / "share" / "rsvo_ros" / "config" / "rsvo_node.yaml").read_text() == \
        (REPO_ROOT / "rsvo_ros" / "ros" / "rsvo_node.yaml").read_text()
    # the launch file and the files it names: the upright parameters and the RViz view
    launch = install / "share" / "rsvo_ros" / "launch" / "rsvo.launch.py"
    named = _launch_constants(launch)
    assert set(named) == {"RVIZ_CONFIG", "UPRIGHT_PARAMS"}
    for key, source in (("RVIZ_CONFIG", "rsvo.rviz"), ("UPRIGHT_PARAMS", "rsvo_upright.yaml")):
        installed = install / "share" / "rsvo_ros" / named[key]
        assert installed.read_bytes() == (REPO_ROOT / "rsvo_ros" / "ros" / source).read_bytes()


def _launch_constants(path: Path) -> dict[str, str]:
    """The launch file's module-level ``NAME = os.path.join(...)`` paths (launch itself is not
    on PyPI: the file is read, not run), and a check that it declares ``upright`` and ``rviz``."""
    import ast

    tree = ast.parse(path.read_text())
    out = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and isinstance(node.value, ast.Call) \
                and ast.unparse(node.value.func) == "os.path.join":  # fmt: skip
            out[node.targets[0].id] = str(Path(*(a.value for a in node.value.args)))
    declared = {c.args[0].value for c in ast.walk(tree) if isinstance(c, ast.Call)
                and ast.unparse(c.func) == "DeclareLaunchArgument"}  # fmt: skip
    assert {"upright", "rviz", "model", "line_delay"} <= declared, declared
    return out


ODOM_EXCHANGE = r"""
import sys, time
import rclpy
from rclpy.executors import SingleThreadedExecutor
from nav_msgs.msg import Odometry

ctx = rclpy.Context()
ctx.init(domain_id=int(sys.argv[1]))
pub_node = rclpy.create_node("smoke_pub", context=ctx)
sub_node = rclpy.create_node("smoke_sub", context=ctx)
got = []
sub_node.create_subscription(Odometry, "/rsvo/odom", got.append, 10)
pub = pub_node.create_publisher(Odometry, "/rsvo/odom", 10)
ex = SingleThreadedExecutor(context=ctx)
ex.add_node(pub_node)
ex.add_node(sub_node)
msg = Odometry()
msg.header.frame_id = "odom"
msg.child_frame_id = "camera_optical_frame"
msg.pose.pose.position.x = 1.5
deadline = time.monotonic() + 20.0
while not got and time.monotonic() < deadline:
    pub.publish(msg)
    ex.spin_once(timeout_sec=0.1)
ex.shutdown()
pub_node.destroy_node()
sub_node.destroy_node()
ctx.try_shutdown()
assert got, "no Odometry received within 20 s"
m = got[0]
assert (m.header.frame_id, m.child_frame_id, m.pose.pose.position.x) == (
    "odom", "camera_optical_frame", 1.5)
print("received", len(got))
"""


@pytest.mark.ros
def test_dds_smoke_two_nodes_exchange_odometry(tmp_path):
    """Two nodes in a private Context and ROS_DOMAIN_ID exchange nav_msgs/Odometry over DDS."""
    domain = ros_domain(3)
    script = tmp_path / "exchange.py"
    script.write_text(ODOM_EXCHANGE)
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, str(script), str(domain)], capture_output=True,
                          text=True, env=ros_test_env(domain), timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "received" in proc.stdout
    assert time.monotonic() - t0 < 120


@pytest.mark.parametrize("workers", [1, 2, 3, 4])
def test_parallel_test_workers_never_share_a_ros_domain(monkeypatch, workers):
    """Each pytest-xdist worker's ROS domains lie in a range of their own inside 10-209."""
    monkeypatch.setenv("PYTEST_XDIST_WORKER_COUNT", str(workers))
    taken: list[set[int]] = []
    for w in range(workers):
        monkeypatch.setenv("PYTEST_XDIST_WORKER", f"gw{w}")
        ids = {ros_domain(offset) for offset in range(250)}
        assert min(ids) >= 10 and max(ids) <= 209
        assert all(not ids & other for other in taken), f"worker {w} of {workers}"
        taken.append(ids)
