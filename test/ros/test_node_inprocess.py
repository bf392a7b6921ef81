"""rsvo_node's features in one process: reset service, debug image, base_link odometry,
the newest-frame policy. (The cross-process DDS graphs are in test_node.py.)"""

from __future__ import annotations

import dataclasses
import threading
import time

import cv2
import numpy as np
import pytest
import rclpy
import yaml
from conftest import ros_domain
from nav_msgs.msg import Odometry, Path
from rcl_interfaces.srv import SetParameters
from rclpy.exceptions import ParameterException
from rclpy.executors import MultiThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_srvs.srv import Trigger

from rsvo_ros.odometry.tracker import DEFAULT_WINDOW_PX, AutoDecimation
from rsvo_ros.ros.node import STARTUP_ERRORS, RsvoNode
from rsvo_ros.ros.params import (
    DEFAULTS_FILE,
    PARAMETERS,
    _yaml_value,
    defaults_yaml,
    params_yaml,
)
from rsvo_ros.sim.synth import SequenceRenderer, SynthConfig

pytestmark = pytest.mark.ros


@pytest.fixture
def ros_context():
    ctx = rclpy.Context()
    ctx.init(domain_id=ros_domain())
    yield ctx
    ctx.try_shutdown()


def _frames(n=6):
    cfg = SynthConfig(frames=n, motion="vehicle", severity=0.5, width=320, height=180)
    r = SequenceRenderer(cfg)
    info = CameraInfo()
    info.k = [float(x) for x in r.K.ravel()]
    info.width, info.height = cfg.width, cfg.height
    msgs = []
    for f in r:
        m = Image()
        m.height, m.width, m.encoding, m.step = 180, 320, "mono8", 320
        m.data = f.image.tobytes()
        ns = round(f.stamp * 1e9)
        m.header.stamp.sec, m.header.stamp.nanosec = ns // 10**9, ns % 10**9
        msgs.append(m)
    return info, msgs


def _stamp(msg) -> int:
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


class Harness:
    def __init__(self, ctx, overrides=None):
        self.node = RsvoNode(context=ctx, parameter_overrides=overrides or [])
        self.client_node = rclpy.create_node("harness", context=ctx)
        self.odom, self.debug = [], []
        self.client_node.create_subscription(Odometry, "/rsvo/odom", self.odom.append, 50)
        self.client_node.create_subscription(Image, "/rsvo/debug_image", self.debug.append,
                                             qos_profile_sensor_data)
        self.ex = MultiThreadedExecutor(context=ctx)
        self.ex.add_node(self.node)
        self.ex.add_node(self.client_node)
        self.thread = threading.Thread(target=self.ex.spin, daemon=True)
        self.thread.start()

    def feed(self, info, msgs, wait=True):
        self.node._on_info(info)
        for m in msgs:
            self.node._on_image(m)
            if wait:
                self._idle()

    def _idle(self, timeout=10.0):
        """Until no frame waits and none is being processed (the pipeline's lock is free),
        checked again after a pause: the worker takes a frame before it takes the lock."""
        t_end = time.monotonic() + timeout

        def busy():
            return (self.node._pending is not None or self.node._wake.is_set()
                    or self.node._pipeline_lock.locked())

        for _ in range(2):
            while time.monotonic() < t_end and busy():
                time.sleep(0.01)
            time.sleep(0.15)

    def close(self):
        self.ex.shutdown()
        self.thread.join(timeout=5.0)  # spin has returned: no handler runs on destroyed nodes
        self.node.destroy_node()
        self.client_node.destroy_node()


def test_reset_service_restarts_at_the_origin_and_debug_image_is_drawn(ros_context):
    h = Harness(ros_context, [Parameter("model", value="gs"),
                              Parameter("image_qos_reliability", value="reliable")])
    try:
        info, msgs = _frames(6)
        t_end = time.monotonic() + 10
        while h.node.pub_debug.get_subscription_count() == 0 and time.monotonic() < t_end:
            time.sleep(0.05)
        h.feed(info, msgs[:4])
        assert len(h.odom) == 4
        moved = h.odom[-1].pose.pose.position
        assert np.linalg.norm([moved.x, moved.y, moved.z]) > 0.1
        cli = h.client_node.create_client(Trigger, "/rsvo/reset")
        assert cli.wait_for_service(timeout_sec=10)
        fut = cli.call_async(Trigger.Request())
        t_end = time.monotonic() + 10
        while not fut.done() and time.monotonic() < t_end:
            time.sleep(0.02)
        assert fut.result().success
        h.feed(info, msgs[4:])
        first_after = h.odom[4].pose.pose
        assert np.allclose([first_after.position.x, first_after.position.y,
                            first_after.position.z], 0.0)
        assert first_after.orientation.w == pytest.approx(1.0)
        # The debug image is best effort (sensor-data QoS), so one may be dropped or late:
        # wait for the stream to settle, then look at every image that came.
        t_end, n_seen = time.monotonic() + 3.0, -1
        while len(h.debug) != n_seen and time.monotonic() < t_end:
            n_seen = len(h.debug)
            time.sleep(0.3)
        assert h.debug, "no debug image"
        origins = {_stamp(msgs[0]), _stamp(msgs[4])}  # no pair: nothing to draw
        greens = {}
        for d in list(h.debug):
            assert (d.encoding, d.width, d.height) == ("bgr8", 320, 180)
            img = np.frombuffer(bytes(d.data), np.uint8).reshape(180, 320, 3)
            greens[_stamp(d)] = int(((img[..., 1] > 150) & (img[..., 0] < 50)
                                     & (img[..., 2] < 50)).sum())
        # every posed frame draws its inlier tracks: the pairwise start, the map's
        # initialisation and the frames tracked against the map alike
        drawn = [g for stamp, g in greens.items() if stamp not in origins]
        assert len(drawn) >= 2 and min(drawn) > 100, greens
    finally:
        h.close()


def test_trajectory_file_holds_every_published_pose_and_marks_a_reset(ros_context, tmp_path):
    """trajectory_file: the odometry as published, one TUM line per message, a comment line
    where the reset service started a new trajectory; what evo and numpy's loadtxt read."""
    path = tmp_path / "live.tum"
    h = Harness(ros_context, [Parameter("model", value="gs"),
                              Parameter("trajectory_file", value=str(path))])
    try:
        info, msgs = _frames(6)
        h.feed(info, msgs[:4])
        h.node._on_reset(Trigger.Request(), Trigger.Response())
        h.feed(info, msgs[4:])
        assert len(h.odom) == 6
    finally:
        h.close()  # closes the file
    lines = path.read_text().splitlines()
    assert len(lines) == 7 and lines[4] == "# new trajectory (reset service)"
    rows = np.loadtxt(path, comments="#")
    for row, odom in zip(rows, h.odom, strict=True):
        p, q = odom.pose.pose.position, odom.pose.pose.orientation
        assert row[0] == pytest.approx(_stamp(odom) * 1e-9, abs=1e-9)
        assert np.allclose(row[1:], [p.x, p.y, p.z, q.x, q.y, q.z, q.w], atol=1e-8)
    assert np.linalg.norm(rows[3, 1:4]) > 0.1 and np.allclose(rows[4, 1:4], 0.0)


def test_a_namespaced_node_keeps_its_topics_and_service_in_its_namespace(ros_context):
    """`rsvo_node --ros-args -r __ns:=/left`: a second camera's odometry beside the first
    (the default topic names are relative; absolute ones ignored the namespace)."""
    node = RsvoNode(context=ros_context, namespace="/left",
                    parameter_overrides=[Parameter("model", value="gs"),
                                         Parameter("image_qos_reliability", value="reliable")])
    try:
        names = {node.pub_odom.topic_name, node.pub_path.topic_name, node.pub_debug.topic_name,
                 node.pub_map.topic_name, node.pub_keyframes.topic_name,
                 node.sub_image.topic_name, node.sub_info.topic_name}
        assert names == {"/left/rsvo/odom", "/left/rsvo/path", "/left/rsvo/debug_image",
                         "/left/rsvo/map_points", "/left/rsvo/keyframes",
                         "/left/camera/image_raw", "/left/camera/camera_info"}
        services = dict(node.get_service_names_and_types_by_node("rsvo_node", "/left"))
        assert "/left/rsvo/reset" in services and "/rsvo/reset" not in services
        assert node.pub_diag.topic_name == "/diagnostics"  # where the aggregator listens
    finally:
        node.destroy_node()


def test_base_frame_odometry_uses_the_fixed_transform(ros_context):
    q = Rotation.from_euler("xyz", [-90, 0, -90], degrees=True).as_quat()  # optical -> base
    h = Harness(ros_context, [Parameter("model", value="gs"),
                              Parameter("base_frame", value="base_link"),
                              Parameter("base_to_camera", value=[0.2, 0.0, 1.0, *q])])
    try:
        info, msgs = _frames(4)
        h.feed(info, msgs)
        assert {o.child_frame_id for o in h.odom} == {"base_link"}
        first = h.odom[0].pose.pose
        assert np.allclose([first.position.x, first.position.y, first.position.z], 0.0,
                           atol=1e-9)  # the base starts at the odom origin
        last = h.odom[-1].pose.pose.position
        # the camera drives forward (optical z) = base x
        assert last.x > 0 and abs(last.x) > abs(last.z)
    finally:
        h.close()


RVIZ_FILE = DEFAULTS_FILE.parent / "rsvo.rviz"
UPRIGHT_FILE = DEFAULTS_FILE.parent / "rsvo_upright.yaml"


def test_the_rviz_view_shows_every_topic_the_node_publishes_as_it_publishes_it(ros_context):
    """rviz/rsvo.rviz: one display per output topic of a node at its defaults (odometry,
    path, keyframes, local map, tracks image), each subscribed with the publisher's
    reliability (a reliable display on a best-effort topic shows nothing), the fixed frame the
    node's odom frame, and /tf shown."""
    view = yaml.safe_load(RVIZ_FILE.read_text())["Visualization Manager"]
    node = RsvoNode(context=ros_context)
    try:
        published = {pub.topic_name: pub.qos_profile.reliability for pub in node.publishers
                     if pub.topic_name not in ("/diagnostics", "/tf", "/tf_static", "/rosout",
                                               "/parameter_events")}  # fmt: skip
        assert view["Global Options"]["Fixed Frame"] == node.p["odom_frame"]
    finally:
        node.destroy_node()
    shown = {d["Topic"]["Value"]: d["Topic"]["Reliability Policy"] for d in view["Displays"]
             if "Topic" in d}  # fmt: skip
    policy = {"Reliable": ReliabilityPolicy.RELIABLE,
              "Best Effort": ReliabilityPolicy.BEST_EFFORT}
    assert {t: policy[r] for t, r in shown.items()} == published
    assert len(published) == 5
    assert "rviz_default_plugins/TF" in {d["Class"] for d in view["Displays"]}


def test_the_upright_parameter_file_gives_z_up_odometry(tmp_path):
    """config/rsvo_upright.yaml: odometry for base_link, x forward and z up (REP 103), as the
    RViz view expects: the camera driving forward along its optical axis moves along x."""
    q = Rotation.from_euler("xyz", [-90, 0, -90], degrees=True).as_quat()  # optical -> base
    ctx = rclpy.Context()
    ctx.init(args=["--ros-args", "--params-file", str(UPRIGHT_FILE)],
             domain_id=ros_domain(3))
    h = Harness(ctx, [Parameter("model", value="gs")])
    try:
        assert h.node.p["base_frame"] == "base_link"
        assert np.allclose(h.node.p["base_to_camera"], [0.0, 0.0, 0.0, *q])
        h.feed(*_frames(4))
        assert {o.child_frame_id for o in h.odom} == {"base_link"}
        last = h.odom[-1].pose.pose.position
        assert last.x > 0 and abs(last.x) > 3 * max(abs(last.y), abs(last.z))
    finally:
        h.close()
        ctx.try_shutdown()


def test_odometry_twist_is_the_base_frames_motion_with_a_measured_covariance(ros_context):
    """The twist of /rsvo/odom: unknown (1e6) for the first pose, then the base frame's
    velocity (lever arm included), which the published base poses' differences agree with."""
    q = Rotation.from_euler("xyz", [-90, 0, -90], degrees=True).as_quat()  # optical -> base
    h = Harness(ros_context, [Parameter("base_frame", value="base_link"),
                              Parameter("base_to_camera", value=[3.0, 2.0, 1.0, *q])])
    try:
        info, msgs = _frames(12)
        h.feed(info, msgs)
        assert len(h.odom) == 12
        covs = [np.reshape(o.twist.covariance, (6, 6)).diagonal() for o in h.odom]
        assert np.allclose(covs[0], 1e6)
        known = [i for i, c in enumerate(covs) if not np.all(c == 1e6)]
        assert len(known) >= 4 and known[0] >= 2
        diag = h.node._diagnostic_values()  # the last message's twist, and the settings
        assert diag["twist"] == ("measured" if known[-1] == 11 else "none")
        assert (diag["readout_direction"], diag["camera_frame"]) == ("down",
                                                                     "camera_optical_frame")

        def pose(o):
            p, r = o.pose.pose.position, o.pose.pose.orientation
            return np.array([p.x, p.y, p.z]), Rotation.from_quat([r.x, r.y, r.z, r.w]).as_matrix()

        for i in known:
            (p0, R0), (p1, R1) = pose(h.odom[i - 1]), pose(h.odom[i])
            dt = (_stamp(h.odom[i]) - _stamp(h.odom[i - 1])) * 1e-9
            tw = h.odom[i].twist.twist
            ang = np.array([tw.angular.x, tw.angular.y, tw.angular.z])
            lin = np.array([tw.linear.x, tw.linear.y, tw.linear.z])
            ang_diff = Rotation.from_matrix(R0.T @ R1).as_rotvec() / dt
            lin_diff = R1.T @ (p1 - p0) / dt
            assert np.allclose(ang, ang_diff, atol=1e-3 + 0.02 * np.linalg.norm(ang_diff))
            assert np.allclose(lin, lin_diff, atol=0.05 * np.linalg.norm(lin_diff))
            assert lin[0] > abs(lin[1]) and lin[0] > abs(lin[2])  # driving forward: base x
    finally:
        h.close()


def test_a_binned_cameras_full_resolution_info_gives_the_same_odometry(ros_context):
    """REP 104: a camera that bins 2 x 2 publishes the full-resolution calibration with
    binning_x/y = 2; its half-size images were refused as 'image size differs from camera
    info'. They now get the intrinsics scaled, and the same odometry as a plain camera info."""
    info, msgs = _frames(6)
    binned = CameraInfo()
    binned.k = [float(x) for x in (np.reshape(info.k, (3, 3)) * [[2], [2], [1]]).ravel()]
    binned.width, binned.height = 2 * info.width, 2 * info.height
    binned.binning_x = binned.binning_y = 2
    poses = []
    for camera_info in (info, binned):
        h = Harness(ros_context, [Parameter("model", value="gs")])
        try:
            h.feed(camera_info, msgs)
            assert h.node.stats["bad"] == 0 and len(h.odom) == 6
            poses.append([(o.pose.pose.position.x, o.pose.pose.position.y,
                           o.pose.pose.position.z) for o in h.odom])
        finally:
            h.close()
    assert np.array_equal(poses[0], poses[1])


def test_the_klt_windows_reach_the_tracker(ros_context):
    """klt_window_px, klt_refine_window_px and tracking_decimation set the pipeline's tracker
    (defaults: 21, the window backend's 11, 1); a 13-px pyramid window at half resolution
    tracks the frames as well."""
    info, msgs = _frames(4)
    for params, want in (([], (DEFAULT_WINDOW_PX, 11, 1)),
                         ([Parameter("klt_window_px", value=13),
                           Parameter("klt_refine_window_px", value=7),
                           Parameter("tracking_decimation", value=2)], (13, 7, 2))):
        h = Harness(ros_context, [Parameter("model", value="gs"), *params])
        try:
            h.feed(info, msgs)
            tracker = h.node.pipeline.tracker
            assert (tracker.options.window_px, tracker.refine_window_px,
                    tracker.options.decimation) == want
            assert h.node.stats["bad"] == 0 and len(h.odom) == 4
        finally:
            h.close()


def test_an_uncalibrated_camera_info_is_refused_or_assumed_as_asked(ros_context):
    """A driver without a calibration file publishes K all zero: refused and counted (the
    odometry never starts) unless uncalibrated_focal_factor is set; then the pinhole of that
    many image widths, the diagnostics saying so, and odometry for every frame."""
    info, msgs = _frames(6)
    info.k = [0.0] * 9
    for factor, expected in ((0.0, 0), (0.78125, 6)):
        h = Harness(ros_context, [Parameter("model", value="gs"),
                                  Parameter("uncalibrated_focal_factor", value=factor)])
        try:
            h.feed(info, msgs, wait=bool(expected))
            assert len(h.odom) == expected
            values = h.node._diagnostic_values()
            if expected:
                assert values["intrinsics"] == "assumed" and h.node.stats["bad"] == 0
                assert h.node._camera[0][0, 0] == 250.0
            else:
                assert values["intrinsics"] == "none yet" and h.node.stats["bad"] >= 1
        finally:
            h.close()


def test_a_fault_that_stays_resets_the_node_after_three_frames(ros_context, monkeypatch):
    """The window backend raises on every frame from the second (a state gone bad): the node
    counts the faults, resets after three in a row (logged, diagnostics fault_resets) and
    posts odometry again from the frame after, where before it never posted again."""
    from rsvo_ros.odometry.window import WindowOdometry

    info, msgs = _frames(6)
    poisoned, track = [], WindowOdometry.track

    def failing(self, stamp_ns, obs, hint=None, memory_from_hint=None):
        if stamp_ns >= _stamp(msgs[1]) and not poisoned and self.K[0, 0] == info.k[0]:
            poisoned.append(self)
        if poisoned and self is poisoned[0]:
            raise RuntimeError("state gone bad")
        return track(self, stamp_ns, obs, hint, memory_from_hint)

    monkeypatch.setattr(WindowOdometry, "track", failing)
    h = Harness(ros_context, [Parameter("model", value="gs")])
    try:
        h.feed(info, msgs)
        assert h.node.stats["fault_resets"] == 1 and h.node.stats["bad"] == 3
        assert len(h.odom) == 3  # the first frame, and the two after the reset
        assert h.node._diagnostic_values()["fault_resets"] == "1"
        first_after = h.odom[1].pose.pose.position
        assert (first_after.x, first_after.y, first_after.z) == (0.0, 0.0, 0.0)  # a new origin
    finally:
        h.close()


@pytest.mark.parametrize("image_frame", ["front_cam_optical", ""])
def test_an_empty_camera_frame_takes_the_images_frame_id(ros_context, image_frame):
    """camera_frame '': the odometry's child frame and base -> camera on /tf_static name the
    frame the camera driver stamps its images with (camera_optical_frame if they have none)."""
    from tf2_msgs.msg import TFMessage

    from rsvo_ros.ros.node import TF_STATIC_QOS

    info, msgs = _frames(3)
    for m in msgs:
        m.header.frame_id = image_frame
    expected = image_frame or "camera_optical_frame"
    h = Harness(ros_context, [Parameter("model", value="gs"), Parameter("camera_frame", value="")])
    try:
        assert h.node.camera_frame == ""  # nothing names it before an image
        h.feed(info, msgs)
        assert {o.child_frame_id for o in h.odom} == {expected}
        assert h.node.camera_frame == expected == h.node._diagnostic_values()["camera_frame"]
    finally:
        h.close()
    h = Harness(ros_context, [Parameter("model", value="gs"), Parameter("camera_frame", value=""),
                              Parameter("base_frame", value="base_link")])
    static = []
    h.client_node.create_subscription(TFMessage, "/tf_static", static.append, TF_STATIC_QOS)
    try:
        time.sleep(0.5)
        assert not static  # base -> camera waits for the image that names the camera
        h.feed(info, msgs)
        t_end = time.monotonic() + 5.0
        while not static and time.monotonic() < t_end:
            time.sleep(0.05)
        (tf,) = static[-1].transforms
        assert (tf.header.frame_id, tf.child_frame_id) == ("base_link", expected)
        assert {o.child_frame_id for o in h.odom} == {"base_link"}
    finally:
        h.close()


def test_path_publish_period_bounds_the_path_messages(ros_context):
    """Every frame has its odometry; the path goes out at most once per period (the first
    frame's here), and holds every pose so far."""
    h = Harness(ros_context, [Parameter("model", value="gs"),
                              Parameter("path_publish_period_s", value=60.0)])
    paths = []
    h.client_node.create_subscription(Path, "/rsvo/path", paths.append, 50)
    try:
        info, msgs = _frames(4)
        h.feed(info, msgs)
        assert len(h.odom) == 4
        assert [len(p.poses) for p in paths] == [1]
    finally:
        h.close()


def _set_parameter(h, name, value):
    """``ros2 param set /rsvo_node NAME VALUE``: the node's SetParameters service."""
    client = h.client_node.create_client(SetParameters, "/rsvo_node/set_parameters")
    assert client.wait_for_service(timeout_sec=10.0)
    future = client.call_async(SetParameters.Request(
        parameters=[Parameter(name, value=value).to_parameter_msg()]))
    t_end = time.monotonic() + 10.0
    while not future.done() and time.monotonic() < t_end:
        time.sleep(0.01)
    h.client_node.destroy_client(client)
    return future.result().results[0]


def test_a_running_node_takes_its_live_parameters_and_refuses_the_others(ros_context):
    """What `ros2 param set` sees: a start-up parameter is refused (it used to be accepted and
    ignored), a live one is checked and taken from the next frame."""
    h = Harness(ros_context, [Parameter("model", value="gs"),
                              Parameter("publish_debug_image", value=False)])
    try:
        assert h.node.describe_parameter("line_delay").read_only
        assert not h.node.describe_parameter("publish_debug_image").read_only
        info, msgs = _frames(6)
        h.feed(info, msgs[:3])
        time.sleep(0.3)
        assert len(h.odom) == 3 and h.debug == []
        refused = _set_parameter(h, "line_delay", 5e-5)
        assert not refused.successful and "read-only" in refused.reason
        assert h.node.get_parameter("line_delay").value == 0.0 and h.node.p["line_delay"] == 0.0
        bad = _set_parameter(h, "lost_odometry", "hold")
        assert not bad.successful and "large_covariance" in bad.reason
        assert h.node.p["lost_odometry"] == "large_covariance"
        out_of_range = _set_parameter(h, "diagnostics_period_s", 0.0)
        assert not out_of_range.successful
        assert _set_parameter(h, "diagnostics_period_s", 0.5).successful
        assert h.node._diag_timer.timer_period_ns == 500_000_000
        # rclpy's own parameter keeps its own rules: use_sim_time can be switched
        assert _set_parameter(h, "use_sim_time", True).successful
        assert _set_parameter(h, "use_sim_time", False).successful
        assert _set_parameter(h, "publish_debug_image", True).successful
        assert h.node.p["publish_debug_image"] is True
        h.feed(info, msgs[3:])
        t_end = time.monotonic() + 5.0
        while not h.debug and time.monotonic() < t_end:
            time.sleep(0.05)
        assert len(h.odom) == 6 and h.debug, "the debug image was not switched on"
    finally:
        h.close()


def test_frames_arriving_while_busy_are_dropped_not_queued(ros_context):
    h = Harness(ros_context, [Parameter("model", value="gs")])
    try:
        info, msgs = _frames(5)
        h.node._on_info(info)
        gate, seen = threading.Event(), []
        original = h.node._process

        def slow(msg, t_recv):  # a busy worker
            seen.append(msg)
            gate.wait(10.0)
            original(msg, t_recv)

        h.node._process = slow
        h.node._on_image(msgs[0])
        t_end = time.monotonic() + 10
        while not seen and time.monotonic() < t_end:
            time.sleep(0.01)
        for m in msgs[1:]:  # the first waits, each later one replaces it
            h.node._on_image(m)
        gate.set()
        h._idle()
        assert h.node.stats["received"] == 5
        assert h.node.stats["dropped"] == 3
        assert seen == [msgs[0], msgs[4]]  # the newest frame, nothing queued
    finally:
        h.close()


def test_a_stall_with_dropped_frames_does_not_skip_the_next_frame(ros_context):
    """The worker busy for 1.5 s of a 30 Hz stream (a DDS burst at start-up, a long frame):
    the frames meanwhile are dropped, and the next one, 1.5 s after the last processed frame,
    is processed, not skipped as "stamp far ahead" and logged as bad input (the pipeline is
    told the dropped frames' newest stamp)."""
    h = Harness(ros_context, [Parameter("model", value="gs")])
    try:
        info, msgs = _frames(2)
        h.feed(info, msgs[:1])
        t0, dt = _stamp(msgs[0]), 33_333_333

        def at(k):  # frame k of the stream (the second image, stamped k intervals on)
            m = Image()
            m.height, m.width, m.encoding, m.step, m.data = 180, 320, "mono8", 320, msgs[1].data
            m.header.stamp.sec, m.header.stamp.nanosec = divmod(t0 + k * dt, 10**9)
            return m

        gate, seen = threading.Event(), []
        original = h.node.pipeline.process

        def slow(stamp, gray):  # the pipeline busy with frame 1
            seen.append(stamp)
            if len(seen) == 1:
                gate.wait(10.0)
            return original(stamp, gray)

        h.node.pipeline.process = slow
        h.node._on_image(at(1))
        t_end = time.monotonic() + 10
        while not seen and time.monotonic() < t_end:
            time.sleep(0.01)
        for k in range(2, 47):  # 1.5 s of frames while frame 1 is processed
            h.node._on_image(at(k))
        gate.set()
        h._idle()
        assert seen == [t0 + dt, t0 + 46 * dt]
        assert h.node.stats["dropped"] == 44 and h.node.stats["processed"] == 3
        assert h.node.stats["bad"] == h.node.stats["skipped"] == 0
        assert [_stamp(o) for o in h.odom][-1] == t0 + 46 * dt
    finally:
        h.close()


def test_the_image_callback_never_waits_for_a_frame_being_processed(ros_context):
    """While the pipeline works on a frame, new images are still taken (and counted): the
    callback used to wait for the processing, and DDS overwrote the images it did not take
    (runs of 10-40 unseen frames at 30 Hz, README)."""
    h = Harness(ros_context, [Parameter("model", value="gs")])
    try:
        info, msgs = _frames(5)
        h.node._on_info(info)  # builds the pipeline
        gate, inside = threading.Event(), threading.Event()
        original = h.node.pipeline.process

        def slow(stamp, gray):  # the pipeline busy with a frame (under its lock)
            inside.set()
            gate.wait(20.0)
            return original(stamp, gray)

        h.node.pipeline.process = slow
        h.node._on_image(msgs[0])
        assert inside.wait(10.0)
        callbacks = threading.Thread(target=lambda: [h.node._on_image(m) for m in msgs[1:]])
        callbacks.start()
        callbacks.join(timeout=5.0)
        done_while_busy = not callbacks.is_alive()
        received_while_busy = h.node.stats["received"]
        gate.set()
        callbacks.join(timeout=20.0)
        h._idle()
        assert done_while_busy and received_while_busy == 5
        assert h.node.stats["dropped"] == 3 and h.node.stats["processed"] == 2
    finally:
        h.close()


def test_looped_input_resets_and_gives_two_trajectories(ros_context):
    """Time going back (a looped bag, a restarted simulator) resets the odometry: the second
    pass is a new trajectory from the origin, counted in the diagnostics."""
    h = Harness(ros_context, [Parameter("model", value="gs")])
    try:
        info, msgs = _frames(5)
        h.feed(info, msgs)
        h.feed(info, msgs)
        assert len(h.odom) == 10
        assert h.node.stats["time_resets"] == 1
        p = [o.pose.pose.position for o in h.odom]
        assert np.allclose([p[5].x, p[5].y, p[5].z], 0.0)
        assert np.allclose([[q.x, q.y, q.z] for q in p[:5]], [[q.x, q.y, q.z] for q in p[5:]])
    finally:
        h.close()


@pytest.mark.parametrize("mode", ["large_covariance", "none"])
def test_lost_tracking_is_visible_to_consumers(ros_context, mode):
    h = Harness(ros_context, [Parameter("model", value="gs"),
                              Parameter("lost_odometry", value=mode)])
    try:
        info, msgs = _frames(6)
        blank = []
        for m in msgs[4:]:  # textureless frames: nothing to track
            b = Image()
            b.height, b.width, b.encoding, b.step = m.height, m.width, m.encoding, m.step
            b.data = bytes(len(m.data))
            b.header = m.header
            blank.append(b)
        h.feed(info, msgs[:4] + blank)
        assert h.node._tracking == "lost" and h.node._state.startswith("lost")
        if mode == "none":
            assert len(h.odom) == 4
        else:
            assert len(h.odom) == 6
            assert max(h.odom[0].pose.covariance) < 1e3
            assert np.allclose(np.diag(np.reshape(h.odom[-1].pose.covariance, (6, 6))), 1e6)
    finally:
        h.close()


def test_line_delay_auto_is_reported_in_the_diagnostics(ros_context):
    h = Harness(ros_context, [Parameter("line_delay_mode", value="auto")])
    try:
        info, msgs = _frames(6)
        h.feed(info, msgs)
        assert len(h.odom) == 6
        diag = h.node._line_delay_diagnostics()
        assert diag["line_delay_status"] == "collecting" and "line_delay_windows" in diag
        assert float(diag["line_delay_used"]) > 0  # a nominal readout until the first estimate
        assert h.node.pipeline.options.line_delay_auto
    finally:
        h.close()


def test_line_delay_rerun_revises_the_path_live_only_on_request(ros_context):
    """line_delay_rerun: with the first estimate the frames so far are processed again with
    it, their new poses go into the path and the count into the diagnostics; without it (the
    default) the node keeps no frames for that and goes on from the estimate."""
    from rsvo_ros.odometry.line_delay import LineDelayEstimate

    # 30 us/row: away from the starting readout (half a frame interval, 93 us/row here)
    est = LineDelayEstimate("estimated", line_delay_s=3e-5, std_s=2e-6, readout_fraction=0.32,
                            std_fraction=0.02, readout_s=5.4e-3, windows=9, frames=60)
    info, msgs = _frames(7)
    for rerun in (True, False):
        h = Harness(ros_context, [Parameter("line_delay_mode", value="auto"),
                                  Parameter("line_delay_rerun", value=rerun),
                                  Parameter("async_mapping", value=False)])
        try:
            h.feed(info, msgs[:6])
            before = [p.pose.position.x for p in h.node._path]
            h.node.pipeline._take_estimate(est, 0)
            h.feed(info, msgs[6:])
            assert h.node.pipeline.line_delay == 3e-5 and len(h.odom) == 7
            after = [p.pose.position.x for p in list(h.node._path)[:6]]
            if rerun:
                assert h.node.stats["frames_revised"] == 6
                assert h.node._diagnostic_values()["frames_revised"] == "6"
                assert [r["frames"] for r in h.node.pipeline.line_delay_reruns] == [6]
                assert after != before  # the path took the new poses
            else:
                assert h.node.pipeline.options.line_delay_rerun_max_frames == 0
                assert h.node.stats["frames_revised"] == 0 and after == before
                assert h.node.pipeline.line_delay_reruns == []
        finally:
            h.close()


def test_line_delay_save_file_is_the_next_start(ros_context, tmp_path):
    """line_delay_mode auto with line_delay_save_file: a converged estimate is written as a
    parameter file (once per value; at shutdown the last estimate), and a node started from
    that file begins from its line delay instead of the nominal readout."""
    import yaml

    from rsvo_ros.odometry.line_delay import LineDelayEstimate

    saved = tmp_path / "line_delay.yaml"
    h = Harness(ros_context, [Parameter("line_delay_mode", value="auto"),
                              Parameter("line_delay_save_file", value=str(saved))])
    try:
        info, msgs = _frames(8)
        h.feed(info, msgs[:4])
        assert not saved.exists()  # collecting: nothing to save
        est = LineDelayEstimate("estimated", line_delay_s=4.2e-5, std_s=2e-6,
                                readout_fraction=0.45, std_fraction=0.02, readout_s=7.6e-3,
                                windows=9, frames=60)
        h.node.pipeline._take_estimate(est, 0)
        h.feed(info, msgs[4:5])
        assert not saved.exists()  # estimated, not converged: only at shutdown
        h.node.pipeline._take_estimate(dataclasses.replace(est, status="converged",
                                                           line_delay_s=4.5e-5), 0)
        h.feed(info, msgs[5:6])
        params = yaml.safe_load(saved.read_text())["rsvo_node"]["ros__parameters"]
        assert params == {"line_delay": 4.5e-5, "line_delay_mode": "auto"}
        saved.write_text("not written again")
        h.feed(info, msgs[6:7])
        assert saved.read_text() == "not written again"  # the same value: once
        h.node.pipeline._take_estimate(dataclasses.replace(est, line_delay_s=4.7e-5), 0)
        h.feed(info, msgs[7:8])
        assert saved.read_text() == "not written again"  # a new estimate, not converged
    finally:
        h.close()
    params = yaml.safe_load(saved.read_text())["rsvo_node"]["ros__parameters"]
    assert params["line_delay"] == 4.7e-5  # at shutdown: the last estimate
    h = Harness(ros_context, [Parameter(k, value=v) for k, v in params.items()])
    try:
        h.feed(info, msgs[:3])
        assert h.node.pipeline.options.line_delay_auto
        assert h.node.pipeline.line_delay == 4.7e-5  # the start, until its own first estimate
    finally:
        h.close()


def test_line_delay_refinement_is_reported_and_saved(ros_context, tmp_path):
    """line_delay_refine_frames reaches the pipeline; images the node drops while busy are
    kept for it (its second pass sees the camera's frames); a refined estimate is used, shown
    in the diagnostics beside the first one, and written to line_delay_save_file at once; 0:
    off."""
    import time

    import yaml

    from rsvo_ros.odometry.line_delay import LineDelayEstimate, RefinedLineDelay

    saved = tmp_path / "line_delay.yaml"
    h = Harness(ros_context, [Parameter("line_delay_mode", value="auto"),
                              Parameter("line_delay_refine_frames", value=40),
                              Parameter("line_delay_save_file", value=str(saved))])
    try:
        info, msgs = _frames(6)
        h.feed(info, msgs[:2])
        pipe = h.node.pipeline
        assert pipe.options.line_delay_auto_refine_frames == 40
        assert pipe._refine_frames is not None and len(pipe._refine_frames) == 2
        # the worker busy with frame 2 (held at the pipeline's lock): 3 is dropped for 4
        with h.node._pipeline_lock:
            h.node._on_image(msgs[2])
            t_end = time.monotonic() + 10.0
            while h.node._pending is not None and time.monotonic() < t_end:
                time.sleep(0.01)  # the worker has taken frame 2
            h.node._on_image(msgs[3])
            h.node._on_image(msgs[4])
        h._idle()
        assert h.node.stats["dropped"] == 1 and h.node.stats["dropped_kept"] == 1
        assert h.node.stats["processed"] == 4
        assert [st for st, _ in pipe._refine_frames] == [_stamp(m) for m in msgs[:5]]
        assert pipe._refine_unprocessed == 1
        est = LineDelayEstimate("estimated", 4.2e-5, 2e-6, 0.45, 0.02, 7.6e-3, 9, 60)
        pipe._take_estimate(est, 0)
        pipe._take_refined(RefinedLineDelay("refined", 5e-5, 3e-6, 12, 60, "12 blocks"),
                           est, est, time.perf_counter(), 0)  # fmt: skip
        h.feed(info, msgs[5:6])
        diag = h.node._line_delay_diagnostics()
        assert diag["line_delay_status"] == diag["line_delay_refinement"] == "refined"
        assert diag["line_delay_first_estimate"] == "4.2e-05"
        assert diag["line_delay_estimate"] == diag["line_delay_used"] == "5e-05"
        params = yaml.safe_load(saved.read_text())["rsvo_node"]["ros__parameters"]
        assert params["line_delay"] == 5e-5  # refined: written at once
        assert "(refined)" in saved.read_text()
    finally:
        h.close()
    h = Harness(ros_context, [Parameter("line_delay_mode", value="auto"),
                              Parameter("line_delay_refine_frames", value=0)])
    try:
        h.feed(info, msgs[:2])
        assert h.node.pipeline._refine_frames is None  # nothing kept
        assert "line_delay_refinement" not in h.node._line_delay_diagnostics()
    finally:
        h.close()


def test_compressed_image_transport_subscribes_to_the_compressed_topic(ros_context):
    """image_transport compressed: sensor_msgs/CompressedImage (PNG) published on
    /camera/image_raw/compressed reaches the node over DDS and gives the raw images'
    odometry; an undecodable one is counted as bad, and nothing on the raw topic is read."""
    info, msgs = _frames(4)
    inline = [Parameter("model", value="gs"), Parameter("async_mapping", value=False),
              Parameter("image_qos_reliability", value="reliable")]
    reference = Harness(ros_context, inline)
    try:
        reference.feed(info, msgs)
        expected = {(o.header.stamp.sec, o.header.stamp.nanosec): o.pose.pose.position
                    for o in reference.odom}
    finally:
        reference.close()
    assert len(expected) == 4
    compressed = []
    for m in msgs:
        img = np.frombuffer(bytes(m.data), np.uint8).reshape(m.height, m.width)
        ok, buf = cv2.imencode(".png", img)
        assert ok
        c = CompressedImage()
        c.header, c.format, c.data = m.header, "mono8; png compressed mono8", buf.tobytes()
        compressed.append(c)
    h = Harness(ros_context, [*inline, Parameter("image_transport", value="compressed")])
    try:
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        pub = h.client_node.create_publisher(CompressedImage, "/camera/image_raw/compressed", qos)
        raw_pub = h.client_node.create_publisher(Image, "/camera/image_raw", qos)
        t_end = time.monotonic() + 10
        while pub.get_subscription_count() == 0 and time.monotonic() < t_end:
            time.sleep(0.05)
        assert pub.get_subscription_count() == 1
        assert raw_pub.get_subscription_count() == 0
        h.node._on_info(info)
        for k, c in enumerate(compressed):
            pub.publish(c)
            t_end = time.monotonic() + 10
            while h.node.stats["received"] < k + 1 and time.monotonic() < t_end:
                time.sleep(0.01)
            h._idle()
        bad = CompressedImage()
        bad.header, bad.format, bad.data = msgs[-1].header, "png", b"not an image"
        pub.publish(bad)
        t_end = time.monotonic() + 10
        while h.node.stats["bad"] == 0 and time.monotonic() < t_end:
            time.sleep(0.01)
        assert h.node.stats["bad"] == 1 and h.node.stats["received"] == 5
        assert len(h.odom) == 4
        for o in h.odom:
            a, b = o.pose.pose.position, expected[(o.header.stamp.sec, o.header.stamp.nanosec)]
            assert np.allclose([a.x, a.y, a.z], [b.x, b.y, b.z], atol=1e-9)
        assert np.linalg.norm([a.x, a.y, a.z]) > 0.1  # it moved
    finally:
        h.close()


def test_a_camera_file_stands_in_for_camera_info(ros_context, tmp_path):
    """camera_file (a ROS camera calibration YAML): the camera info topic is not subscribed
    and images alone give odometry; a bad file stops the node at start-up naming it."""
    info, msgs = _frames(4)
    K = np.array(info.k).reshape(3, 3)
    calib = tmp_path / "camera.yaml"
    calib.write_text(f"image_width: {info.width}\nimage_height: {info.height}\n"
                     f"camera_matrix:\n  rows: 3\n  cols: 3\n  data: {K.ravel().tolist()}\n"
                     "distortion_model: plumb_bob\ndistortion_coefficients:\n  rows: 1\n"
                     "  cols: 5\n  data: [0, 0, 0, 0, 0]\n")
    h = Harness(ros_context, [Parameter("model", value="gs"),
                              Parameter("camera_file", value=f"file://{calib}")])
    try:
        assert h.node.sub_info is None
        for m in msgs:  # no camera info at all
            h.node._on_image(m)
            h._idle()
        assert len(h.odom) == 4 and h.node.stats["bad"] == 0
        last = h.odom[-1].pose.pose.position
        assert np.linalg.norm([last.x, last.y, last.z]) > 0.1
    finally:
        h.close()
    with pytest.raises(ValueError, match="parameter camera_file: .*neither a ROS camera"):
        (tmp_path / "bad.yaml").write_text("foo: 1\n")
        RsvoNode(context=ros_context,
                 parameter_overrides=[Parameter("camera_file", value=str(tmp_path / "bad.yaml"))])


def test_rectified_images_use_the_projection_and_no_lens(ros_context):
    """image_rectified: CameraInfo's P is the camera and its D is not applied (image_rect)."""
    info, msgs = _frames(3)
    info.d = [-0.3, 0.1, 0.0, 0.0, 0.0]
    info.distortion_model = "plumb_bob"
    info.p = [*info.k[:3], 0.0, *info.k[3:6], 0.0, *info.k[6:], 0.0]
    info.k = [1.2 * x for x in info.k[:8]] + [1.0]  # the raw camera's: not used
    h = Harness(ros_context, [Parameter("model", value="gs"),
                              Parameter("image_rectified", value=True)])
    try:
        h.feed(info, msgs)
        assert len(h.odom) == 3
        assert h.node.pipeline.D is None
        assert np.array_equal(h.node.pipeline.K, np.array(info.p).reshape(3, 4)[:, :3])
    finally:
        h.close()


def _p(text: str) -> Parameter:
    """``name:=value`` as ``--ros-args -p`` would type it."""
    name, value = text.split(":=")
    return Parameter(name, value=yaml.safe_load(value))


def test_every_invalid_parameter_is_refused_by_name(tmp_path):
    """What rsvo_node exits 2 on at start-up (test_node.py runs three of them as processes):
    the node refuses each with an exception that names the parameter."""
    cases = ((["model:=fisheye"], "model"),
             (["max_features:=3"], "max_features"),
             (["klt_refine_window_px:=2"], "klt_refine_window_px"),
             (["klt_window_px:=3"], "klt_window_px"),
             (["klt_window_px:=99"], "klt_window_px"),
             (["tracking_decimation:=0"], "tracking_decimation"),
             (["tracking_decimation:=5"], "tracking_decimation"),
             (["uncertain_rotation_deg:=-0.5"], "uncertain_rotation_deg"),
             (["stall_frames:=0.5"], "parameter stall_frames must be 0 (off) or more than 1"),
             (["line_delay:=-1.0"], "line_delay"),
             (["base_to_camera:=[0.0, 0.0]"], "base_to_camera"),
             (["line_delay_mode:=auto", "model:=gs"], "line_delay_mode"),
             (["lost_odometry:=zero"], "lost_odometry"),
             (["line_delay_save_file:=/tmp/x.yaml"], "line_delay_save_file"),
             (["line_delay_rerun:=true"], "line_delay_rerun needs"),
             (["line_delay_mode:=auto", f"line_delay_save_file:={tmp_path}/no/such/x.yaml"],
              "does not exist"),
             ([f"trajectory_file:={tmp_path}/no/such/live.tum"], "trajectory_file"),
             (["odom_topic:=rsvo odom"], "odom_topic: 'rsvo odom' is not a"),
             (["path_topic:=/rsvo//path"], "repeated '/'"))
    for args, word in cases:
        ctx = rclpy.Context()
        ctx.init(domain_id=ros_domain(11))
        try:
            with pytest.raises(STARTUP_ERRORS) as err:
                RsvoNode(context=ctx, parameter_overrides=[_p(a) for a in args])
            assert word in str(err.value), (args, str(err.value))
        finally:
            ctx.try_shutdown()


class _Log:
    """The node's logger, keeping what it is told (the worker thread warns too: the images
    come without a camera info)."""

    def __init__(self):
        self.infos = []
        self.others = []

    def info(self, text):
        self.infos.append(text)

    def warning(self, text):
        self.others.append(text)

    def error(self, text):
        self.others.append(text)


@pytest.mark.parametrize("width,height,age_ms,hinted", [(1280, 720, 20.0, True),
                                                        (640, 480, 20.0, False),
                                                        (1280, 720, 2.0, False)])
def test_late_large_images_get_one_hint_at_the_dds_profile(ros_context, monkeypatch, width,
                                                           height, age_ms, hinted):
    """Images over Fast DDS's default 512 KB shared-memory segment that arrive late: one log
    line naming the shipped profile; small or prompt images: none. The age is in the
    diagnostics either way."""
    h = Harness(ros_context, [Parameter("model", value="gs")])
    log = _Log()
    monkeypatch.setattr(h.node, "get_logger", lambda: log)
    try:
        for _ in range(40):  # no camera info: the images only pass the callback
            m = Image()
            m.height, m.width, m.encoding, m.step = height, width, "mono8", width
            m.data = bytes(width * height)
            ns = h.node.get_clock().now().nanoseconds - round(age_ms * 1e6)
            m.header.stamp.sec, m.header.stamp.nanosec = ns // 10**9, ns % 10**9
            h.node._on_image(m)
        for _ in range(2):
            h.node._publish_diagnostics()
        hints = [t for t in log.infos if "FASTRTPS_DEFAULT_PROFILES_FILE" in t]
        assert len(hints) == (1 if hinted else 0), log.infos
        if hinted:
            assert "900 KB" in hints[0] and "python -m rsvo_ros.ros.dds" in hints[0]
        assert age_ms <= np.median(h.node._image_delay_ms) < age_ms + 50.0
    finally:
        h.close()


@pytest.mark.parametrize("width,height,decimation,hinted", [(1280, 720, 1, True),
                                                            (640, 480, 1, False),
                                                            (1280, 720, 2, False)])
def test_a_node_that_drops_large_images_gets_one_hint_at_decimation(ros_context, monkeypatch,
                                                                    width, height,
                                                                    decimation, hinted):
    """Large images that the node drops (more than 5 % of 150 or more): one log line naming
    tracking_decimation; small images, or tracking already decimated: none."""
    h = Harness(ros_context, [Parameter("model", value="gs"),
                              Parameter("tracking_decimation", value=decimation)])
    log = _Log()
    monkeypatch.setattr(h.node, "get_logger", lambda: log)
    try:
        m = Image()
        m.height, m.width, m.encoding, m.step = height, width, "mono8", width
        m.data = bytes(width * height)
        for _ in range(200):  # no camera info: the images only pass the callback
            h.node._on_image(m)
        h.node.stats["dropped"] = max(h.node.stats["dropped"], 20)  # however fast the worker
        for _ in range(2):
            h.node._publish_diagnostics()
        hints = [t for t in log.infos if "tracking_decimation:=2" in t]
        assert len(hints) == (1 if hinted else 0), log.infos
        if hinted:
            assert f"{width}x{height}" in hints[0] and "of 200 images" in hints[0]
    finally:
        h.close()


@pytest.mark.parametrize("mode", ["fixed", "auto"])
def test_tracking_decimation_mode_auto_steps_down_when_images_drop(ros_context, monkeypatch,
                                                                    mode):
    """tracking_decimation_mode auto: once a span of images had too many dropped, the node
    tracks at half the resolution from the next frame on, without losing the odometry (every
    frame posed), logs it, counts it and reports the decimation in use in /diagnostics; fixed
    (the default): the same drops change nothing. (The governor's span and its minimum image
    side scaled down to this test's 320x180 frames and 8 images.)"""
    info, msgs = _frames(8)
    h = Harness(ros_context, [Parameter("model", value="gs"),
                              Parameter("tracking_decimation_mode", value=mode)])
    log = _Log()
    monkeypatch.setattr(h.node, "get_logger", lambda: log)
    try:
        if mode == "auto":
            assert isinstance(h.node._auto_decimation, AutoDecimation)
            h.node._auto_decimation = AutoDecimation(settle=0, span=3, min_side_px=150)
        else:
            assert h.node._auto_decimation is None
        h.feed(info, msgs[:3])
        h.node.stats["dropped"] += 2  # as if 2 of the next 3 images had come too soon
        h.feed(info, msgs[3:])
        stepped = mode == "auto"
        assert h.node.pipeline.tracker.options.decimation == (2 if stepped else 1)
        assert h.node.stats["decimation_steps"] == int(stepped)
        assert len(h.odom) == 8 and h.node.stats["bad"] == 0 and h.node.stats["held"] == 0
        values = h.node._diagnostic_values()
        assert values["tracking_decimation"] == ("2" if stepped else "1")
        assert values["tracking_decimation_mode"] == mode
        steps = [t for t in log.infos if t.startswith("tracking_decimation_mode auto")]
        assert len(steps) == int(stepped), log.infos
        if stepped:
            assert "tracking at 1/2 of the resolution" in steps[0]
    finally:
        h.close()


def _node_with_params_file(path, domain_offset):
    """An rsvo_node started as `rsvo_node --ros-args --params-file path` would start."""
    ctx = rclpy.Context()
    ctx.init(args=["--ros-args", "--params-file", str(path)],
             domain_id=ros_domain(domain_offset))
    return ctx, RsvoNode(context=ctx)


def test_the_shipped_parameter_file_is_every_default_and_loads(tmp_path):
    """rsvo_ros/ros/rsvo_node.yaml (share/rsvo_ros/config/ once installed) is what
    `python -m rsvo_ros.ros.params` writes: every parameter at its default, typed so that the
    node takes it; an edited copy changes what it says."""
    assert DEFAULTS_FILE.read_text() == defaults_yaml(), \
        "regenerate it: python -m rsvo_ros.ros.params --output rsvo_ros/ros/rsvo_node.yaml"
    ctx, node = _node_with_params_file(DEFAULTS_FILE, 1)
    try:
        for name, (default, _) in PARAMETERS.items():
            value = node.get_parameter(name).value
            assert value == default and type(value) is type(default), (name, value)
    finally:
        node.destroy_node()
        ctx.try_shutdown()
    edited = DEFAULTS_FILE.read_text().replace("model: 'rs'", "model: 'gs'") \
        .replace("line_delay: 0.0", "line_delay: 5.0e-05") \
        .replace("max_features: 500", "max_features: 300")
    (tmp_path / "mine.yaml").write_text(edited)
    ctx, node = _node_with_params_file(tmp_path / "mine.yaml", 2)
    try:
        assert node.p["model"] == "gs" and node.p["max_features"] == 300
        assert node.p["line_delay"] == pytest.approx(5e-5)
    finally:
        node.destroy_node()
        ctx.try_shutdown()


def test_a_line_delay_file_of_a_global_shutter_loads(tmp_path):
    """rsvo_calibrate's file for an estimate of exactly 0 (a global shutter) is a float
    parameter the node takes (written as "0" it was an integer, which the node refuses)."""
    estimate = {"status": "converged", "windows": 6, "frames": 150, "line_delay_s": 0.0,
                "std_s": 1e-7, "readout_s": 0.0, "readout_fraction": 0.0,
                "std_fraction": 0.002}  # fmt: skip
    path = tmp_path / "calib.yaml"
    path.write_text(params_yaml(estimate, "test"))
    ctx, node = _node_with_params_file(path, 3)
    try:
        assert node.p["line_delay"] == 0.0 and node.p["line_delay_mode"] == "fixed"
    finally:
        node.destroy_node()
        ctx.try_shutdown()


def test_a_line_delay_file_of_a_turned_camera_sets_its_readout_direction(tmp_path):
    """An estimate made with columns read (rsvo_calibrate --readout-direction right) is per
    column: its file sets the direction too, and the node's pipeline takes it."""
    estimate = {"status": "converged", "windows": 16, "frames": 150, "line_delay_s": 3e-5,
                "std_s": 1e-6, "readout_s": 0.0192, "readout_fraction": 0.576,
                "std_fraction": 0.02}  # fmt: skip
    path = tmp_path / "calib.yaml"
    path.write_text(params_yaml(estimate, "test", readout_direction="right"))
    assert "readout_direction" not in params_yaml(estimate, "test")  # the default: not written
    ctx, node = _node_with_params_file(path, 4)
    try:
        assert node.p["readout_direction"] == "right" and node.p["line_delay"] == 3e-5
        info, msgs = _frames(2)
        node._on_info(info)
        assert node.pipeline.options.readout == "right"
    finally:
        node.destroy_node()
        ctx.try_shutdown()
    with pytest.raises(ValueError, match="readout must be one of"):
        params_yaml(estimate, "test", readout_direction="sideways")


@pytest.mark.parametrize("value,text", [(0.0, "0.0"), (5e-05, "5.0e-05"), (1e20, "1.0e+20"),
                                        (2.5, "2.5"), (3, "3"), (True, "true"),
                                        ("it's", "'it''s'"), ([0.0, 1.0], "[0.0, 1.0]")])
def test_parameter_file_values_keep_their_type(value, text):
    assert _yaml_value(value) == text
    assert yaml.safe_load(f"x: {text}")["x"] == value


def test_an_integer_for_a_double_parameter_is_taken_as_that_double(ros_context):
    """`rsvo_node --ros-args -p mapping_lag_s:=0 -p line_delay:=0` and `ros2 param set
    /rsvo_node diagnostics_period_s 2`: ROS parses those values as integers, which rclpy
    refused for a double parameter ("expecting type 'DOUBLE'") and the node did not start.
    They are the doubles 0.0 / 2.0 now, still within their ranges; a string stays refused."""
    ctx = rclpy.Context()
    ctx.init(args=["--ros-args", "-p", "mapping_lag_s:=0", "-p", "line_delay:=0",
                   "-p", "path_publish_period_s:=1"], domain_id=ros_domain(5))
    try:
        node = RsvoNode(context=ctx)
        try:
            for name, value in (("mapping_lag_s", 0.0), ("line_delay", 0.0),
                                ("path_publish_period_s", 1.0)):
                got = node.get_parameter(name).value
                assert got == value and isinstance(got, float), (name, got)
            assert node.p["mapping_lag_s"] == 0.0
        finally:
            node.destroy_node()
        ctx2 = rclpy.Context()
        ctx2.init(args=["--ros-args", "-p", "mapping_lag_s:=3"], domain_id=ros_domain(6))
        try:
            with pytest.raises(ParameterException, match="mapping_lag_s"):
                RsvoNode(context=ctx2)  # 3.0 s: out of its range [0, 2]
        finally:
            ctx2.try_shutdown()
    finally:
        ctx.try_shutdown()
    h = Harness(ros_context, [Parameter("model", value="gs")])
    try:
        assert _set_parameter(h, "diagnostics_period_s", 2).successful
        assert h.node.get_parameter("diagnostics_period_s").value == 2.0
        assert h.node._diag_timer.timer_period_ns == 2_000_000_000
        assert not _set_parameter(h, "diagnostics_period_s", "2").successful
    finally:
        h.close()
