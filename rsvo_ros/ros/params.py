"""rsvo_node's parameters: names, defaults, descriptions and ranges, and their validation.

Each parameter is declared with a ``ParameterDescriptor`` (description, type, range), as
image_tools does; :func:`read_config` turns the declared values into a checked
:class:`NodeConfig` or raises ``ValueError`` naming the parameter (the node then exits 2).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
)
from rclpy.exceptions import InvalidTopicNameException
from rclpy.expand_topic_name import expand_topic_name
from rclpy.parameter import Parameter
from rclpy.validate_full_topic_name import validate_full_topic_name
from scipy.spatial.transform import Rotation

from rsvo_ros.core.readout import READOUTS, check_readout
from rsvo_ros.odometry.local_map import ACCELERATION_STD_RAD_S2
from rsvo_ros.odometry.pairwise import (
    BOOTSTRAP_UNCERTAIN_ROTATION_DEG,
    UNCERTAIN_PAIR_ROTATION_DEG,
    uncertain_rotation_or_auto,
)
from rsvo_ros.odometry.pipeline import BACKENDS
from rsvo_ros.odometry.tracker import (
    AUTO_BUSY_SHARE,
    AUTO_DROP_SHARE,
    AUTO_MIN_SIDE_PX,
    AUTO_SETTLE_IMAGES,
    AUTO_SPAN_IMAGES,
    DEFAULT_WINDOW_PX,
    MAX_DECIMATION,
    MAX_REFINE_WINDOW_PX,
    MAX_WINDOW_PX,
    MIN_WINDOW_PX,
    RETRY_BELOW_SHARE,
    refine_window_or_auto,
)
from rsvo_ros.odometry.window import (
    MAX_MAPPING_LAG_S,
    NODE_MAPPING_LAG_S,
    STALL_INTERVALS,
    check_stall,
)
from rsvo_ros.ros.camera_file import load_camera_file
from rsvo_ros.ros.convert import CameraIntrinsics
from rsvo_ros.twoview.estimator import MODELS

QOS_CHOICES = ("auto", "reliable", "best_effort")
LOST_CHOICES = ("large_covariance", "none")
LINE_DELAY_MODES = ("fixed", "auto")
DECIMATION_MODES = ("fixed", "auto")
IMAGE_TRANSPORTS = ("raw", "compressed")


def _float(desc, lo, hi, step=0.0):
    return ParameterDescriptor(description=desc, type=ParameterType.PARAMETER_DOUBLE,
                               floating_point_range=[FloatingPointRange(
                                   from_value=lo, to_value=hi, step=step)])  # fmt: skip


def _int(desc, lo, hi):
    return ParameterDescriptor(description=desc, type=ParameterType.PARAMETER_INTEGER,
                               integer_range=[IntegerRange(from_value=lo, to_value=hi, step=1)])


def _str(desc, choices=None):
    extra = f" One of: {', '.join(choices)}." if choices else ""
    return ParameterDescriptor(description=desc + extra, type=ParameterType.PARAMETER_STRING,
                               additional_constraints=extra.strip())  # fmt: skip


def _bool(desc):
    return ParameterDescriptor(description=desc, type=ParameterType.PARAMETER_BOOL)


PARAMETERS = {
    "image_topic": ("camera/image_raw", _str("Input sensor_msgs/Image topic (the base "
                                             "topic with image_transport compressed).")),
    "image_transport": ("raw", _str(
        "raw: sensor_msgs/Image on image_topic; compressed: sensor_msgs/CompressedImage (JPEG "
        "or PNG) on image_topic + '/compressed', as image_transport's compressed plugin "
        "publishes it (decoded here; JPEG artefacts cost some accuracy).", IMAGE_TRANSPORTS)),
    "camera_info_topic": ("camera/camera_info", _str("Input sensor_msgs/CameraInfo topic.")),
    "image_rectified": (False, _bool(
        "The images are rectified (image_proc's image_rect): the intrinsics are CameraInfo's "
        "projection P (with camera_file: its projection_matrix) and no lens distortion is "
        "removed (false: the raw image, K and D).")),
    "camera_file": ("", _str(
        "Intrinsics from a calibration file instead of camera_info_topic (not subscribed then): "
        "a ROS camera calibration YAML (camera_calibration, camera_info_manager) or a Kalibr "
        "camchain YAML (pinhole; radtan, equidistant or no distortion); a path or a file:// "
        "URL. '' (default): the topic.")),
    "camera_file_entry": ("", _str(
        "camera_file is a Kalibr camchain of several cameras: the entry to use (cam0, cam1, "
        "...); '' (default): the only one, or cam0.")),
    "uncalibrated_focal_factor": (0.0, _float(
        "A camera info without calibration (K all zero, as drivers publish without a "
        "calibration file): > 0 assumes a pinhole camera of focal length this many image widths "
        "(0.7-1.2 for most phones, webcams and dash cams), principal point at the centre, no "
        "lens distortion, with a warning (diagnostics intrinsics: assumed); odometry from a "
        "guessed focal length is approximate, calibrate for accuracy. 0 (default): such camera "
        "infos are refused and counted as bad.", 0.0, 10.0)),
    "odom_topic": ("rsvo/odom", _str("Output nav_msgs/Odometry topic.")),
    "path_topic": ("rsvo/path", _str("Output nav_msgs/Path topic.")),
    "debug_image_topic": ("rsvo/debug_image", _str("Output debug image (tracks, inliers).")),
    "line_delay": (0.0, _float("Seconds per image row (rolling-shutter line delay, tau); "
                               "0 for a global shutter.", 0.0, 1e-3)),
    "line_delay_mode": ("fixed", _str(
        "fixed: use line_delay; auto: estimate the line delay from the video (RS model, window "
        "backend; line_delay is the start, or a nominal half-frame readout when it is 0) and "
        "report it in the diagnostics.", LINE_DELAY_MODES)),
    "line_delay_rerun": (False, _bool(
        "line_delay_mode auto: when the first estimate comes, process the frames so far again "
        "with it (at most 300, kept as images until then; again with a later estimate over 10 "
        "% away, at most 3 times) and publish their new poses as the path; the odometry stays "
        "continuous. Takes a second or two on that frame, during "
        "which the camera's frames are dropped (the newest is kept), so false (default) for a "
        "live camera: a vehicle's odometry does not survive that gap (emulated, ATE 5-40x "
        "worse on vehicles, 1.6x over 33 bags; README, line-delay section); rsvo_replay does "
        "it unless --no-line-delay-rerun (the frames before the first estimate otherwise keep "
        "the map and scale the starting readout gave them).")),
    "line_delay_refine_frames": (150, _int(
        "line_delay_mode auto: after this many frames, run them again (the dropped ones too) "
        "at the calibrator's estimate over all its windows, in the background with the map's "
        "shear removed, and take the refined line delay (status refined; as rsvo_calibrate's "
        "second pass, over these frames; they are kept as images until then, 138 MB at "
        "1280x720; in a process of its own at the lowest CPU priority; only for frames at 25 "
        "Hz or faster). 0: keep the calibrator's estimate.",
        0, 100000)),
    "line_delay_save_file": ("", _str(
        "line_delay_mode auto: write the estimate to this ROS 2 parameter file when it "
        "converges or is refined and at shutdown (line_delay: the estimate, line_delay_mode: "
        "auto), so that the next start with --params-file FILE begins from it instead of the "
        "nominal "
        "half-frame readout; '' (default): not written.")),
    "trajectory_file": ("", _str(
        "Write every published odometry pose to this file as TUM lines (stamp x y z qx qy qz "
        "qw, odom_frame to the published child frame), for evo or the TUM tools; a reset or "
        "time jump back starts a new trajectory after a '# new trajectory' comment line; "
        "replaced at start-up, flushed every second and at shutdown. '' (default): not "
        "written.")),
    "model": ("rs", _str("Relative pose model.", MODELS)),
    "readout_direction": ("down", _str(
        "Which way the rolling shutter reads the images as they arrive: down (rows top to "
        "bottom), up (an image turned by 180 degrees: a camera mounted upside down and the "
        "image turned the right way up), right / left (columns: an image turned by 90 degrees, "
        "a phone filming in portrait); line_delay is then the time per line read.", READOUTS)),
    "backend": ("window", _str("Odometry backend: window (keyframes, a local map and the RS "
                               "window bundle adjustment) or pairwise (the paper's chain of "
                               "frame pairs).", BACKENDS)),
    "async_mapping": (True, _bool(
        "Window backend: keyframe insertion and the window bundle adjustment on a background "
        "thread, off the publishing path (false: inline, as rsvo_replay does; with "
        "mapping_lag_s the same poses either way).")),
    "mapping_lag_s": (NODE_MAPPING_LAG_S, _float(
        "Window backend: pick up each keyframe's bundle adjustment at the first frame stamped "
        "at least this many seconds after the keyframe, waiting for it if it has not finished "
        "(the odometry then follows from the frames, not from the machine's speed: where the "
        "node processed every frame, rsvo_replay --mapping-lag S gives the same poses "
        "offline; at 15 Hz 0.05 s is the next frame, at 30 Hz the second); 0: at the first "
        "frame after it finishes (the odometry depends on the timing).", 0.0,
        MAX_MAPPING_LAG_S)),
    "refind_map": (True, _bool(
        "Window backend: remember the landmarks with ORB descriptors and, when the map is lost "
        "(a look around, a stop) or rebuilt after a loss, find it again by matching them (the "
        "old map's world and scale: /odom jumps back to where the old map puts the camera; "
        "false: the pair estimator's recovery only).")),
    "stall_frames": (STALL_INTERVALS, _float(
        "Window backend: a frame that comes more than this many frame intervals (and at most "
        "1 s) after the last one (a camera or a node that stalled) is checked: its tracks may "
        "have locked onto a copy of a repeated pattern, so a pose tracked far off the "
        "constant-velocity prediction with few of the usual inliers, or a pair recovery far "
        "off it, is not taken, and the map starts over at the prediction with the speed from "
        "before (rendered cars along a repeated texture, 0.2-0.67 s stalls: ATE 0.39x and "
        "0.53x in geometric mean; walks and hand-held video unchanged). 0: off (the frame is "
        "tracked and recovered as any other).", 0.0, 1000.0)),
    "angular_acceleration_std": (ACCELERATION_STD_RAD_S2, _float(
        "Window backend, RS: std (rad/s^2) of the zero-mean prior on each frame's angular "
        "acceleration during its readout (a 10 Hz shake of 1 rad/s); 0 keeps the paper's "
        "constant velocity within a frame (smooth vehicle motion: ATE up to 6 % lower, "
        "per-frame rotation error 14-27 % higher; README).", 0.0, 10000.0)),
    "max_features": (500, _int("Tracked corners (paper: 500).", 20, 5000)),
    "klt_window_px": (DEFAULT_WINDOW_PX, _int(
        "KLT: the image pyramid's window (px). Its time grows with its area: 17 px tracks in "
        "0.45-0.63x the time of 21 (fewer frames dropped at camera rate) with the same accuracy "
        "on the README's synthetic bags, but turned one real pair's RS estimate 4 deg off "
        "(README).", MIN_WINDOW_PX, MAX_WINDOW_PX)),
    "tracking_decimation": (1, _int(
        "Track corners at 1/this of the images' resolution (the images averaged down; "
        "rtabmap's Odom/ImageDecimation): 1 is full resolution; 2 tracked a 1280x720 camera in "
        "0.6x the time, for a machine that cannot keep up with its camera at full resolution "
        "(frames dropped; less accurate on vehicles and on a real pair); the KLT windows, the "
        "refinement and the corner distances are then in the reduced image's pixels (README).",
        1, MAX_DECIMATION)),
    "tracking_decimation_mode": ("fixed", _str(
        "fixed: track at tracking_decimation throughout; auto: start there and, when more "
        f"than {100 * AUTO_DROP_SHARE:.0f} % of {AUTO_SPAN_IMAGES} images in a row were dropped "
        f"or the node was busy processing more than {100 * AUTO_BUSY_SHARE:.0f} % of their time "
        f"(after the first {AUTO_SETTLE_IMAGES}), track at the next lower resolution without "
        f"losing a track, as long as the reduced images' longer side stays at least "
        f"{AUTO_MIN_SIDE_PX} px (a 640x480 camera stays at full resolution); logged and in the "
        "diagnostics; never back during a run (README, 'Tracking at a reduced resolution').",
        DECIMATION_MODES)),
    "klt_refine_window_px": (-1, _int(
        "KLT: after the pyramid's window, polish each track at full resolution with a "
        "window of this many px (the window backend's vehicles otherwise shrink by about 2 %/s; "
        "README). -1: the backend's choice (11 for window, 0 for pairwise); 0: off; else "
        f"3-{MAX_REFINE_WINDOW_PX}.", -1, MAX_REFINE_WINDOW_PX)),
    "photometric_compensation": (True, _bool(
        "KLT: where the brightness changed from the last image (auto exposure, auto gain), fit "
        "the change on the tracked points and track again in the last image's grey levels "
        "(counted in diagnostics as brightness_compensated; false: track the images as they "
        "are).")),
    "klt_shift_retry": (True, _bool(
        f"KLT: where it keeps less than {100 * RETRY_BELOW_SHARE:.0f} % of the tracks (a turn "
        "faster than its reach: at "
        "15 Hz a quick head turn moves the image 150-240 px), measure the images' shift by "
        "phase correlation and track again from it, keeping the attempt with more tracks "
        "(counted in diagnostics as tracked_from_shift; false: KLT's own tracks only).")),
    "ransac_threshold_px": (1.0, _float("Sampson distance of an inlier (px).", 0.05, 20.0)),
    "motion_prior": (True, _bool(
        "RS: centre the velocity prior on the constant velocity of each frame pair's motion "
        "(from the image stamps) and start the search also from the previous pair's motion. "
        "False: each pair on its own, as in the paper.")),
    "rotation_only_parallax_px": (3.0, _float(
        "Pairwise chain (pairwise backend; window backend while its map starts): a frame pair "
        "whose tracks a turning camera explains to within this many px (median, at 1000 px "
        "focal) is posed by that rotation, its baseline too short for the pair estimator "
        "(hand-held walks: ATE about halved, README). 0: never.", 0.0, 100.0)),
    "uncertain_rotation_deg": (-1.0, _float(
        "RS pairwise chain: a frame pair whose estimated rotation std is over this many "
        "degrees is posed by a turning camera's rotation at any parallax, its scale the last "
        "baseline (vehicles' first frames: RPE rotation about 0.7x, README). -1: the backend's "
        f"choice ({BOOTSTRAP_UNCERTAIN_ROTATION_DEG:g} for the window's bootstrap, "
        f"{UNCERTAIN_PAIR_ROTATION_DEG:g} for pairwise); 0: never.", -1.0, 180.0)),
    "lm_max_iterations": (30, _int("Levenberg-Marquardt iterations of the refinements.", 1,
                                   500)),
    "odom_frame": ("odom", _str("frame_id of the odometry and path.")),
    "camera_frame": ("camera_optical_frame", _str(
        "The camera's optical frame id; '' takes the images' own header.frame_id (the first "
        "image's; camera_optical_frame where it is empty), so that /tf joins the camera "
        "driver's frames.")),
    "base_frame": ("", _str("If set, odometry is published for this frame (child_frame_id) "
                            "using base_to_camera.")),
    "base_to_camera": ([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
                       ParameterDescriptor(description="Fixed T_base_camera as [x, y, z, qx, "
                                           "qy, qz, qw] (m, unit quaternion).",
                                           type=ParameterType.PARAMETER_DOUBLE_ARRAY)),
    "publish_tf": (True, _bool("Broadcast odom_frame -> base_frame (or camera_frame) on /tf "
                               "with every odometry message, and base_frame -> camera_frame on "
                               "/tf_static when base_frame is set.")),
    "lost_odometry": ("large_covariance", _str(
        "While tracking is lost: large_covariance publishes the held pose with a covariance of "
        "1e6 on the diagonal (rtabmap's convention); none publishes no odometry (and no /tf).",
        LOST_CHOICES)),
    "map_points_topic": ("rsvo/map_points", _str("Output sensor_msgs/PointCloud2: the local "
                                                 "map's landmarks in odom_frame.")),
    "keyframe_path_topic": ("rsvo/keyframes", _str("Output nav_msgs/Path: the keyframes as the "
                                                   "window last corrected them.")),
    "map_publish_period_s": (1.0, _float("Period of the map points and keyframe path (s); "
                                         "0 publishes them with every frame.", 0.0, 60.0)),
    "path_max_length": (1000, _int("Poses kept in the published path (and keyframes kept "
                                   "for the keyframe path).", 1, 100000)),
    "path_publish_period_s": (0.1, _float("Least time between two /rsvo/path messages (s); 0 "
                                          "publishes the path with every odometry message. A "
                                          "1000-pose path takes about 5 ms to publish: per "
                                          "frame at 30 Hz, a sixth of the frame time.", 0.0,
                                          60.0)),
    "image_qos_reliability": ("auto", _str("Image subscription reliability; auto matches the "
                                           "publisher as rosbag2's recorder does.",
                                           QOS_CHOICES)),
    "publish_debug_image": (True, _bool("Publish the debug image.")),
    "diagnostics_period_s": (1.0, _float("Diagnostics publishing period (s).", 0.1, 60.0)),
}

# the topic parameters: relative names (the defaults) take the node's namespace, so that
# `--ros-args -r __ns:=/left` runs a second camera's odometry beside the first
TOPIC_PARAMETERS = ("image_topic", "camera_info_topic", "odom_topic", "path_topic",
                    "debug_image_topic", "map_points_topic", "keyframe_path_topic")
for _name in TOPIC_PARAMETERS:
    PARAMETERS[_name][1].description += (" A relative name (the default) is in the node's "
                                         "namespace; a leading / makes it absolute.")

# the parameters a running node takes (``ros2 param set``), from its next frame (the
# diagnostics period: from the next period); every other one is read once at start-up and
# declared read-only, so that a change is refused ("Trying to set a read-only parameter")
# instead of accepted and ignored
LIVE_PARAMETERS = ("publish_debug_image", "lost_odometry", "path_publish_period_s",
                   "map_publish_period_s", "diagnostics_period_s")
for _name, (_default, _desc) in PARAMETERS.items():
    _desc.read_only = _name not in LIVE_PARAMETERS
    _desc.description += (" Can be changed while the node runs." if _name in LIVE_PARAMETERS
                          else " Read at start-up (read-only).")


def integer_as_double(param: Parameter) -> Parameter:
    """An integer given for one of the node's double parameters (``-p line_delay:=0``,
    ``ros2 param set /rsvo_node diagnostics_period_s 1``), as that double: rclpy refuses it
    otherwise ("expecting type 'DOUBLE'"), and ROS users write ``:=0``. Anything else as it
    is (a string for a double is still refused by rclpy)."""
    spec = PARAMETERS.get(param.name)
    if spec is None or spec[1].type != ParameterType.PARAMETER_DOUBLE \
            or param.type_ != Parameter.Type.INTEGER:  # fmt: skip
        return param
    return Parameter(param.name, Parameter.Type.DOUBLE, float(param.value))


def check_live_change(name: str, value) -> str:
    """Why a running node refuses ``name = value`` ('' when it takes it); ranges and types
    are rclpy's (the descriptors), this checks the choices."""
    if name not in LIVE_PARAMETERS:
        return f"{name} is read at start-up: restart the node with -p {name}:=VALUE"
    if name in CHOICES and value not in CHOICES[name]:
        return f"parameter {name} must be one of {CHOICES[name]}, got {value!r}"
    return ""


@dataclass
class NodeConfig:
    """The checked parameter values; ``T_base_cam`` (4, 4) from ``base_to_camera``."""

    values: dict
    T_base_cam: np.ndarray = field(default_factory=lambda: np.eye(4))
    camera: CameraIntrinsics | None = None  # from camera_file (None: from the topic)

    def __getitem__(self, name: str):
        return self.values[name]


def _yaml_value(value) -> str:
    """A parameter value as ROS 2's parameter-file parser reads it back with the same type:
    floats always with a point, strings quoted."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        text = repr(value)
        if "." not in text and "inf" not in text and "nan" not in text:
            text = text.replace("e", ".0e") if "e" in text else text + ".0"
        return text
    if isinstance(value, str):
        return "'" + value.replace("'", "''") + "'"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_yaml_value(v) for v in value) + "]"
    raise TypeError(f"no parameter-file form for {type(value).__name__}")


def params_yaml(estimate: dict, source: str, mode: str = "fixed",
                node_name: str = "rsvo_node", readout_direction: str = "down") -> str:
    """A ROS 2 parameter file for the node with a line delay estimate (a
    :class:`~rsvo_ros.odometry.line_delay.LineDelayEstimate` as a dict); ``mode``: the
    ``line_delay_mode`` it sets (fixed: use the value; auto: start from it and go on
    estimating); ``readout_direction``: the one the estimate was made with (written where it
    is not the default: the line delay is per line read in that direction)."""
    if mode not in LINE_DELAY_MODES:
        raise ValueError(f"mode must be one of {LINE_DELAY_MODES}, got {mode!r}")
    check_readout(readout_direction)
    direction = "" if readout_direction == "down" else \
        f"    readout_direction: {_yaml_value(readout_direction)}\n"
    return (f"# {source}: {estimate['status']}, {estimate['windows']} windows, "
            f"{estimate['frames']} frames\n"
            f"# line delay {estimate['line_delay_s']:.6g} +- {estimate['std_s']:.3g} s/row; "
            f"readout {estimate['readout_s'] * 1e3:.3f} ms = "
            f"{estimate['readout_fraction']:.3f} +- {estimate['std_fraction']:.3f} frame "
            "intervals\n"
            f"{node_name}:\n"
            "  ros__parameters:\n"
            f"    line_delay: {_yaml_value(float(format(estimate['line_delay_s'], '.6g')))}\n"
            f"    line_delay_mode: {_yaml_value(mode)}\n" + direction)


# the string parameters that take one of a few values
CHOICES = {"model": MODELS, "backend": BACKENDS, "image_qos_reliability": QOS_CHOICES,
           "readout_direction": READOUTS,
           "image_transport": IMAGE_TRANSPORTS, "line_delay_mode": LINE_DELAY_MODES,
           "lost_odometry": LOST_CHOICES, "tracking_decimation_mode": DECIMATION_MODES}


def read_config(values: dict) -> NodeConfig:
    """Check the declared values (ranges are enforced by rclpy already); ``ValueError`` names
    the parameter that is wrong."""
    p = values
    for name, choices in CHOICES.items():
        if p[name] not in choices:
            raise ValueError(f"parameter {name} must be one of {choices}, got {p[name]!r}")
    if p["line_delay_mode"] == "auto" and (p["model"] != "rs" or p["backend"] != "window"):
        raise ValueError("parameter line_delay_mode auto needs model rs and backend window")
    if p["line_delay_rerun"] and p["line_delay_mode"] != "auto":
        raise ValueError("parameter line_delay_rerun needs line_delay_mode auto")
    if p["line_delay_save_file"]:
        if p["line_delay_mode"] != "auto":
            raise ValueError("parameter line_delay_save_file needs line_delay_mode auto")
        folder = Path(p["line_delay_save_file"]).expanduser().parent
        if not folder.is_dir():
            raise ValueError(f"parameter line_delay_save_file: folder {folder} does not exist")
    if p["trajectory_file"]:
        folder = Path(p["trajectory_file"]).expanduser().parent
        if not folder.is_dir():
            raise ValueError(f"parameter trajectory_file: folder {folder} does not exist")
    refine_window_or_auto(p["klt_refine_window_px"], "parameter klt_refine_window_px")
    uncertain_rotation_or_auto(p["uncertain_rotation_deg"], "parameter uncertain_rotation_deg")
    check_stall(p["stall_frames"], name="parameter stall_frames")
    tf = np.asarray(p["base_to_camera"], float)
    if tf.shape != (7,) or not np.isfinite(tf).all() or abs(np.linalg.norm(tf[3:]) - 1) > 1e-3:
        raise ValueError("parameter base_to_camera must be [x, y, z, qx, qy, qz, qw] with a "
                         f"unit quaternion, got {list(tf)}")  # fmt: skip
    for topic in TOPIC_PARAMETERS:
        if not p[topic]:
            raise ValueError(f"parameter {topic} must not be empty")
        try:  # as rclpy checks it, in the root namespace (the node's own is checked by rcl)
            validate_full_topic_name(expand_topic_name(p[topic], "rsvo_node", "/"))
        except (InvalidTopicNameException, ValueError) as exc:  # rcl's expansion: ValueError
            reason = str(exc).splitlines()[0].split(": ", 1)[-1].split(", at /")[0]
            reason = reason.rstrip(":")
            raise ValueError(f"parameter {topic}: {p[topic]!r} is not a topic name ({reason})"
                             ) from None
    T_base_cam = np.eye(4)
    T_base_cam[:3, :3] = Rotation.from_quat(tf[3:]).as_matrix()
    T_base_cam[:3, 3] = tf[:3]
    camera = None
    if p["camera_file"]:
        path = p["camera_file"].removeprefix("file://")
        try:
            camera = load_camera_file(path, p["camera_file_entry"] or None,
                                      bool(p["image_rectified"]))
        except (OSError, ValueError) as exc:
            raise ValueError(f"parameter camera_file: {exc}") from None
    return NodeConfig(dict(values), T_base_cam, camera)


def image_subscription(p: NodeConfig | dict) -> tuple[str, str]:
    """``(topic, kind)`` the node subscribes its images on: ``kind`` ``"raw"``
    (sensor_msgs/Image on ``image_topic``) or ``"compressed"`` (sensor_msgs/CompressedImage on
    ``image_topic/compressed``, image_transport's naming)."""
    if p["image_transport"] == "compressed":
        return p["image_topic"].rstrip("/") + "/compressed", "compressed"
    return p["image_topic"], "raw"


def help_text() -> str:
    """``rsvo_node --help``: every parameter with its default and description."""
    lines = ["usage: rsvo_node [--ros-args -p name:=value ... | --params-file FILE]", "",
             "parameters (as a parameter file at the defaults, with these descriptions: "
             "python -m rsvo_ros.ros.params, installed as "
             "share/rsvo_ros/config/rsvo_node.yaml):"]
    for name, (default, desc) in PARAMETERS.items():
        lines.append(f"  {name} (default {default!r}): {desc.description}")
    lines += ["", "images over 512 KB (1280x720 mono8 and up) leave Fast DDS's default "
              "shared-memory segment and arrive 10-15 ms later; in the camera driver's (and "
              "this node's) environment:",
              "  export FASTRTPS_DEFAULT_PROFILES_FILE=$(python -m rsvo_ros.ros.dds)"]
    return "\n".join(lines)


DEFAULTS_FILE = Path(__file__).with_name("rsvo_node.yaml")


def _range_text(desc: ParameterDescriptor) -> str:
    if desc.floating_point_range:
        r = desc.floating_point_range[0]
        return f" Range {r.from_value:g} to {r.to_value:g}."
    if desc.integer_range:
        r = desc.integer_range[0]
        return f" Range {r.from_value} to {r.to_value}."
    return ""


def defaults_yaml(node_name: str = "rsvo_node") -> str:
    """A ROS 2 parameter file with every parameter of the node at its default, each under its
    description and range as comments: ``rsvo_node --ros-args --params-file FILE``."""
    import textwrap

    lines = ["# rsvo_node's parameters at their defaults, each with its description (generated",
             "# by python -m rsvo_ros.ros.params; rsvo_node --help lists the same). Copy, edit",
             "# and start the node with: rsvo_node --ros-args --params-file FILE",
             f"{node_name}:", "  ros__parameters:"]
    for name, (default, desc) in PARAMETERS.items():
        text = desc.description + _range_text(desc)
        lines += textwrap.wrap(text, width=95, initial_indent="    # ",
                               subsequent_indent="    # ")
        lines.append(f"    {name}: {_yaml_value(default)}")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    """``python -m rsvo_ros.ros.params [--output FILE]``: the defaults as a parameter file."""
    import argparse

    p = argparse.ArgumentParser(prog="python -m rsvo_ros.ros.params",
                                description="Write rsvo_node's parameters at their defaults, "
                                "with descriptions, as a ROS 2 parameter file (stdout or "
                                "--output). The same file is installed as "
                                "share/rsvo_ros/config/rsvo_node.yaml.")
    p.add_argument("--output", default=None, help="write it here instead of stdout")
    args = p.parse_args(argv)
    text = defaults_yaml()
    if args.output:
        try:
            Path(args.output).write_text(text)
        except OSError as exc:
            print(f"python -m rsvo_ros.ros.params: cannot write {args.output}: "
                  f"{exc.strerror or exc}", file=sys.stderr)
            return 1
    else:
        print(text, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
