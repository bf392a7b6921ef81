"""rsvo_node: the live ROS 2 node (rclpy). A thin shell over :class:`OdometryPipeline`.

Wiring only: it subscribes to images and camera info, hands the newest image to the pipeline on
a worker thread (frames that arrive while it is busy are dropped and counted, never queued),
and publishes ``nav_msgs/Odometry``, a bounded ``nav_msgs/Path``, a debug image and
diagnostics. Parameters live in :mod:`rsvo_ros.ros.params`, message conversion in
:mod:`rsvo_ros.ros.convert`.
"""

from __future__ import annotations

import os
import sys
import threading
import time
import traceback
from collections import deque
from pathlib import Path as FilePath

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, TransformStamped
from nav_msgs.msg import Odometry, Path
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import JumpThreshold
from rclpy.duration import Duration
from rclpy.exceptions import InvalidParameterTypeException, ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2, PointField
from std_srvs.srv import Trigger

from rsvo_ros.core.geometry import pose_inverse
from rsvo_ros.odometry.pairwise import uncertain_rotation_or_auto
from rsvo_ros.odometry.pipeline import (
    FAULT_RESET_AFTER,
    FrameResult,
    OdometryPipeline,
    PipelineOptions,
    warm_up,
)
from rsvo_ros.odometry.tracker import AutoDecimation, TrackerOptions, refine_window_or_auto
from rsvo_ros.odometry.twist import twist_in_frame
from rsvo_ros.ros.convert import (
    COVARIANCE_UNKNOWN,
    POINT_FIELD_FLOAT32,
    XYZ_FIELDS,
    XYZ_POINT_STEP,
    camera_from_info,
    covariance_for_msg,
    fill_pose,
    fill_transform,
    fill_twist,
    image_to_gray,
    stamp_ns,
    tum_line,
    xyz_cloud_data,
)
from rsvo_ros.ros.dds import DEFAULT_SHM_SEGMENT_BYTES
from rsvo_ros.ros.draw import draw_tracks
from rsvo_ros.ros.params import (
    PARAMETERS,
    check_live_change,
    help_text,
    image_subscription,
    integer_as_double,
    params_yaml,
    read_config,
)

try:  # not on PyPI: a ROS install provides it, else launch_scripts/setup.sh builds it
    from tf2_msgs.msg import TFMessage
except ImportError:  # pragma: no cover - depends on the install
    TFMessage = None

QOS_WAIT_S = 10.0  # auto QoS: wait this long for a publisher, then subscribe best effort
DEFAULT_CAMERA_FRAME = "camera_optical_frame"  # camera_frame '' and images without a frame_id
# images larger than Fast DDS's default shared-memory segment that arrive this late (median of
# 30 or more, ms) get a one-time hint at the shipped profile: 12-15 ms against 2-4 ms with it
# for 1280x720 mono8 here (README, "Large images over DDS"); under a second, as a later median
# is a stamp from another clock (a bag's), not a transport
LARGE_IMAGE_HINT_MS = (8.0, 1000.0)
# a node tracking at full resolution that has dropped more than this share of the images
# (after DROP_HINT_MIN_FRAMES), with images at least DROP_HINT_MIN_WIDTH wide, gets a one-time
# hint at tracking_decimation (README, "Tracking at a reduced resolution")
DROP_HINT_SHARE = 0.05
DROP_HINT_MIN_FRAMES = 150
DROP_HINT_MIN_WIDTH = 960
# what tf2_ros's broadcasters use: /tf keeps 100, /tf_static is latched for late subscribers
# relative: in the node's namespace, as the topics (/rsvo/reset in the root namespace)
RESET_SERVICE = "rsvo/reset"
# shutdown: how long a line-delay refinement still running may take to finish (then stopped)
NODE_REFINE_WAIT_S = 2.0
# images dropped between two processed frames kept for the line-delay refinement (at most)
DROPPED_KEPT_MAX = 30
TF_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
TF_STATIC_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)


class RsvoNode(Node):
    """The ROS shell: parameters, QoS, message conversion, publishing."""

    def __init__(self, **kwargs):
        super().__init__("rsvo_node", **kwargs)
        # -p NAME:=0 for a double parameter: taken as 0.0 (rclpy's overrides, which
        # declare_parameter reads; where rclpy keeps them elsewhere, its own refusal stands)
        overrides = getattr(self, "_parameter_overrides", None)
        if isinstance(overrides, dict):
            for name in PARAMETERS:
                if name in overrides:
                    overrides[name] = integer_as_double(overrides[name])
        self.add_pre_set_parameters_callback(
            lambda params: [integer_as_double(p) for p in params])  # ros2 param set NAME 0
        for name, (default, desc) in PARAMETERS.items():
            self.declare_parameter(name, default, desc)
        self.p = read_config({name: self.get_parameter(name).value for name in PARAMETERS})
        self.T_base_cam = self.p.T_base_cam
        self.T_cam_base = pose_inverse(self.T_base_cam)
        # before anything is advertised: the first run after an install compiles the solver
        self.get_logger().info("loading the solver kernels (the first run after an install "
                               "compiles them: about a minute)")
        self.get_logger().info(f"solver ready in {warm_up():.1f} s")
        # _lock: the hand-over between the image callback and the worker (held for
        # microseconds); _pipeline_lock: the pipeline (held while a frame is processed). The
        # image callback never waits for a frame's processing: while it did, a slow frame kept
        # the callbacks from taking new images and DDS overwrote them unseen (runs of 10-40
        # frames at 30 Hz, README)
        self._lock = threading.Lock()
        self._pipeline_lock = threading.Lock()
        self._pending: tuple | None = None
        self._waiting: tuple | None = None  # the newest image that came before camera info
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._camera: tuple | None = None
        self.pipeline: OdometryPipeline | None = None
        self.stats = {"received": 0, "processed": 0, "dropped": 0, "bad": 0, "skipped": 0,
                      "held": 0, "time_resets": 0, "map_refound": 0,
                      "brightness_compensated": 0, "tracked_from_shift": 0,
                      "fault_resets": 0,
                      "frames_revised": 0, "dropped_kept": 0,
                      "decimation_steps": 0}  # fmt: skip
        # dropped images the line-delay refinement keeps for its second pass (converted on
        # the worker, before the next frame it processes; the callback only queues them)
        self._dropped: deque = deque(maxlen=DROPPED_KEPT_MAX)
        # the newest image dropped since the last processed one: its stamp is the stream's
        # clock for the next frame's time checks (OdometryPipeline.note_dropped)
        self._dropped_stamp: int | None = None
        self._bad_kinds: set[str] = set()
        self._faults = 0  # processing errors in a row (FAULT_RESET_AFTER)
        self._recv_times: deque = deque(maxlen=100)
        # how old each image is when it arrives (the node's clock minus its stamp): the camera
        # driver's and the transport's share of the delay
        self._image_delay_ms: deque = deque(maxlen=100)
        self._image_bytes = 0
        self._large_image_hinted = False
        self._image_size: tuple[int, int] | None = None  # (width, height) of raw images
        self._decimation_hinted = False
        # tracking_decimation_mode auto: steps the tracking resolution down when images drop
        self._auto_decimation = AutoDecimation(int(self.p["tracking_decimation"])) \
            if self.p["tracking_decimation_mode"] == "auto" else None  # fmt: skip
        self._busy_s = 0.0  # time spent processing frames since the start (s)
        self._proc_ms: deque = deque(maxlen=100)
        self._track_ms: deque = deque(maxlen=100)  # per frame, without the window BA
        self._map_ms: deque = deque(maxlen=100)  # per keyframe: the window BA
        self._publish_ms: deque = deque(maxlen=100)  # messages filled and published
        self._last_inlier_ratio = 0.0
        self._line_delay_saved: tuple | None = None  # (status, value) last written
        self._refinement_logged: dict | None = None  # the line-delay refinement last logged
        self._state = "waiting for camera info"
        self._tracking = "initialising"
        self._path: deque = deque(maxlen=int(self.p["path_max_length"]))
        self._trajectory = TrajectoryFile(self.p["trajectory_file"], self.get_logger())
        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.pub_odom = self.create_publisher(Odometry, self.p["odom_topic"], reliable)
        self.pub_path = self.create_publisher(Path, self.p["path_topic"], reliable)
        self.pub_debug = self.create_publisher(Image, self.p["debug_image_topic"],
                                               qos_profile_sensor_data)  # fmt: skip
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.pub_map = self.create_publisher(PointCloud2, self.p["map_points_topic"], reliable)
        self.pub_keyframes = self.create_publisher(Path, self.p["keyframe_path_topic"], reliable)
        self._last_map_publish = -np.inf
        self._last_path_publish = -np.inf
        self.pub_tf = self.pub_tf_static = None
        self._image_frame = ""  # camera_frame '': the first image's frame_id
        self._twist_known = False  # the last odometry message carried a measured twist
        if self.p["publish_tf"]:
            if TFMessage is None:
                self.get_logger().error("tf2_msgs is not installed: /tf is not published (run "
                                        "launch_scripts/setup.sh, which builds it)")
            else:
                self.pub_tf = self.create_publisher(TFMessage, "/tf", TF_QOS)
                if self.p["base_frame"]:
                    self.pub_tf_static = self.create_publisher(TFMessage, "/tf_static",
                                                               TF_STATIC_QOS)  # fmt: skip
                    if self.camera_frame:  # else with the first image, which names it
                        self._publish_static_tf()
        self.create_service(Trigger, RESET_SERVICE, self._on_reset)
        # ROS time going back (a /clock restart under use_sim_time) resets the odometry; image
        # stamps that go back are caught by the pipeline itself
        self._clock_jump = self.get_clock().create_jump_callback(
            JumpThreshold(min_forward=None, min_backward=Duration(seconds=-0.5),
                          on_clock_change=True), post_callback=self._on_clock_jump)
        self.sub_info = None
        self._intrinsics = "none yet" if self.p.camera is None else "camera_file"
        if self.p.camera is None:
            self.sub_info = self.create_subscription(CameraInfo, self.p["camera_info_topic"],
                                                     self._on_info, qos_profile_sensor_data)
        else:  # intrinsics from the calibration file: no camera info topic
            cam = self.p.camera
            self._camera = (cam.K, cam.lens, cam.width, cam.height)
            with self._pipeline_lock:
                self._ensure_pipeline()
            self.get_logger().info(f"camera intrinsics from {self.p['camera_file']} "
                                   f"({cam.width}x{cam.height}, f = {cam.K[0, 0]:.1f} px); "
                                   f"{self.p['camera_info_topic']} is not subscribed")
        self.sub_image = None
        self._qos_deadline = time.monotonic() + QOS_WAIT_S
        if self.p["image_qos_reliability"] == "auto":
            self._qos_timer = self.create_timer(0.2, self._try_subscribe_images)
        else:
            self._subscribe_images(self.p["image_qos_reliability"] == "reliable")
        self._diag_timer = self.create_timer(float(self.p["diagnostics_period_s"]),
                                             self._publish_diagnostics)
        # ros2 param set: the live parameters are checked, then taken from the next frame
        self.add_on_set_parameters_callback(self._check_parameter_change)
        self.add_post_set_parameters_callback(self._apply_parameter_change)
        self._worker = threading.Thread(target=self._work, name="rsvo_worker", daemon=True)
        self._worker.start()

    # ------------------------------------------------------------------ set-up

    def _try_subscribe_images(self) -> None:
        infos = self.get_publishers_info_by_topic(image_subscription(self.p)[0])
        if infos:
            reliable = all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in infos)
        elif time.monotonic() < self._qos_deadline:
            return
        else:
            reliable = False  # best effort connects to both kinds of publisher
        self._qos_timer.cancel()
        self._subscribe_images(reliable)

    def _subscribe_images(self, reliable: bool) -> None:
        qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE if reliable
                         else ReliabilityPolicy.BEST_EFFORT)  # fmt: skip
        topic, kind = image_subscription(self.p)
        msg_type = CompressedImage if kind == "compressed" else Image
        self.sub_image = self.create_subscription(msg_type, topic, self._on_image, qos)
        self.get_logger().info(f"subscribed to {topic} ({msg_type.__name__}, "
                               f"{'reliable' if reliable else 'best effort'})")

    def _check_parameter_change(self, params: list) -> SetParametersResult:
        for param in params:
            if param.name not in PARAMETERS:
                continue  # rclpy's own (use_sim_time): its own rules
            reason = check_live_change(param.name, param.value)
            if reason:
                return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)

    def _apply_parameter_change(self, params: list) -> None:
        for param in params:
            if param.name not in PARAMETERS:
                continue
            old = self.p.values[param.name]
            self.p.values[param.name] = param.value
            if param.name == "diagnostics_period_s":
                self._diag_timer.cancel()
                self.destroy_timer(self._diag_timer)
                self._diag_timer = self.create_timer(float(param.value),
                                                     self._publish_diagnostics)
            self.get_logger().info(f"parameter {param.name}: {old!r} -> {param.value!r}")

    # ------------------------------------------------------------------ callbacks

    def _on_info(self, msg: CameraInfo) -> None:
        try:
            cam = camera_from_info(msg, bool(self.p["image_rectified"]),
                                   float(self.p["uncalibrated_focal_factor"]))
        except ValueError as exc:
            self._bad(str(exc))
            return
        if cam.assumed and self._camera is None:
            self.get_logger().warning(
                f"camera info is uncalibrated (all zero): assuming a pinhole camera of focal "
                f"length {cam.K[0, 0]:.1f} px (uncalibrated_focal_factor "
                f"{self.p['uncalibrated_focal_factor']:g} x {cam.width} px), principal point at "
                f"the centre, no lens distortion; calibrate the camera for accurate odometry")
        self._intrinsics = "assumed" if cam.assumed else "camera info"
        if cam.binning_y > 1 and self._camera is None:
            self.get_logger().info(
                f"camera info: binning {cam.binning_y} rows, images {cam.width}x{cam.height} "
                f"(intrinsics scaled as REP 104 says); line_delay is per image row, "
                f"{cam.binning_y} x the sensor's row time")
        self._camera = (cam.K, cam.lens, cam.width, cam.height)
        if self.pipeline is None:  # build it now, not on the first image (keeps that one fast)
            with self._pipeline_lock:
                self._ensure_pipeline()
            with self._lock:
                if self._waiting is not None and self._pending is None:
                    self._pending, self._waiting = self._waiting, None
                    self._wake.set()

    def _on_image(self, msg: Image) -> None:
        self._recv_times.append(time.monotonic())
        self._image_delay_ms.append(
            (self.get_clock().now().nanoseconds - stamp_ns(msg.header)) * 1e-6)
        self._image_bytes = len(msg.data)
        if getattr(msg, "width", 0):  # (a CompressedImage has no size)
            self._image_size = (int(msg.width), int(msg.height))
        with self._lock:
            self.stats["received"] += 1
            if self._pending is not None:
                self.stats["dropped"] += 1  # the worker is busy: keep only the newest
                self._dropped_stamp = stamp_ns(self._pending[0].header)
                pipeline = self.pipeline
                if pipeline is not None and pipeline.wants_unprocessed_frames:
                    self._dropped.append(self._pending[0])  # for the refinement's second pass
            self._pending = (msg, time.monotonic())
        self._wake.set()

    def _restart_odometry(self, reason: str) -> None:
        """The pipeline forgets everything (call with _pipeline_lock held): the next frame
        starts a new trajectory at the identity; the path restarts and the trajectory file
        says why."""
        if self.pipeline is not None:
            self.pipeline.reset()
        self._path.clear()
        self._trajectory.new_trajectory(reason)

    def _on_clock_jump(self, jump) -> None:
        with self._pipeline_lock:
            self._restart_odometry("ROS time jumped back")
            self.stats["time_resets"] += 1
        self.get_logger().warning("ROS time jumped back (a /clock restart?): odometry reset, "
                                  "the next frame starts a new trajectory")

    def _on_reset(self, request, response):
        with self._pipeline_lock:
            self._restart_odometry("reset service")
        response.success = True
        response.message = "odometry reset: the next frame is the new origin"
        self.get_logger().info(response.message)
        return response

    def _ensure_pipeline(self) -> None:
        """Create the pipeline once the camera is known (call with _pipeline_lock held)."""
        if self.pipeline is not None or self._camera is None:
            return
        K, D, _, _ = self._camera
        opts = PipelineOptions(model=self.p["model"], backend=self.p["backend"],
                               readout=self.p["readout_direction"],
                               tracker=TrackerOptions(
                                   max_features=int(self.p["max_features"]),
                                   window_px=int(self.p["klt_window_px"]),
                                   decimation=int(self.p["tracking_decimation"]),
                                   refine_window_px=refine_window_or_auto(
                                       int(self.p["klt_refine_window_px"]),
                                       "parameter klt_refine_window_px"),
                                   photometric_compensation=bool(
                                       self.p["photometric_compensation"]),
                                   shift_retry=bool(self.p["klt_shift_retry"])),
                               motion_prior=bool(self.p["motion_prior"]))
        opts.ransac.threshold_px = float(self.p["ransac_threshold_px"])
        opts.lm.max_iterations = int(self.p["lm_max_iterations"])
        opts.rotation_only_parallax_px = float(self.p["rotation_only_parallax_px"])
        opts.uncertain_rotation_deg = uncertain_rotation_or_auto(
            float(self.p["uncertain_rotation_deg"]), "parameter uncertain_rotation_deg")
        opts.window.async_mapping = bool(self.p["async_mapping"])
        opts.window.mapping_lag_s = float(self.p["mapping_lag_s"])
        opts.window.stall_intervals = float(self.p["stall_frames"])
        if not self.p["refind_map"]:
            opts.window.reloc_min_inliers = 0
        opts.window.map.prior_acc_rad_s2 = float(self.p["angular_acceleration_std"])
        opts.window.keyframe_log_max = int(self.p["path_max_length"])  # flat memory
        opts.line_delay_auto = self.p["line_delay_mode"] == "auto"
        # live, the frames before the first estimate are processed again with it (the replay's
        # default) only on request: that takes a second or two in one frame, and the frames
        # the camera sends meanwhile are dropped
        if not self.p["line_delay_rerun"]:
            opts.line_delay_rerun_max_frames = 0
        opts.line_delay_auto_refine_frames = int(self.p["line_delay_refine_frames"])
        self.pipeline = OdometryPipeline(K, D, float(self.p["line_delay"]), opts)

    def _bad(self, kind: str) -> None:
        self.stats["bad"] += 1
        if kind not in self._bad_kinds:
            self._bad_kinds.add(kind)
            self.get_logger().warning(f"skipping bad input: {kind} (logged once per kind)")

    # ------------------------------------------------------------------ processing

    def _work(self) -> None:
        while not self._stop.is_set():
            if not self._wake.wait(timeout=0.2):
                continue
            with self._lock:
                item, self._pending = self._pending, None
                self._wake.clear()
            if item is None:
                continue
            try:
                self._process(*item)
                self._faults = 0
            except Exception as exc:  # noqa: BLE001 - the node must keep going
                kind = f"processing error: {type(exc).__name__}: {exc}"
                if not any(k.startswith("processing error") for k in self._bad_kinds):
                    self.get_logger().error(traceback.format_exc())
                self._bad(kind)
                self._faults += 1
                if self._faults >= FAULT_RESET_AFTER:
                    self._fault_reset(kind)

    def _fault_reset(self, kind: str) -> None:
        """FAULT_RESET_AFTER processing errors in a row: the pipeline's state may be what
        fails; start again from the next frame rather than skip every frame from now on."""
        self._faults = 0
        with self._pipeline_lock:
            self._restart_odometry("processing errors")
            self.stats["fault_resets"] += 1
        self.get_logger().error(f"{FAULT_RESET_AFTER} frames in a row failed ({kind}): "
                                f"odometry reset, the next frame starts a new trajectory")

    def _process(self, msg: Image, t_recv: float) -> None:
        self._take_image_frame(msg)
        if self._camera is None:
            # keep the newest image until the camera info arrives (drivers and bags often send
            # an image just before its camera info); an older waiting one cannot be used
            with self._lock:
                if self._waiting is not None:
                    self._bad(f"no camera info on {self.p['camera_info_topic']} yet")
                self._waiting = (msg, t_recv)
            return
        self._keep_dropped()
        try:
            gray = image_to_gray(msg)
        except ValueError as exc:
            self._bad(str(exc).split(" (")[0])
            return
        K, D, w, h = self._camera
        if w and h and (gray.shape[1], gray.shape[0]) != (w, h):
            self._bad("image size differs from camera info")
            return
        t0 = time.perf_counter()
        with self._pipeline_lock:
            self._ensure_pipeline()
            self.pipeline.set_camera(K, D, float(self.p["line_delay"]))
            res = self.pipeline.process(stamp_ns(msg.header), gray)
            self._busy_s += time.perf_counter() - t0
            self._step_decimation()
        self._proc_ms.append((time.perf_counter() - t0) * 1e3)
        self._save_line_delay()
        self._log_refinement()
        # tracking: the frame's time without an inline window BA (an async one ran beside it)
        self._track_ms.append(res.time_ms - res.mapping_ms)
        ba_ms = max(res.mapping_ms, res.background_mapping_ms)  # inline or background
        if ba_ms > 0:
            self._map_ms.append(ba_ms)
        self.stats["processed"] += 1
        if res.time_reset:
            self.stats["time_resets"] += 1
            self._path.clear()
            self._trajectory.new_trajectory("image stamps went back")
            self.get_logger().warning(f"image stamps: {res.reason.split(' (')[0]}")
        if res.status == "skipped":
            self.stats["skipped"] += 1
            self._bad(res.reason.split(" (")[0])
            return
        if res.status == "held":
            self.stats["held"] += 1
        if res.refound:
            self.stats["map_refound"] += 1
        if res.revised:
            self._take_revised(res.revised)
        if res.brightness_change is not None:
            self.stats["brightness_compensated"] += 1
        if res.image_shift is not None:
            self.stats["tracked_from_shift"] += 1
        self._state = {"initialising": f"initialising: {res.reason}", "tracking": "tracking",
                       "lost": f"lost: {res.reason}"}[res.tracking]  # fmt: skip
        self._tracking = res.tracking
        self._last_inlier_ratio = res.inlier_ratio
        t_pub = time.perf_counter()
        self._publish(msg, res, gray)
        self._publish_ms.append((time.perf_counter() - t_pub) * 1e3)

    def _step_decimation(self) -> None:
        """tracking_decimation_mode auto: track at a lower resolution from the next image on
        when too many images were dropped or the node had no headroom
        (:class:`AutoDecimation`; call with _pipeline_lock held)."""
        if self._auto_decimation is None:
            return
        with self._lock:
            received, dropped = self.stats["received"], self.stats["dropped"]
        step = self._auto_decimation.update(received, dropped, self._busy_s, time.monotonic(),
                                            self.pipeline.image_size)
        if step is None:
            return
        self.pipeline.tracker.set_decimation(step.factor)
        self.stats["decimation_steps"] += 1
        self.get_logger().info(f"tracking_decimation_mode auto: {step.describe()}")

    def _keep_dropped(self) -> None:
        """The images dropped since the last processed frame: the newest one's stamp to the
        pipeline's clock (a stall's drops do not make the next frame look far ahead), and the
        images to the line-delay refinement (``line_delay_refine_frames``): its second pass
        then runs over the camera's frames, not only those the node kept up with, as a replay
        of the recording does."""
        with self._lock:
            newest, self._dropped_stamp = self._dropped_stamp, None
            dropped = list(self._dropped)
            self._dropped.clear()
        if newest is not None:
            with self._pipeline_lock:
                if self.pipeline is not None:
                    self.pipeline.note_dropped(newest)
        for msg in dropped:
            try:
                gray = image_to_gray(msg)
            except ValueError:
                continue  # not kept; it stays counted as dropped (it was never processed)
            with self._pipeline_lock:
                if self.pipeline is not None \
                        and self.pipeline.keep_unprocessed(stamp_ns(msg.header), gray):
                    self.stats["dropped_kept"] += 1

    def _take_revised(self, revised: list[FrameResult]) -> None:
        """line_delay_rerun: the frames before the first line-delay estimate, processed again
        with it; the path gets their new poses (the published odometry stays as it was)."""
        poses = {r.stamp_ns: r.T_world_cam for r in revised if r.T_world_cam is not None}
        for ps in self._path:
            T = poses.get(stamp_ns(ps.header))
            if T is not None:
                fill_pose(ps.pose, self._to_odom(T))
        self.stats["frames_revised"] += len(revised)
        info = (self.pipeline.line_delay_reruns or [{}])[-1]
        self.get_logger().info(
            f"line delay auto: the {len(revised)} frames so far processed again with the "
            f"estimate, {info.get('line_delay_s', 0.0) * 1e6:.2f} us/row, in "
            f"{info.get('time_ms', 0.0) / 1e3:.1f} s; the path has their new poses")

    @property
    def camera_frame(self) -> str:
        """The camera's frame id: the parameter, or (parameter '') the first image's frame_id;
        '' until that image arrives."""
        return self.p["camera_frame"] or self._image_frame

    def _take_image_frame(self, msg: Image) -> None:
        """camera_frame '': the first image names the camera's frame."""
        if self.p["camera_frame"] or self._image_frame:
            return
        frame = msg.header.frame_id.strip()
        if not frame:
            frame = DEFAULT_CAMERA_FRAME
            self.get_logger().warning(f"camera_frame '' and the images have no frame_id: "
                                      f"using {frame}")
        self._image_frame = frame
        self.get_logger().info(f"camera frame from the images: {frame}")
        if self.pub_tf_static is not None:
            self._publish_static_tf()

    def _publish_static_tf(self) -> None:
        tf = TransformStamped()
        tf.header.stamp = self.get_clock().now().to_msg()
        tf.header.frame_id = self.p["base_frame"]
        tf.child_frame_id = self.camera_frame
        fill_transform(tf.transform, self.T_base_cam)
        self.pub_tf_static.publish(TFMessage(transforms=[tf]))

    def _to_odom(self, T_world_cam: np.ndarray) -> np.ndarray:
        """The published pose: the camera's, or the base's through ``base_to_camera`` (the odom
        frame is where the base starts)."""
        if not self.p["base_frame"]:
            return T_world_cam
        return self.T_base_cam @ T_world_cam @ self.T_cam_base

    def _publish(self, msg: Image, res: FrameResult, gray: np.ndarray) -> None:
        lost = res.tracking == "lost"
        if lost and self.p["lost_odometry"] == "none":
            return
        T = self._to_odom(res.T_world_cam)
        child = self.p["base_frame"] or self.camera_frame
        odom = Odometry()
        odom.header.stamp = msg.header.stamp
        odom.header.frame_id = self.p["odom_frame"]
        odom.child_frame_id = child
        fill_pose(odom.pose.pose, T)
        cov = np.eye(6) * COVARIANCE_UNKNOWN if lost else res.covariance
        odom.pose.covariance = [float(x) for x in covariance_for_msg(cov)]
        twist = res.twist  # the camera's since the last pose; unknown (1e6) where there is none
        if self.p["base_frame"]:
            twist = twist_in_frame(twist, self.T_base_cam)
        fill_twist(odom.twist.twist, twist.linear, twist.angular)
        self._twist_known = twist.known and not lost
        odom.twist.covariance = [float(x) for x in covariance_for_msg(twist.covariance)]
        self.pub_odom.publish(odom)
        self._trajectory.write(res.stamp_ns, T)
        if self.pub_tf is not None:
            tf = TransformStamped()
            tf.header = odom.header
            tf.child_frame_id = child
            fill_transform(tf.transform, T)
            self.pub_tf.publish(TFMessage(transforms=[tf]))
        ps = PoseStamped()
        ps.header = odom.header
        ps.pose = odom.pose.pose
        self._path.append(ps)
        now = time.monotonic()
        if now - self._last_path_publish >= float(self.p["path_publish_period_s"]):
            self._last_path_publish = now
            path = Path()
            path.header = odom.header
            path.poses = list(self._path)
            self.pub_path.publish(path)
        if self.p["publish_debug_image"] and self.pub_debug.get_subscription_count() > 0:
            self.pub_debug.publish(_debug_image(msg, gray, res))
        if now - self._last_map_publish >= float(self.p["map_publish_period_s"]):
            self._last_map_publish = now
            self._publish_map(odom.header)

    def _publish_map(self, header) -> None:
        """The local map's points and the corrected keyframe path (window backend)."""
        pipeline = self.pipeline
        X = pipeline.map_points()
        if self.p["base_frame"]:
            X = X @ self.T_base_cam[:3, :3].T + self.T_base_cam[:3, 3]
        cloud = PointCloud2()
        cloud.header = header
        data = xyz_cloud_data(X)
        cloud.height, cloud.width = 1, len(data) // XYZ_POINT_STEP
        cloud.fields = [PointField(name=n, offset=o, datatype=POINT_FIELD_FLOAT32, count=1)
                        for n, o in XYZ_FIELDS]  # fmt: skip
        cloud.is_bigendian = False
        cloud.point_step = XYZ_POINT_STEP
        cloud.row_step = len(data)
        cloud.data = data
        cloud.is_dense = True
        self.pub_map.publish(cloud)
        path = Path()
        path.header = header
        for stamp, T in pipeline.keyframe_poses(int(self.p["path_max_length"])):
            ps = PoseStamped()
            ps.header.frame_id = header.frame_id
            ps.header.stamp.sec, ps.header.stamp.nanosec = divmod(int(stamp), 1_000_000_000)
            fill_pose(ps.pose, self._to_odom(T))
            path.poses.append(ps)
        self.pub_keyframes.publish(path)

    def _publish_diagnostics(self) -> None:
        st = DiagnosticStatus()
        st.name = "rsvo_node: odometry"
        st.hardware_id = self.camera_frame
        bad_recent = self.stats["bad"] > 0
        st.level = DiagnosticStatus.OK if not bad_recent and self._tracking != "lost" \
            else DiagnosticStatus.WARN
        st.message = self._state
        st.values = [KeyValue(key=k, value=v) for k, v in self._diagnostic_values().items()]
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [st]
        self.pub_diag.publish(arr)
        self._hint_large_images()
        self._hint_decimation()

    def _diagnostic_values(self) -> dict[str, str]:
        """The key-value pairs of /diagnostics."""
        now = time.monotonic()
        times = [t for t in self._recv_times if now - t < 5.0]
        rate = (len(times) - 1) / (times[-1] - times[0]) if len(times) > 1 else 0.0
        return {
            "input_rate_hz": f"{rate:.2f}",
            **{f"{name}_time_ms_{q_name}": f"{np.percentile(ms, q):.1f}" if ms else "n/a"
               for name, ms in (("processing", self._proc_ms), ("tracking", self._track_ms),
                                ("mapping", self._map_ms), ("publishing", self._publish_ms))
               for q_name, q in (("median", 50), ("p95", 95))},
            **{f"image_delay_ms_{name}": f"{np.percentile(self._image_delay_ms, q):.1f}"
               if self._image_delay_ms else "n/a" for name, q in (("median", 50), ("p95", 95))},
            "inlier_ratio": f"{self._last_inlier_ratio:.3f}",
            "tracking_state": self._tracking,
            **{k: str(v) for k, v in self.stats.items()},
            "model": self.p["model"], "line_delay": str(self.p["line_delay"]),
            "readout_direction": self.p["readout_direction"],
            # the decimation in use (auto mode: it may have stepped up from the parameter's)
            "tracking_decimation": str(self._tracking_decimation()),
            "tracking_decimation_mode": self.p["tracking_decimation_mode"],
            # the camera's frame id in use ('' : not named yet, camera_frame '' waits for an
            # image); whether the last odometry carried a twist (measured) or none (1e6)
            "camera_frame": self.camera_frame,
            "twist": "measured" if self._twist_known else "none",
            # where K comes from: camera info, camera_file, assumed (uncalibrated) or none yet
            "intrinsics": self._intrinsics,
            **self._line_delay_diagnostics(),
        }  # fmt: skip

    def _hint_large_images(self) -> None:
        """Once: images too large for Fast DDS's default shared-memory segment arrive late."""
        if self._large_image_hinted or len(self._image_delay_ms) < 30 \
                or self._image_bytes <= DEFAULT_SHM_SEGMENT_BYTES \
                or os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp") != "rmw_fastrtps_cpp":
            return
        delay = float(np.median(self._image_delay_ms))
        if not LARGE_IMAGE_HINT_MS[0] < delay < LARGE_IMAGE_HINT_MS[1]:
            return
        self._large_image_hinted = True
        self.get_logger().info(
            f"images of {self._image_bytes // 1024} KB arrive {delay:.0f} ms after their stamp "
            f"(median): larger than Fast DDS's default shared-memory segment "
            f"({DEFAULT_SHM_SEGMENT_BYTES // 1024} KB), they leave its fast path. In the "
            f"camera driver's environment: export FASTRTPS_DEFAULT_PROFILES_FILE=$(python -m "
            f"rsvo_ros.ros.dds) (README, 'Large images over DDS')")

    def _tracking_decimation(self) -> int:
        pipeline = self.pipeline
        return pipeline.tracker.options.decimation if pipeline is not None \
            else int(self.p["tracking_decimation"])  # fmt: skip

    def _hint_decimation(self) -> None:
        """Once: a node tracking large images at full resolution drops many of them."""
        received, dropped = self.stats["received"], self.stats["dropped"]
        if self._decimation_hinted or self.p["tracking_decimation"] != 1 \
                or self._auto_decimation is not None \
                or received < DROP_HINT_MIN_FRAMES or dropped <= DROP_HINT_SHARE * received:
            return
        pipeline = self.pipeline
        size = self._image_size or (pipeline.image_size if pipeline is not None else None)
        if size is None or max(size) < DROP_HINT_MIN_WIDTH:
            return
        self._decimation_hinted = True
        self.get_logger().info(
            f"dropped {dropped} of {received} images ({100.0 * dropped / received:.0f} %): this "
            f"machine does not keep up with {size[0]}x{size[1]} images at their rate. "
            f"tracking_decimation:=2 tracks at half the resolution, at 1280x720 in about 0.6x "
            f"the time; tracking_decimation_mode:=auto does so by itself when images drop "
            f"(README, 'Tracking at a reduced resolution')")

    def _line_delay_diagnostics(self) -> dict[str, str]:
        pipeline = self.pipeline
        if pipeline is None:
            return {}
        e = pipeline.line_delay_estimate
        out = {"line_delay_used": f"{pipeline.line_delay:.6g}", "line_delay_status": e.status}
        if e.line_delay_s is not None:
            out["line_delay_estimate"] = f"{e.line_delay_s:.6g}"
            out["line_delay_std"] = f"{e.std_s:.3g}"
            out["readout_fraction"] = f"{e.readout_fraction:.3f}"
        elif e.reason:
            out["line_delay_reason"] = e.reason
        if pipeline.calibrator is not None:
            out["line_delay_windows"] = str(len(pipeline.calibrator.windows))
        ref = pipeline.line_delay_auto_refinement
        if ref is not None:  # line_delay_refine_frames: the second pass's outcome
            out["line_delay_refinement"] = ref["status"]
            if ref.get("first_line_delay_s") is not None:
                out["line_delay_first_estimate"] = f"{ref['first_line_delay_s']:.6g}"
            if ref["status"] != "refined":
                out["line_delay_refinement_reason"] = ref["reason"]
        return out

    def _log_refinement(self) -> None:
        """line_delay_refine_frames: one log line when the second pass is done."""
        ref = self.pipeline.line_delay_auto_refinement if self.pipeline is not None else None
        if ref is None or ref is self._refinement_logged:
            return
        self._refinement_logged = ref
        if ref["status"] == "refined":
            self.get_logger().info(
                f"line delay auto: refined to {ref['line_delay_s'] * 1e6:.2f} +- "
                f"{ref['std_s'] * 1e6:.2f} us/row from {ref['first_line_delay_s'] * 1e6:.2f} in a "
                f"second pass over {ref['frames']} tracked frames "
                f"({ref['time_ms'] / 1e3:.1f} s in a background process)")
        else:
            self.get_logger().warning(f"line delay auto: the estimate is kept, not refined: "
                                      f"{ref['reason']}")

    def _save_line_delay(self, final: bool = False) -> None:
        """``line_delay_save_file``: a converged or refined estimate (or, at shutdown, the
        last one) as a parameter file the next start loads, written once per value
        (atomically)."""
        path = self.p["line_delay_save_file"]
        e = self.pipeline.line_delay_estimate if self.pipeline is not None else None
        if not path or e is None or e.line_delay_s is None \
                or e.status not in (("estimated", "converged", "refined") if final
                                    else ("converged", "refined")):
            return
        if self._line_delay_saved == (e.status, e.line_delay_s):
            return
        target = FilePath(path).expanduser()
        text = params_yaml(e.as_dict(), f"rsvo_node line_delay_mode auto ({e.status})",
                           mode="auto", node_name=self.get_name(),
                           readout_direction=self.p["readout_direction"])
        try:
            tmp = target.with_name(target.name + ".tmp")
            tmp.write_text(text)
            tmp.replace(target)
        except OSError as exc:
            self.get_logger().error(f"line_delay_save_file: cannot write {target}: {exc}")
            self._line_delay_saved = (e.status, e.line_delay_s)  # said once per value
            return
        self._line_delay_saved = (e.status, e.line_delay_s)
        self.get_logger().info(f"line delay {e.line_delay_s:.6g} s/row ({e.status}) written to "
                               f"{target}; start with --params-file {target} to begin from it")

    def destroy_node(self):
        self._stop.set()
        self._wake.set()
        self._worker.join(timeout=5.0)
        if self.pipeline is not None:
            # a line-delay refinement still running: a moment to finish, else stopped (a
            # shutdown must not wait for it; the estimate then saved is the unrefined one)
            self.pipeline.close(refine_wait_s=NODE_REFINE_WAIT_S)
            self._log_refinement()
            self._save_line_delay(final=True)
        self._trajectory.close()
        return super().destroy_node()


class TrajectoryFile:
    """``trajectory_file``: the published poses as TUM lines. A file that cannot be written is
    one error in the log, and the node goes on without it."""

    FLUSH_PERIOD_S = 1.0

    def __init__(self, path: str, logger):
        self.path, self._logger = path, logger
        self._file = None
        self._lines = 0  # since the last "new trajectory"
        self._last_flush = time.monotonic()
        self._lock = threading.Lock()  # the worker writes, a service or a clock jump marks
        if path:
            try:
                self._file = open(FilePath(path).expanduser(), "w")  # noqa: SIM115
                logger.info(f"writing the published poses to {path} (TUM)")
            except OSError as exc:
                logger.error(f"trajectory_file: cannot write {path}: {exc}")

    def write(self, stamp_ns: int, T: np.ndarray) -> None:
        with self._lock:
            if self._file is None:
                return
            try:
                self._file.write(tum_line(stamp_ns, T) + "\n")
                self._lines += 1
                now = time.monotonic()
                if now - self._last_flush >= self.FLUSH_PERIOD_S:
                    self._file.flush()
                    self._last_flush = now
            except OSError as exc:
                self._logger.error(f"trajectory_file: cannot write {self.path}: {exc}; "
                                   "no more poses are written to it")
                self._close()

    def new_trajectory(self, reason: str) -> None:
        with self._lock:
            if self._file is not None and self._lines:
                try:
                    self._file.write(f"# new trajectory ({reason})\n")
                except OSError:
                    pass  # the next write says so
                self._lines = 0

    def close(self) -> None:
        with self._lock:
            self._close()

    def _close(self) -> None:
        if self._file is not None:
            try:
                self._file.close()
            except OSError as exc:
                self._logger.error(f"trajectory_file: cannot write {self.path}: {exc}")
            self._file = None


def _debug_image(msg: Image, gray: np.ndarray, res: FrameResult) -> Image:
    """The frame's tracks (:func:`rsvo_ros.ros.draw.draw_tracks`) as a bgr8 Image."""
    img = draw_tracks(gray, res)
    out = Image()
    out.header = msg.header
    out.height, out.width = img.shape[:2]
    out.encoding = "bgr8"
    out.step = img.shape[1] * 3
    out.data = img.tobytes()
    return out


# what a bad parameter raises while the node starts (main: exit code 2, named on stderr)
STARTUP_ERRORS = (ValueError, ParameterException, InvalidParameterTypeException)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv if argv is None else argv
    if any(a in ("-h", "--help") for a in args[1:]):
        print(help_text())
        return 0
    rclpy.init(args=args)
    node = None
    try:
        node = RsvoNode()
        # One executor thread: every callback only hands data over (the frames are processed
        # on the worker thread). rclpy's MultiThreadedExecutor loops in Python while a
        # callback runs on its pool, holding the GIL that tracking needs: at 30 Hz 1280x720 the
        # node posed 74-119 of 300 frames with it against 287-294 with this one (README, "The
        # executor took the tracking's time").
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        executor.spin()
    except STARTUP_ERRORS as exc:
        print(f"rsvo_node: invalid parameter: {exc}", file=sys.stderr)
        return 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
