"""rsvo_replay: the odometry pipeline over a recorded rosbag2 (or a ROS 1 .bag), as fast as the
machine allows.

Streams the bag (memory does not grow with its length) and writes into ``--output``:
``trajectory.tum``, the ``odometry`` bag (``/rsvo/odom`` and ``/tf`` per frame, ``/rsvo/path`` at
most 10 times per second of bag time and with the last frame, the map), ``summary.json`` and
``trajectory.png``. Accuracy (ATE after Sim(3) alignment, RPE) comes from ``evo``.
Exit codes: 0 done, 1 the bag cannot be read or holds no usable frames, 2 bad arguments.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import shutil
import sys
import time
import traceback
from collections import Counter, deque
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from rsvo_ros.core.geometry import interpolate_poses
from rsvo_ros.core.readout import READOUTS
from rsvo_ros.odometry.local_map import ACCELERATION_STD_RAD_S2
from rsvo_ros.odometry.pairwise import (
    BOOTSTRAP_UNCERTAIN_ROTATION_DEG,
    ROTATION_ONLY_PARALLAX_PX,
    UNCERTAIN_PAIR_ROTATION_DEG,
    uncertain_rotation_or_auto,
)
from rsvo_ros.odometry.pipeline import (
    BACKENDS,
    FAULT_RESET_AFTER,
    FrameResult,
    OdometryPipeline,
    PipelineOptions,
    warm_up,
)
from rsvo_ros.odometry.tracker import (
    DEFAULT_WINDOW_PX,
    MAX_DECIMATION,
    MAX_REFINE_WINDOW_PX,
    MAX_WINDOW_PX,
    MIN_WINDOW_PX,
    RETRY_BELOW_SHARE,
    check_decimation,
    check_window,
    refine_window_or_auto,
)
from rsvo_ros.odometry.twist import Twist, body_twist
from rsvo_ros.odometry.window import MAX_MAPPING_LAG_S, WindowOptions
from rsvo_ros.ros import bagio
from rsvo_ros.ros.camera_file import load_camera_file
from rsvo_ros.ros.convert import (
    POINT_FIELD_FLOAT32,
    XYZ_FIELDS,
    XYZ_POINT_STEP,
    CameraIntrinsics,
    camera_from_info,
    covariance_for_msg,
    image_to_gray,
    pose_components,
    stamp_ns,
    tum_line,
    xyz_cloud_data,
)
from rsvo_ros.ros.draw import draw_tracks
from rsvo_ros.twoview.estimator import MODELS

EXIT_OK, EXIT_BAD_BAG, EXIT_USAGE = 0, 1, 2
PATH_LENGTH = 1000  # poses kept in each /rsvo/path message (bounded)
# /rsvo/path at most once per this much bag time (and with the last frame of a trajectory): a
# 1000-pose Path takes ~27 ms to serialize, which per frame would halve the replay's rate
PATH_PERIOD_NS = 100_000_000
ODOM_TOPIC, PATH_TOPIC = "/rsvo/odom", "/rsvo/path"
MAP_TOPIC, KEYFRAMES_TOPIC, TF_TOPIC = "/rsvo/map_points", "/rsvo/keyframes", "/tf"
MAP_PERIOD_NS = 1_000_000_000  # map points and keyframe path: once per second of bag time
ODOM_FRAME = "odom"
SCALE_CHECK_FRAMES = 60  # scale drift: the whole run's Sim(3) scale against these first frames
TF_TYPE, CLOUD_TYPE = "tf2_msgs/msg/TFMessage", "sensor_msgs/msg/PointCloud2"

# the WindowOptions fields --window-option may set, and their types
NUMERIC_WINDOW_OPTIONS = {f.name: {"int": int, "float": float}[f.type]
                          for f in fields(WindowOptions) if f.type in ("int", "float")}


class ReplayError(Exception):
    """A one-line reason why the bag cannot be replayed."""


@dataclass
class ReplayConfig:
    bag: Path
    output: Path
    model: str = "rs"
    image_topic: str = bagio.IMAGE_TOPIC
    camera_info_topic: str = bagio.CAMERA_INFO_TOPIC
    ground_truth_topic: str = bagio.GROUND_TRUTH_TOPIC
    line_delay: float | None = None
    max_features: int = 500
    overwrite: bool = False
    progress: bool = True
    options: PipelineOptions = field(default_factory=PipelineOptions)
    max_frames: int | None = None  # stop after this many images (None: the whole bag)
    refine_window_px: int | None = None  # TrackerOptions.refine_window_px (None: by backend)
    # intrinsics from a calibration file (ROS or Kalibr YAML) instead of the camera info topic
    camera_file: Path | None = None
    camera_entry: str | None = None  # the Kalibr camchain's entry (cam0, cam1, ...)
    rectified: bool = False  # rectified images: CameraInfo's P, no lens
    debug_video: Path | None = None  # an MP4 of every processed frame with its tracks drawn
    # > 0: a camera info without calibration (K all zero) gets a pinhole of this many image
    # widths as focal length (ros.convert.assumed_intrinsics); 0: refused
    uncalibrated_focal_factor: float = 0.0


def _odometry(res: FrameResult):
    T, tw = res.T_world_cam, res.twist
    return bagio.odometry_msg(res.stamp_ns, T[:3, :3], T[:3, 3], ODOM_FRAME, bagio.CAMERA_FRAME,
                              linear=tw.linear, angular=tw.angular,
                              pose_covariance=covariance_for_msg(res.covariance),
                              twist_covariance=covariance_for_msg(tw.covariance))  # fmt: skip


class PathMessages:
    """``nav_msgs/Path`` messages of ``(stamp_ns, T)`` poses, each pose's ``PoseStamped`` built
    once (building one takes ~0.25 ms: rebuilt for every message, a 1000-pose path cost 0.25 s
    per frame). Only the poses of the last message are kept."""

    def __init__(self):
        self._stamped: dict[tuple[int, bytes], object] = {}

    def __call__(self, poses, stamp_ns: int):
        ts = bagio.typestore()
        keep = {}
        for s, T in poses:
            key = (int(s), np.asarray(T, float).tobytes())
            msg = self._stamped.get(key)
            if msg is None:
                msg = ts.types["geometry_msgs/msg/PoseStamped"](
                    header=bagio.header(s, ODOM_FRAME), pose=bagio.pose_msg(T[:3, :3], T[:3, 3]))
            keep[key] = msg
        self._stamped = keep
        return ts.types[bagio.PATH_TYPE](header=bagio.header(stamp_ns, ODOM_FRAME),
                                         poses=list(keep.values()))


def _tf(res: FrameResult):
    ts = bagio.typestore()
    (x, y, z), (qx, qy, qz, qw) = pose_components(res.T_world_cam)
    vec, quat = ts.types["geometry_msgs/msg/Vector3"], ts.types["geometry_msgs/msg/Quaternion"]
    tf = ts.types["geometry_msgs/msg/TransformStamped"](
        header=bagio.header(res.stamp_ns, ODOM_FRAME), child_frame_id=bagio.CAMERA_FRAME,
        transform=ts.types["geometry_msgs/msg/Transform"](
            translation=vec(x=x, y=y, z=z), rotation=quat(x=qx, y=qy, z=qz, w=qw)))
    return ts.types[TF_TYPE](transforms=[tf])


def _cloud(points: np.ndarray, stamp_ns: int):
    ts = bagio.typestore()
    data = np.frombuffer(xyz_cloud_data(points), np.uint8)
    field = ts.types["sensor_msgs/msg/PointField"]
    return ts.types[CLOUD_TYPE](
        header=bagio.header(stamp_ns, ODOM_FRAME), height=1, width=len(data) // XYZ_POINT_STEP,
        fields=[field(name=n, offset=o, datatype=POINT_FIELD_FLOAT32, count=1)
                for n, o in XYZ_FIELDS],
        is_bigendian=False, point_step=XYZ_POINT_STEP, row_step=len(data), data=data,
        is_dense=True)  # fmt: skip


def replay(cfg: ReplayConfig) -> dict:
    """Run the pipeline over ``cfg.bag``; returns the summary (also written to the output)."""
    if cfg.model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}")
    if cfg.debug_video is not None and not Path(cfg.debug_video).parent.is_dir():
        raise ValueError(f"--debug-video: folder {Path(cfg.debug_video).parent} does not exist")
    if cfg.output.exists() and any(cfg.output.iterdir()) and not cfg.overwrite:
        if (cfg.output / "odometry").exists():
            raise FileExistsError(f"{cfg.output} already holds a replay; pass --overwrite")
    cfg.output.mkdir(parents=True, exist_ok=True)
    odom_bag = cfg.output / "odometry"
    if odom_bag.exists():
        shutil.rmtree(odom_bag)
    try:
        reader = bagio.BagReader(cfg.bag)
    except Exception as exc:  # rosbags raises several types for unreadable bags
        raise ReplayError(f"cannot read bag {cfg.bag}: {exc}") from None
    topics = {c.topic: c for c in reader.connections}
    images = sorted(t for t, c in topics.items() if c.msgtype in bagio.IMAGE_TYPES)
    if cfg.image_topic == bagio.IMAGE_TOPIC and cfg.image_topic not in topics \
            and len(images) == 1:
        # the default topic is not there and the bag has one camera (e.g. only its
        # image_transport compressed topic): that one
        cfg = dataclasses.replace(cfg, image_topic=images[0])
        print(f"rsvo_replay: {bagio.IMAGE_TOPIC} is not in the bag; using its only image topic "
              f"{images[0]} ({topics[images[0]].msgtype.split('/')[-1]})", file=sys.stderr)
    if cfg.image_topic not in topics:
        reader.close()
        others = ", ".join(sorted(topics)) or "none"
        hint = (f"image topics: {', '.join(images)}" if images else
                f"no Image or CompressedImage topic; topics: {others}")
        raise ReplayError(f"no image topic {cfg.image_topic} in {cfg.bag} ({hint}); give "
                          "--image-topic")
    if topics[cfg.image_topic].msgtype not in bagio.IMAGE_TYPES:
        reader.close()
        raise ReplayError(f"{cfg.image_topic} in {cfg.bag} is {topics[cfg.image_topic].msgtype}"
                          f", not sensor_msgs/Image or CompressedImage"
                          f"{' (image topics: ' + ', '.join(images) + ')' if images else ''}; "
                          "give --image-topic")
    infos = sorted(t for t, c in topics.items() if c.msgtype == bagio.CAMERA_INFO_TYPE)
    if cfg.camera_file is None and cfg.camera_info_topic == bagio.CAMERA_INFO_TOPIC \
            and cfg.camera_info_topic not in topics and infos:
        # the default is not there: the image topic's sibling (image_transport's layout:
        # NS/image_raw[/compressed] beside NS/camera_info), else the bag's only camera info
        base = cfg.image_topic.removesuffix("/compressed").rsplit("/", 1)[0]
        sibling = f"{base}/camera_info"
        pick = sibling if sibling in infos else (infos[0] if len(infos) == 1 else None)
        if pick is not None:
            cfg = dataclasses.replace(cfg, camera_info_topic=pick)
            print(f"rsvo_replay: {bagio.CAMERA_INFO_TOPIC} is not in the bag; using {pick}"
                  f"{' (beside the image topic)' if pick == sibling else ''}", file=sys.stderr)
    file_camera: CameraIntrinsics | None = None
    if cfg.camera_file is not None:
        try:
            file_camera = load_camera_file(cfg.camera_file, cfg.camera_entry, cfg.rectified)
        except (OSError, ValueError) as exc:
            reader.close()
            raise ReplayError(f"camera file {cfg.camera_file}: {exc}") from None
    elif cfg.camera_info_topic not in topics:
        reader.close()
        known = f"camera info topics: {', '.join(infos)}" if infos else "none in the bag"
        raise ReplayError(f"no camera info topic {cfg.camera_info_topic} in {cfg.bag} "
                          f"(the intrinsics K are needed; {known}); give --camera-info-topic "
                          "or --camera-file")
    line_delay = cfg.line_delay
    bag_text = bagio.custom_data(cfg.bag).get(bagio.LINE_DELAY_KEY)
    try:
        bag_line_delay = None if bag_text is None else float(bag_text)
    except ValueError:
        bag_line_delay = None  # reported as unknown; an error below where it is needed
    auto = cfg.options.line_delay_auto and cfg.model == "rs"
    if auto:
        line_delay = 0.0  # estimated from the video; the bag's value is only reported
    elif line_delay is None:
        if bag_text is not None and bag_line_delay is None:
            reader.close()
            raise ReplayError(f"{cfg.bag} records {bagio.LINE_DELAY_KEY} = {bag_text!r}, not a "
                              "number; give --line-delay (seconds per image row, or auto)")
        if bag_text is None and cfg.model == "rs":
            reader.close()
            raise ReplayError(f"{cfg.bag} does not record {bagio.LINE_DELAY_KEY}; give "
                              "--line-delay (seconds per image row, or auto)")
        line_delay = bag_line_delay if bag_line_delay is not None else 0.0
    if not np.isfinite(line_delay) or line_delay < 0:
        reader.close()
        raise ReplayError(f"line delay must be finite and >= 0, got {line_delay}")

    gt_topic = cfg.ground_truth_topic if cfg.ground_truth_topic in topics else None
    if gt_topic and topics[gt_topic].msgtype not in GROUND_TRUTH_TYPES:
        reader.close()
        raise ReplayError(f"ground truth topic {gt_topic} is {topics[gt_topic].msgtype}; "
                          f"supported: {', '.join(GROUND_TRUTH_TYPES)}")
    info_topic = None if file_camera is not None else cfg.camera_info_topic
    wanted = [topics[cfg.image_topic]] + ([topics[info_topic]] if info_topic else [])
    if gt_topic:
        wanted.append(topics[gt_topic])
    n_images = topics[cfg.image_topic].msgcount
    if cfg.max_frames is not None:
        n_images = min(n_images, cfg.max_frames)
    options = cfg.options
    options.model = cfg.model
    # the command line's tracker settings over the given options' (their other fields kept)
    options.tracker = dataclasses.replace(options.tracker, max_features=cfg.max_features,
                                          refine_window_px=cfg.refine_window_px)

    skipped: Counter = Counter()
    statuses: Counter = Counter()
    results_meta = []
    gt: dict[int, np.ndarray] = {}
    gt_w: dict[int, np.ndarray] = {}  # the ground truth's angular velocity (row-0 frame)
    est: dict[int, np.ndarray] = {}  # the current trajectory (a time reset starts another)
    twists: list[tuple[int, Twist]] = []  # each posed frame's odometry twist (stamps may repeat)
    trajectories: list[dict[int, np.ndarray]] = [est]
    # each trajectory as published frame by frame (a line_delay auto re-run revises the frames
    # before its first estimate in ``est``, not what a live node had published)
    published: dict[int, np.ndarray] = {}
    published_trajectories: list[dict[int, np.ndarray]] = [published]
    revised = 0  # frames re-posed by such a re-run
    time_resets = 0
    faults = fault_resets = 0  # processing errors in a row; resets after FAULT_RESET_AFTER
    refound = 0  # frames where the window re-found a lost map by its descriptors
    brightness = 0  # frames tracked in the previous image's grey levels (auto exposure)
    from_shift = 0  # frames tracked again from the images' shift (a turn past KLT's reach)
    last_map_ns = None
    images_read = 0
    pipeline: OdometryPipeline | None = None
    camera: CameraIntrinsics | None = None
    poses: deque = deque(maxlen=PATH_LENGTH)
    warm_s = warm_up()  # one-off kernel compile/load, not part of the frame rate
    t_start = time.perf_counter()
    bar = None
    if cfg.progress:
        from tqdm import tqdm

        bar = tqdm(total=n_images, desc="rsvo_replay", unit="frame", file=sys.stderr)
    # the first camera info, so that an image stamped with it (often written first) is usable
    camera = file_camera
    for c_info, _t, raw in reader.messages(connections=[topics[info_topic]] if info_topic
                                           else []):  # fmt: skip
        try:
            camera = camera_from_info(reader.deserialize(raw, c_info.msgtype), cfg.rectified,
                                      cfg.uncalibrated_focal_factor)  # fmt: skip
            break
        except Exception:  # noqa: BLE001 - a bad one is skipped, the next one may do
            continue
    if camera is not None and camera.assumed:
        print(f"rsvo_replay: the camera info is uncalibrated (all zero): assuming a pinhole "
              f"camera of focal length {camera.K[0, 0]:.1f} px ({cfg.uncalibrated_focal_factor:g} "
              f"x {camera.width} px), principal point at the centre, no lens distortion; "
              f"calibrate the camera for accurate odometry", flush=True)
    if camera is not None and camera.binning_y > 1:
        print(f"rsvo_replay: camera info with binning {camera.binning_y} rows: images "
              f"{camera.width}x{camera.height}, intrinsics scaled (REP 104); the line delay is "
              f"per image row, {camera.binning_y} x the sensor's row time", flush=True)
    video = None if cfg.debug_video is None else DebugVideo(cfg.debug_video)
    writer = bagio.open_writer(odom_bag, "sqlite3")
    ts = bagio.typestore()
    with writer, open(cfg.output / "trajectory.tum", "w") as tum:
        c_odom = writer.add_connection(ODOM_TOPIC, bagio.ODOMETRY_TYPE, typestore=ts)
        c_path = writer.add_connection(PATH_TOPIC, bagio.PATH_TYPE, typestore=ts)
        c_tf = writer.add_connection(TF_TOPIC, TF_TYPE, typestore=ts)
        c_map = writer.add_connection(MAP_TOPIC, CLOUD_TYPE, typestore=ts)
        c_kf = writer.add_connection(KEYFRAMES_TOPIC, bagio.PATH_TYPE, typestore=ts)

        path_msg, keyframe_path_msg = PathMessages(), PathMessages()
        last_path_ns = None

        def write_map(stamp: int) -> None:
            writer.write(c_map, stamp, bagio.serialize(_cloud(pipeline.map_points(), stamp)))
            writer.write(c_kf, stamp, bagio.serialize(keyframe_path_msg(
                pipeline.keyframe_poses(PATH_LENGTH), stamp)))

        def write_path(stamp: int) -> None:
            nonlocal last_path_ns
            writer.write(c_path, stamp, bagio.serialize(path_msg(poses, stamp)))
            last_path_ns = stamp

        def finish_path() -> None:
            """The whole path with the trajectory's last frame, if not written with it yet."""
            if poses and last_path_ns != poses[-1][0]:
                write_path(poses[-1][0])

        def new_trajectory() -> None:
            """The ended trajectory's last map and whole path written; the next pose starts
            another (a time reset, a reset after faults)."""
            nonlocal est, published, last_map_ns, last_path_ns
            if last_map_ns is not None:
                write_map(last_map_ns)
            finish_path()
            est, published, last_map_ns, last_path_ns = {}, {}, None, None
            trajectories.append(est)
            published_trajectories.append(published)
            poses.clear()

        def messages():
            """The bag's messages until the storage fails (a truncated or corrupt file in the
            middle of the bag): that ends the bag, counted; any other error is not the
            bag's."""
            it = iter(reader.messages(connections=wanted))
            while True:
                try:
                    item = next(it)
                except StopIteration:
                    return
                except Exception as exc:  # noqa: BLE001 - the reader's, whatever it raises
                    skipped[f"bag read stopped: {type(exc).__name__}: {exc}"[:200]] += 1
                    return
                yield item

        try:
            for conn, _t, raw in messages():
                try:
                    msg = reader.deserialize(raw, conn.msgtype)
                except Exception as exc:
                    if conn.topic == cfg.image_topic:
                        skipped[f"corrupt message: {type(exc).__name__}"] += 1
                        if bar is not None:
                            bar.update(1)
                    continue
                if conn.topic == info_topic:
                    try:
                        camera = camera_from_info(msg, cfg.rectified,
                                                  cfg.uncalibrated_focal_factor)  # fmt: skip
                    except ValueError as exc:
                        skipped[f"camera info: {exc}"] += 1
                    continue
                if conn.topic == gt_topic:
                    T, w = ground_truth_of(msg, conn.msgtype)
                    if np.isfinite(T).all():
                        gt[stamp_ns(msg.header)] = T
                        if w is not None:
                            gt_w[stamp_ns(msg.header)] = w
                    continue
                images_read += 1
                if cfg.max_frames is not None and images_read > cfg.max_frames:
                    break
                if bar is not None:
                    bar.update(1)
                stamp = stamp_ns(msg.header)
                if camera is None:
                    skipped["no camera info received yet"] += 1
                    continue
                try:
                    gray = image_to_gray(msg)
                except ValueError as exc:
                    skipped[str(exc).split(" (")[0]] += 1
                    continue
                if (gray.shape[1], gray.shape[0]) != (camera.width, camera.height) \
                        and camera.width > 0:
                    skipped["image size differs from camera info"] += 1
                    continue
                if pipeline is None:
                    pipeline = OdometryPipeline(camera.K, camera.lens, line_delay, options)
                else:
                    pipeline.set_camera(camera.K, camera.lens, line_delay)
                try:
                    res = pipeline.process(stamp, gray)
                    faults = 0
                except Exception as exc:  # noqa: BLE001 - as the node: one frame, not the bag
                    # the pipeline skips bad data itself; this is a fault of the package,
                    # counted per frame with the first traceback printed, the rest goes on
                    key = f"processing error: {type(exc).__name__}: {exc}"[:200]
                    if not any(k.startswith("processing error") for k in skipped):
                        traceback.print_exc(file=sys.stderr)
                    skipped[key] += 1
                    faults += 1
                    if faults >= FAULT_RESET_AFTER:  # as the node: start again
                        faults = 0
                        fault_resets += 1
                        pipeline.reset()
                        if est:
                            new_trajectory()
                    continue
                if video is not None:
                    video.add(stamp, draw_tracks(gray, res))
                if res.status == "skipped":
                    skipped[res.reason.split(" (")[0]] += 1
                    continue
                statuses[res.status] += 1
                refound += res.refound
                brightness += res.brightness_change is not None
                from_shift += res.image_shift is not None
                if res.time_reset:
                    time_resets += 1
                    new_trajectory()
                for r in res.revised or ():  # line_delay auto's re-run of the frames so far
                    revised += 1
                    if r.T_world_cam is None:
                        est.pop(r.stamp_ns, None)
                    elif r.stamp_ns in est:
                        est[r.stamp_ns] = r.T_world_cam
                est[stamp] = published[stamp] = res.T_world_cam
                twists.append((stamp, res.twist))
                writer.write(c_odom, stamp, bagio.serialize(_odometry(res)))
                writer.write(c_tf, stamp, bagio.serialize(_tf(res)))
                poses.append((stamp, res.T_world_cam))
                if last_path_ns is None or stamp - last_path_ns >= PATH_PERIOD_NS:
                    write_path(stamp)
                if last_map_ns is None or stamp - last_map_ns >= MAP_PERIOD_NS:
                    write_map(stamp)
                    last_map_ns = stamp
                results_meta.append({"stamp_ns": stamp, "status": res.status,
                                     "inlier_ratio": res.inlier_ratio,
                                     "inliers": res.num_inliers, "tracks": res.num_tracks,
                                     "time_ms": res.time_ms, "reason": res.reason,
                                     "keyframe": res.keyframe,
                                     "tracking": res.tracking})  # fmt: skip
        finally:
            # every trajectory as it ended (with the frames a re-run revised)
            for t in trajectories:
                tum.writelines(tum_line(s, T) + "\n" for s, T in t.items())
            if est and results_meta and results_meta[-1]["stamp_ns"] != last_map_ns:
                write_map(results_meta[-1]["stamp_ns"])  # the final map and keyframes
            finish_path()
            reader.close()
            if video is not None:
                video.close()
            if bar is not None:
                bar.close()
    wall = time.perf_counter() - t_start
    if pipeline is not None:
        pipeline.close()
    frames_in = sum(statuses.values()) + sum(skipped.values())
    keep = [i for i, t in enumerate(trajectories) if t]
    trajectories = [trajectories[i] for i in keep]
    published_trajectories = [published_trajectories[i] for i in keep]
    est = max(trajectories, key=len) if trajectories else {}
    published = max(published_trajectories, key=len) if trajectories else {}
    summary = {
        "bag": str(cfg.bag), "model": cfg.model, "backend": options.backend,
        "motion_prior": options.motion_prior, "readout_direction": options.readout,
        "rotation_only_parallax_px": options.rotation_only_parallax_px,
        # the chain's uncertain-rotation limit in use (deg; 0: never)
        "uncertain_rotation_deg": (pipeline.chain.uncertain_rotation_deg
                                   if pipeline is not None else None),
        "async_mapping": options.window.async_mapping,
        # each keyframe's BA picked up at the first frame this many s after it (0: at once)
        "mapping_lag_s": options.window.mapping_lag_s,
        "angular_acceleration_std": options.window.map.prior_acc_rad_s2,
        "klt_window_px": options.tracker.window_px,  # the pyramid's KLT window (px)
        # tracking at 1/this of the images' resolution (1: full resolution)
        "tracking_decimation": options.tracker.decimation,
        # the tracker's small-window refinement in use (px; 0: off)
        "klt_refine_window_px": (pipeline.tracker.refine_window_px if pipeline is not None
                                 else None),
        "photometric_compensation": options.tracker.photometric_compensation,
        "klt_shift_retry": options.tracker.shift_retry,
        # numeric WindowOptions fields away from their defaults (--window-option)
        "window_options_changed": changed_window_options(options.window),
        # the line delay used at the end (line_delay auto: the estimate, see line_delay_auto)
        "line_delay_s": pipeline.line_delay if pipeline is not None else line_delay,
        "image_topic": cfg.image_topic,
        "camera_file": None if cfg.camera_file is None else str(cfg.camera_file),
        "rectified": cfg.rectified,
        # where K came from: the camera info, a calibration file, or assumed (uncalibrated)
        "intrinsics": "camera_file" if cfg.camera_file is not None else (
            "assumed" if camera is not None and camera.assumed else "camera info"),
        "debug_video": None if video is None else {"path": str(cfg.debug_video),
                                                   "frames": video.frames},
        "frames_in_bag": n_images,
        "frames_in": frames_in, "frames_posed": sum(len(t) for t in trajectories),
        "frames_estimated": statuses.get("posed", 0), "frames_held": statuses.get("held", 0),
        "frames_skipped": sum(skipped.values()), "skipped_reasons": dict(skipped),
        "inlier_ratio_mean": float(np.mean([m["inlier_ratio"] for m in results_meta
                                            if m["status"] == "posed"] or [0.0])),
        "time_ms_per_frame_median": float(np.median([m["time_ms"] for m in results_meta]
                                                    or [0.0])),
        "time_ms_per_frame_p95": float(np.percentile([m["time_ms"] for m in results_meta]
                                                     or [0.0], 95)),
        "wall_time_s": wall, "frames_per_second": frames_in / max(wall, 1e-9),
        "solver_warm_up_s": warm_s,
        # time that jumped back (a looped bag): each reset starts a trajectory; "accuracy" is
        # that of the longest one
        "time_resets": time_resets,
        "fault_resets": fault_resets,
        # the window backend re-found its map (descriptors against the remembered landmarks)
        "map_refound": refound,
        # frames whose brightness changed (auto exposure), tracked in the previous image's grey
        # levels (TrackerOptions.photometric_compensation)
        "frames_brightness_compensated": brightness,
        # frames where KLT alone kept too few tracks and they were found again from the
        # images' shift (TrackerOptions.shift_retry: a turn faster than KLT's reach)
        "frames_tracked_from_shift": from_shift,
        "trajectories": [{"first_stamp_ns": min(t), "frames": len(t)} for t in trajectories],
    }  # fmt: skip
    if auto and pipeline is not None:
        summary["line_delay_auto"] = {
            **pipeline.line_delay_estimate.as_dict(),
            "curve": pipeline.line_delay_estimate.curve,
            "history": pipeline.line_delay_history,
            "bag_line_delay_s": bag_line_delay,
            # the frames before the first estimate processed again with it, and with later
            # estimates away from it ([]: not done; PipelineOptions.line_delay_rerun_*)
            "reruns": pipeline.line_delay_reruns,
            "frames_revised": revised,
            # the estimate refined in a second pass over the first frames
            # (PipelineOptions.line_delay_auto_refine_frames; None: not started)
            "refinement": pipeline.line_delay_auto_refinement,
        }
    if pipeline is not None and pipeline.options.line_delay_refine:
        # the given line delay refined from the frames' turn rates (rsvo_calibrate)
        summary["line_delay_refined"] = {**pipeline.refined_line_delay().as_dict(),
                                         "given_line_delay_s": pipeline.line_delay}
    if gt:
        gt_info = {"topic": gt_topic, "type": topics[gt_topic].msgtype, "poses": len(gt),
                   "resampled": False}
        posed = [m["stamp_ns"] for m in results_meta]
        if posed and sum(s in gt for s in posed) < 0.5 * len(posed):
            # a ground truth of its own rate (motion capture): its poses at the frames'
            # stamps, between two of its own at most GT_MAX_GAP_S apart
            stamps = np.array(sorted(gt))
            gt = interpolate_poses(stamps, np.array([gt[s] for s in stamps]), np.array(posed),
                                   round(GT_MAX_GAP_S * 1e9))  # fmt: skip
            gt_w = {}  # twist at the frames' stamps: not resampled
            gt_info["resampled"] = True
            gt_info["frames_covered"] = len(gt)
        summary["ground_truth"] = gt_info
    if gt and len(est) >= 3:
        _put_accuracy(summary, gt, est)
        if revised and len(published) >= 3:
            # the same trajectory as the odometry was published frame by frame, before the
            # re-run revised its first frames (what a live node's subscribers saw)
            pub: dict = {}
            _put_accuracy(pub, gt, published)
            summary["accuracy_as_published"] = pub.get("accuracy", pub)
    if "accuracy" in summary:
        first = dict(sorted(est.items())[:SCALE_CHECK_FRAMES])
        if len(est) >= 2 * SCALE_CHECK_FRAMES and sum(s in gt for s in first) >= 3:
            # monocular scale drift: the Sim(3) scale of the whole run against its start's
            s0 = accuracy(gt, first)["sim3_scale"]
            summary["accuracy"]["scale_drift"] = {
                "first_frames": SCALE_CHECK_FRAMES, "sim3_scale_first": s0,
                "ratio": summary["accuracy"]["sim3_scale"] / s0}
        for t, row in zip(trajectories, summary["trajectories"], strict=True):
            if len(t) >= 3 and sum(s in gt for s in t) >= 3:
                row["ate_m_rmse"] = accuracy(gt, t)["ate_m"]["rmse"]
    summary["twist"] = twist_summary(twists, gt_w, gt,
                                     summary.get("accuracy", {}).get("sim3_scale"))
    if pipeline is not None and options.backend == "window":
        summary["keyframes"] = keyframe_summary(pipeline.window.keyframe_log, gt_w,
                                                pipeline.window.row0_time())
        kf_poses = dict(pipeline.keyframe_poses())
        with open(cfg.output / "keyframes.tum", "w") as f:
            f.writelines(tum_line(s, T) + "\n" for s, T in sorted(kf_poses.items()))
        if gt and sum(s in gt for s in kf_poses) >= 3:
            # the corrected keyframe trajectory (the window's last word on each keyframe),
            # beside the continuous published odometry above
            _put_accuracy(summary["keyframes"], gt, kf_poses)
    summary["frames"] = results_meta
    with open(cfg.output / "summary.json", "w") as f:
        json.dump(summary, f, indent=1)
    plot_trajectory(cfg.output / "trajectory.png", est, gt, results_meta, cfg.model)
    if not est:
        raise ReplayError(f"no frame of {cfg.image_topic} could be used "
                          f"({dict(skipped) or 'no images'}); see {cfg.output / 'summary.json'}")
    return summary


FIRST_PASS_DIR = "first_pass"  # --two-pass: the online (first) pass's outputs, under --output


def replay_two_pass(cfg: ReplayConfig) -> dict:
    """``line_delay auto`` offline, in two passes: the first replays the bag as the live node
    runs (estimating the line delay while it goes, without re-running the first frames; its
    outputs in ``OUTPUT/first_pass``), the
    second replays it again with the first pass's last estimate fixed. Online, the frames before
    the first estimate (30-90) are posed with the nominal readout, and a wrong one can shrink
    or stretch the map's scale there for good; the second pass poses them with the estimate.
    Without a usable estimate (too little motion, too short a bag) the first pass is the
    result, moved up into ``OUTPUT``. Returns the second pass's summary with ``two_pass``
    (the first pass's line delay used at its end and its accuracy) and the first pass's
    ``line_delay_auto``."""
    if not cfg.options.line_delay_auto:
        raise ValueError("two passes need line_delay auto (PipelineOptions.line_delay_auto)")
    if (cfg.output / "odometry").exists() and not cfg.overwrite:
        raise FileExistsError(f"{cfg.output} already holds a replay; pass --overwrite")
    second_options = copy.deepcopy(cfg.options)  # replay() sets the tracker's options in place
    first_options = copy.deepcopy(cfg.options)
    # as the node: no re-runs of the first frames, which would move the estimate the second
    # pass takes (on the README's table 30 of 33 bags within 10 % of the true line delay's ATE
    # with them, 33 without) and cost time for frames the second pass replays anyway
    first_options.line_delay_rerun_max_frames = 0
    first_dir = cfg.output / FIRST_PASS_DIR
    first = replay(dataclasses.replace(cfg, output=first_dir, overwrite=True,
                                       options=first_options))
    estimate = first["line_delay_auto"]
    two_pass = {"first_pass_dir": FIRST_PASS_DIR, "first_pass_line_delay_s": first["line_delay_s"],
                "first_pass_wall_time_s": first["wall_time_s"],
                "first_pass_ate_m": (first["accuracy"]["ate_m"]["rmse"]
                                     if "accuracy" in first else None)}
    if estimate["status"] not in ("estimated", "converged", "refined") \
            or estimate["line_delay_s"] is None:
        for item in first_dir.iterdir():  # the first pass is the result
            target = cfg.output / item.name
            if target.is_dir():
                shutil.rmtree(target)
            item.replace(target)
        first_dir.rmdir()
        two_pass.update(second_pass=False, first_pass_dir=None,
                        reason=f"no estimate to replay with: {estimate['status']} "
                               f"({estimate.get('reason', '')})")
        first["two_pass"] = two_pass
        with open(cfg.output / "summary.json", "w") as f:
            json.dump(first, f, indent=1)
        return first
    second_options.line_delay_auto = False
    summary = replay(dataclasses.replace(cfg, line_delay=float(estimate["line_delay_s"]),
                                         options=second_options, overwrite=True))
    two_pass["second_pass"] = True
    summary["two_pass"] = two_pass
    summary["line_delay_auto"] = estimate
    with open(cfg.output / "summary.json", "w") as f:
        json.dump(summary, f, indent=1)
    return summary


class DebugVideo:
    """An MP4 (OpenCV's mp4v) of drawn frames, its rate from the first two stamps (the
    first frame is held until the second comes; a lone frame is written at 30 frames/s)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.frames = 0
        self._writer = None
        self._first: tuple[int, np.ndarray] | None = None

    def _open(self, fps: float, image: np.ndarray) -> None:
        import cv2

        self._writer = cv2.VideoWriter(str(self.path), cv2.VideoWriter_fourcc(*"mp4v"),
                                       float(np.clip(fps, 1.0, 240.0)),
                                       (image.shape[1], image.shape[0]))  # fmt: skip
        if not self._writer.isOpened():
            raise ReplayError(f"cannot write the debug video {self.path} (OpenCV's mp4v)")

    def add(self, stamp_ns: int, image: np.ndarray) -> None:
        if self._writer is None and self._first is None:
            self._first = (stamp_ns, image)
            return
        if self._writer is None:
            dt = (stamp_ns - self._first[0]) * 1e-9
            self._open(1.0 / dt if dt > 0 else 30.0, self._first[1])
            self._write(self._first[1])
        self._write(image)

    def _write(self, image: np.ndarray) -> None:
        h, w = image.shape[:2]
        if self.frames and (w, h) != self._size:
            return  # the camera changed size mid-bag: the video keeps its first size
        self._size = (w, h)
        self._writer.write(image)
        self.frames += 1

    def close(self) -> None:
        if self._writer is None and self._first is not None:
            self._open(30.0, self._first[1])
            self._write(self._first[1])
        if self._writer is not None:
            self._writer.release()


GROUND_TRUTH_TYPES = (bagio.ODOMETRY_TYPE, "geometry_msgs/msg/PoseStamped",
                      "geometry_msgs/msg/PoseWithCovarianceStamped",
                      "geometry_msgs/msg/TransformStamped")
GT_MAX_GAP_S = 0.2  # a resampled ground truth interpolates across gaps up to this


def ground_truth_of(msg, msgtype: str) -> tuple[np.ndarray, np.ndarray | None]:
    """``T_world_camera`` (4, 4) of a ground-truth message (one of ``GROUND_TRUTH_TYPES``) and
    its angular velocity (nav_msgs/Odometry's twist; None for the others)."""
    T = np.eye(4)
    if msgtype == "geometry_msgs/msg/TransformStamped":
        tr = msg.transform.translation
        T[:3, :3], T[:3, 3] = bagio.rotation_of(msg.transform.rotation), [tr.x, tr.y, tr.z]
        return T, None
    pose = msg.pose if msgtype == "geometry_msgs/msg/PoseStamped" else msg.pose.pose
    T[:3, :3], T[:3, 3] = bagio.pose_of(pose)
    if msgtype != bagio.ODOMETRY_TYPE:
        return T, None
    tw = msg.twist.twist
    return T, np.array([tw.angular.x, tw.angular.y, tw.angular.z])


def keyframe_summary(log: dict, gt_w: dict[int, np.ndarray], row0_time: float = 0.0) -> dict:
    """The window backend's keyframes (their final, window-refined states): how many, their
    row-0 velocities (``velocities``: stamp, ``w`` rad/s and ``v`` map units/s in the row-0
    camera frame, as CONTRACTS.md reports a frame's), and where the bag's ground truth has
    angular velocities, the median error of theirs relative to the true ``|w|`` (both at the
    row-0 time, ``row0_time`` s from the reference row)."""
    out = {"count": len(log)}
    rows, rel = [], []
    for s, st in sorted(log.items()):
        w, v = st.row0_velocities(row0_time)
        if not (np.isfinite(w).all() and np.isfinite(v).all()):
            continue
        rows.append({"stamp_ns": int(s), "w": [float(x) for x in w],
                     "v": [float(x) for x in v]})
        if s in gt_w and np.linalg.norm(gt_w[s]) > 1e-6:
            rel.append(float(np.linalg.norm(w - gt_w[s]) / np.linalg.norm(gt_w[s])))
    out["velocities"] = rows
    if rel:
        out["w_rel_error_median"] = float(np.median(rel))
        out["w_compared"] = len(rel)
    return out


def twist_summary(twists: list[tuple[int, Twist]], gt_w: dict[int, np.ndarray],
                  gt: dict[int, np.ndarray] | None = None, scale: float | None = None) -> dict:
    """How many frames' odometry carried a twist (``known``: a finite covariance), and its
    errors where the bag has ground truth. Against the true mean over the same interval (the
    ground truth's poses at both stamps, ``gt``): angular (deg/s, median) and, with the
    trajectory's Sim(3) ``scale``, linear (relative to the median true speed); this is what
    the twist estimates. Against the instantaneous row-0 angular velocity (``gt_w``, the
    synthetic bags' twist): what a filter taking it as the rate at the stamp sees (shake faster
    than the frame rate makes the two differ). ``angular_within_2_sigma``: the share of angular
    components within two standard deviations of the published covariance, against the
    interval's truth where there is one (about 95 % where the covariance is honest and the
    errors Gaussian)."""
    known = [(s, t) for s, t in twists if t.known]  # (stamp, twist); a looped bag repeats stamps
    out = {"frames": len(twists), "known": len(known)}
    gt = gt or {}
    matched = [(s, t) for s, t in known if s in gt and t.since_ns in gt]
    sigma_err = None
    if matched:
        truth = [body_twist(gt[t.since_ns], gt[s], (s - t.since_ns) * 1e-9) + (t,)
                 for s, t in matched]  # (true linear, true angular, published)
        err_w = np.array([t.angular - w for _, w, t in truth])
        out["interval_compared"] = len(matched)
        out["angular_error_vs_interval_deg_s_median"] = float(
            np.degrees(np.median(np.linalg.norm(err_w, axis=1))))
        out["angular_interval_deg_s_median"] = float(
            np.degrees(np.median([np.linalg.norm(w) for _, w, _ in truth])))
        sigma_err = (err_w, np.array([t.covariance.diagonal()[3:] for _, _, t in truth]))
        speed = np.median([np.linalg.norm(v) for v, _, _ in truth])
        if scale is not None and np.isfinite(scale) and speed > 0:
            err_v = [np.linalg.norm(scale * t.linear - v) for v, _, t in truth]
            out["linear_rel_error_vs_interval_median"] = float(np.median(err_v) / speed)
    inst = [(t, gt_w[s]) for s, t in known if s in gt_w]
    if inst:
        err = np.array([t.angular - w for t, w in inst])
        true = np.median([np.linalg.norm(w) for _, w in inst])
        med = float(np.median(np.linalg.norm(err, axis=1)))
        out["angular_compared"] = len(inst)
        out["angular_error_deg_s_median"] = float(np.degrees(med))
        out["angular_true_deg_s_median"] = float(np.degrees(true))
        out["angular_rel_error_median"] = med / true if true > 0 else float("nan")
        if sigma_err is None:
            sigma_err = (err, np.array([t.covariance.diagonal()[3:] for t, _ in inst]))
    if sigma_err is not None:
        out["angular_within_2_sigma"] = float(np.mean(np.abs(sigma_err[0])
                                                      <= 2.0 * np.sqrt(sigma_err[1])))
    return out


def _evo_traj(poses: dict[int, np.ndarray]):
    from evo.core.trajectory import PoseTrajectory3D

    stamps = np.array(sorted(poses))
    return PoseTrajectory3D(poses_se3=[poses[s] for s in stamps], timestamps=stamps / 1e9)


def sim3_aligned_positions(gt: dict[int, np.ndarray],
                           est: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Positions (M, 3) of the ground truth and of the estimate after evo's Sim(3) (Umeyama)
    alignment, on the stamps they share."""
    from evo.core import sync

    ref, traj = sync.associate_trajectories(_evo_traj(gt), _evo_traj(est), max_diff=1e-3)
    traj.align(ref, correct_scale=True)
    return ref.positions_xyz, traj.positions_xyz


def _put_accuracy(out: dict, gt: dict[int, np.ndarray], est: dict[int, np.ndarray]) -> None:
    """``out["accuracy"]``, or ``out["accuracy_error"]`` where evo refuses the trajectory (one
    that diverged to 1e16 m is not a valid SE(3) path for it): the summary is still written."""
    try:
        out["accuracy"] = accuracy(gt, est)
    except Exception as exc:  # noqa: BLE001 - any evo failure is reported, not raised
        out["accuracy_error"] = f"{type(exc).__name__}: {exc}"


def accuracy(gt: dict[int, np.ndarray], est: dict[int, np.ndarray]) -> dict:
    """ATE (after Sim(3) alignment) and RPE (one frame, aligned) with evo."""
    import copy

    from evo.core import metrics, sync

    ref, traj = sync.associate_trajectories(_evo_traj(gt), _evo_traj(est), max_diff=1e-3)
    aligned = copy.deepcopy(traj)
    _, _, s = aligned.align(ref, correct_scale=True)
    out = {"matched_poses": int(ref.num_poses), "sim3_scale": float(s)}
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, aligned))
    out["ate_m"] = {k: float(v) for k, v in ape.get_all_statistics().items()}
    for name, rel in (("rpe_trans_m", metrics.PoseRelation.translation_part),
                      ("rpe_rot_deg", metrics.PoseRelation.rotation_angle_deg)):
        rpe = metrics.RPE(rel, delta=1, delta_unit=metrics.Unit.frames, all_pairs=False)
        rpe.process_data((ref, aligned))
        out[name] = {k: float(v) for k, v in rpe.get_all_statistics().items()}
    rate = scale_rate(ref.timestamps, ref.positions_xyz, traj.positions_xyz)
    if rate is not None:
        out["scale_rate"] = rate
    return out


SCALE_WINDOW_S = 0.5  # the displacements scale_rate compares
SCALE_MIN_STEP_M = 0.01  # windows in which the truth moved less are left out (a stop)


def scale_rate(stamps_s: np.ndarray, gt_xyz: np.ndarray, est_xyz: np.ndarray) -> dict | None:
    """How fast the estimate's scale changes (``accuracy.scale_drift`` compares the whole
    run's Sim(3) scale with its start's): over windows of ``SCALE_WINDOW_S`` (one
    starting every sixth of that), the ratio of the estimated to the true displacement, fitted
    as ``c exp(b t)``; ``percent_per_s`` is ``100 (exp(b) - 1)`` (negative: the trajectory
    shrinks as it goes). None with fewer than three windows (a short or stopped run)."""
    t = np.asarray(stamps_s, float)
    starts = np.arange(t[0], t[-1] - SCALE_WINDOW_S, SCALE_WINDOW_S / 6) if len(t) > 1 else []
    ts, logs = [], []
    for t0 in starts:
        i = int(np.searchsorted(t, t0))
        j = int(np.searchsorted(t, t0 + SCALE_WINDOW_S))
        if j >= len(t) or j <= i:
            continue
        g = float(np.linalg.norm(gt_xyz[j] - gt_xyz[i]))
        e = float(np.linalg.norm(est_xyz[j] - est_xyz[i]))
        if g < SCALE_MIN_STEP_M or not e > 0:
            continue
        ts.append(0.5 * (t[i] + t[j]))
        logs.append(np.log(e / g))
    if len(ts) < 3:
        return None
    b = float(np.polyfit(ts, logs, 1)[0])
    return {"percent_per_s": 100.0 * float(np.expm1(b)), "windows": len(ts)}


def plot_trajectory(path: Path, est: dict, gt: dict, frames: list, model: str) -> None:
    """Top view (x-z: the world's y points down) of the estimate, Sim(3)-aligned to the ground
    truth when there is one, and the inlier ratio per frame (like the paper's Fig. 8)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(12, 5), gridspec_kw={"width_ratios": [1, 1.3]})
    if est:
        xyz = np.array([est[s][:3, 3] for s in sorted(est)])
        label = f"estimate ({model})"
        if gt and len(est) >= 3:
            g, xyz = sim3_aligned_positions(gt, est)
            ax.plot(g[:, 0], g[:, 2], "k-", lw=2, label="ground truth")
            label += ", Sim(3)-aligned"
        ax.plot(xyz[:, 0], xyz[:, 2], "-", color="tab:red", lw=1.5, label=label)
        ax.plot(xyz[0, 0], xyz[0, 2], "o", color="tab:red")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    if est:
        ax.legend(loc="best", fontsize=8)
    else:
        ax.text(0.5, 0.5, "no frame posed\n(summary.json: skipped_reasons)", ha="center",
                va="center", transform=ax.transAxes)
    ax.set_title("trajectory, top view")
    if frames:
        t0 = frames[0]["stamp_ns"]
        tt = [(m["stamp_ns"] - t0) / 1e9 for m in frames if m["status"] == "posed"]
        ir = [100 * m["inlier_ratio"] for m in frames if m["status"] == "posed"]
        ax2.plot(tt, ir, ".-", color="k", ms=3)
        held = [(m["stamp_ns"] - t0) / 1e9 for m in frames if m["status"] == "held"]
        if held:
            ax2.plot(held, [0] * len(held), "x", color="tab:red", label="held (no estimate)")
            ax2.legend(loc="lower right", fontsize=8)
    ax2.set_ylim(0, 105)
    ax2.set_xlabel("time (s)")
    ax2.set_ylabel("inlier ratio (%)")
    ax2.grid(True, alpha=0.3)
    ax2.set_title("inliers per frame pair")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _describe_estimate(e: dict) -> str:
    if e["line_delay_s"] is None:
        return f"{e['status']} ({e['reason']})"
    return (f"{e['line_delay_s'] * 1e6:.2f} +- {e['std_s'] * 1e6:.2f} us/row (readout "
            f"{e['readout_fraction']:.3f} +- {e['std_fraction']:.3f} frame intervals; "
            f"{e['status']}, {e['windows']} windows)")


def _line_delay_arg(text: str):
    if text == "auto":
        return "auto"
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"line delay must be seconds per row or auto, got {text!r}") from None


def window_option_arg(text: str) -> tuple[str, float]:
    """``NAME=VALUE`` of a numeric :class:`WindowOptions` field (argparse type)."""
    name, _, value = text.partition("=")
    if name not in NUMERIC_WINDOW_OPTIONS:
        known = ", ".join(sorted(NUMERIC_WINDOW_OPTIONS))
        raise argparse.ArgumentTypeError(f"{name!r} is not a numeric WindowOptions field "
                                         f"({known})")
    try:
        number = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: the value is not a number") from None
    if not np.isfinite(number):
        raise argparse.ArgumentTypeError(f"{text!r}: the value must be finite")
    if number < 0:  # every numeric field is a count, a threshold, a share or a std
        raise argparse.ArgumentTypeError(f"{text!r}: the value must be >= 0")
    if NUMERIC_WINDOW_OPTIONS[name] is int and number != int(number):
        raise argparse.ArgumentTypeError(f"{text!r}: {name} takes a whole number")
    return name, number


def changed_window_options(window: WindowOptions) -> dict[str, float]:
    """The numeric :class:`WindowOptions` fields of ``window`` that differ from the defaults."""
    default = WindowOptions()
    return {name: getattr(window, name) for name in sorted(NUMERIC_WINDOW_OPTIONS)
            if getattr(window, name) != getattr(default, name)}


def set_window_options(options: PipelineOptions, values: list[tuple[str, float]]) -> None:
    """Set numeric :class:`WindowOptions` fields (from :func:`window_option_arg`)."""
    for name, value in values:
        setattr(options.window, name, NUMERIC_WINDOW_OPTIONS[name](value))


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="rsvo_replay",
                                description="Run rsvo_ros's odometry pipeline over a rosbag2 "
                                            "or a ROS 1 bag.")
    p.add_argument("bag", type=Path, help="rosbag2 directory (sqlite3 or mcap) or ROS 1 .bag file")
    p.add_argument("--output", "-o", type=Path, required=True, help="output directory")
    p.add_argument("--model", choices=MODELS, default="rs", help="relative pose model (rs)")
    p.add_argument("--image-topic", default=bagio.IMAGE_TOPIC,
                   help=f"sensor_msgs/Image or CompressedImage (JPEG, PNG: image_transport's "
                        f"compressed, e.g. {bagio.IMAGE_TOPIC}/compressed) topic "
                        f"(default {bagio.IMAGE_TOPIC})")
    p.add_argument("--camera-info-topic", default=bagio.CAMERA_INFO_TOPIC)
    p.add_argument("--camera-file", type=Path, default=None, metavar="YAML",
                   help="intrinsics from a calibration file instead of the camera info topic: "
                        "ROS camera calibration YAML (camera_calibration, camera_info_manager) "
                        "or Kalibr camchain YAML (pinhole; radtan, equidistant or no "
                        "distortion)")
    p.add_argument("--rectified", action="store_true",
                   help="the images are rectified (image_proc's image_rect): the intrinsics are "
                        "CameraInfo's projection P (with --camera-file: the ROS file's "
                        "projection_matrix), and no lens distortion is removed")
    p.add_argument("--uncalibrated-focal-factor", type=float, default=0.0, metavar="F",
                   help="a camera info without calibration (K all zero, as drivers publish "
                        "without a calibration file): assume a pinhole camera of focal length "
                        "F image widths (0.7-1.2 for most phones, webcams and dash cams), "
                        "principal point at the centre, no lens distortion (default 0: such a "
                        "camera info is refused, each of its images skipped)")
    p.add_argument("--debug-video", type=Path, default=None, metavar="MP4",
                   help="also write every processed frame with its tracks drawn (inliers "
                        "green, outliers red, tracks with no map point grey), as the node's "
                        "debug image, into this MP4")
    p.add_argument("--camera-entry", default=None, metavar="CAM",
                   help="with a Kalibr camchain of several cameras: the entry (default cam0)")
    p.add_argument("--ground-truth-topic", default=bagio.GROUND_TRUTH_TOPIC)
    p.add_argument("--line-delay", type=_line_delay_arg, default=None, metavar="S|auto",
                   help=f"seconds per image row (default: the bag's {bagio.LINE_DELAY_KEY}); "
                        "auto: estimated from the video (RS model, window backend; the bag's "
                        "value is then only reported)")
    p.add_argument("--two-pass", action="store_true",
                   help="with --line-delay auto: replay the bag twice, first as the live node "
                        "does (estimating the line delay; outputs in OUTPUT/first_pass), then "
                        "with that estimate fixed, so that the frames before the first "
                        "estimate are posed with it too (offline only)")
    p.add_argument("--no-line-delay-rerun", action="store_true",
                   help="with --line-delay auto: go on from the first estimate as the live "
                        "node does, instead of processing the frames before it again with it "
                        "(the default here: at most PipelineOptions.line_delay_rerun_max_frames "
                        "frames, again with a later estimate over 10 %% away, at most "
                        "line_delay_reruns times; trajectory.tum and the accuracy get their new "
                        "poses)")
    p.add_argument("--line-delay-refine-frames", type=int,
                   default=PipelineOptions.line_delay_auto_refine_frames, metavar="N",
                   help="with --line-delay auto: after N frames, run them again at the "
                        "estimate with the map's shear removed and take the refined line delay "
                        "(as rsvo_calibrate's second pass, over the first N frames; a pause of "
                        "a few seconds at that frame); 0: keep the calibrator's estimate "
                        "(default 150)")
    p.add_argument("--max-features", type=int, default=500, help="tracked corners (500)")
    p.add_argument("--max-frames", type=int, default=None, metavar="N",
                   help="stop after the first N images (default: the whole bag)")
    p.add_argument("--readout-direction", choices=READOUTS, default="down",
                   help="which way the rolling shutter reads the images as they are in the bag: "
                        "down (rows top to bottom, default), up (an image turned by 180 "
                        "degrees: a camera mounted upside down), right / left (columns: an "
                        "image turned by 90 degrees, a phone in portrait); the line delay is "
                        "then per line read")
    p.add_argument("--backend", choices=BACKENDS, default="window",
                   help="window: keyframes, a local map and the RS window bundle adjustment "
                        "(default); pairwise: the paper's chain of frame pairs")
    p.add_argument("--no-motion-prior", action="store_true",
                   help="RS: estimate each frame pair on its own (the paper's setting) instead "
                        "of centring the velocity prior on the stream's constant velocity and "
                        "starting from the previous pair's motion")
    p.add_argument("--async-mapping", action="store_true",
                   help="window backend: map keyframes on a background thread as the live node "
                        "does (default: inline, deterministic)")
    p.add_argument("--mapping-lag", type=float, default=0.0, metavar="S",
                   help="window backend: pick up each keyframe's bundle adjustment at the "
                        "first frame S seconds or more after the keyframe, as the live node "
                        "with mapping_lag_s:=S does (inline, the BA held back: the node's "
                        "odometry whatever its speed; with --async-mapping on the mapping "
                        "thread); 0 (default): at once")
    p.add_argument("--angular-acceleration", type=float, default=ACCELERATION_STD_RAD_S2,
                   metavar="STD",
                   help="window backend, RS: std (rad/s^2) of the prior on each frame's angular "
                        f"acceleration during its readout (default {ACCELERATION_STD_RAD_S2:g}; "
                        "0: the paper's constant velocity within a frame)")
    p.add_argument("--rotation-only-parallax", type=float, default=ROTATION_ONLY_PARALLAX_PX,
                   metavar="PX",
                   help="pairwise chain: a pair whose tracks a turning camera explains to "
                        "within PX (median, at 1000 px focal) is posed by that rotation "
                        f"(default {ROTATION_ONLY_PARALLAX_PX:g}; 0: never)")
    p.add_argument("--uncertain-rotation", type=float, default=-1.0, metavar="DEG",
                   help="RS pairwise chain: a pair whose estimated rotation std is over DEG "
                        "takes a turning camera's rotation at any parallax (-1, default: "
                        f"{BOOTSTRAP_UNCERTAIN_ROTATION_DEG:g} for the window backend's "
                        f"bootstrap, {UNCERTAIN_PAIR_ROTATION_DEG:g} for the pairwise one; "
                        "0: never)")
    p.add_argument("--window-option", type=window_option_arg, action="append", default=[],
                   metavar="NAME=VALUE",
                   help="window backend: set a numeric WindowOptions field, e.g. "
                        "init_max_rotation_std_deg=0 (repeatable; for A/B runs)")
    p.add_argument("--klt-window", type=int, default=DEFAULT_WINDOW_PX, metavar="PX",
                   help=f"KLT: the pyramid's window (default {DEFAULT_WINDOW_PX}; "
                        f"{MIN_WINDOW_PX}-{MAX_WINDOW_PX}): its time grows with its area (17: "
                        "0.45-0.63x the time of 21; README)")
    p.add_argument("--decimation", type=int, default=1, metavar="D",
                   help=f"track at 1/D of the images' resolution (1-{MAX_DECIMATION}; default "
                        "1: full resolution; the tracker's windows and distances are then in "
                        "the reduced image's pixels): for large images on a slow machine "
                        "(README, \"Tracking at a reduced resolution\")")
    p.add_argument("--klt-refine-window", type=int, default=-1, metavar="PX",
                   help="KLT: polish each track at full resolution with a PX window after the "
                        "pyramid's (-1, default: 11 for the window backend, off for "
                        f"the pairwise one; 0: off; else 3-{MAX_REFINE_WINDOW_PX})")
    p.add_argument("--no-photometric-compensation", action="store_true",
                   help="KLT: do not map an image whose brightness changed (auto exposure) into "
                        "the previous image's grey levels before tracking")
    p.add_argument("--no-klt-shift-retry", action="store_true",
                   help=f"KLT: where it keeps less than {100 * RETRY_BELOW_SHARE:.0f} %% of the "
                        "tracks, do not track them again from the images' shift (phase "
                        "correlation)")
    p.add_argument("--overwrite", action="store_true", help="replace an earlier replay")
    p.add_argument("--no-progress", action="store_true")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.max_features < 20:
        print("rsvo_replay: --max-features must be at least 20", file=sys.stderr)
        return EXIT_USAGE
    if args.max_frames is not None and args.max_frames < 1:
        print("rsvo_replay: --max-frames must be at least 1", file=sys.stderr)
        return EXIT_USAGE
    if not (np.isfinite(args.rotation_only_parallax) and args.rotation_only_parallax >= 0):
        print("rsvo_replay: --rotation-only-parallax must be a finite number of px >= 0",
              file=sys.stderr)
        return EXIT_USAGE
    if not (np.isfinite(args.uncalibrated_focal_factor)
            and 0 <= args.uncalibrated_focal_factor <= 10):
        print("rsvo_replay: --uncalibrated-focal-factor must be in [0, 10] image widths",
              file=sys.stderr)
        return EXIT_USAGE
    if not (np.isfinite(args.angular_acceleration) and args.angular_acceleration >= 0):
        print("rsvo_replay: --angular-acceleration must be a std >= 0 (rad/s^2)",
              file=sys.stderr)
        return EXIT_USAGE
    try:
        refine_window = refine_window_or_auto(args.klt_refine_window, "--klt-refine-window")
        check_window(args.klt_window, "--klt-window")
        check_decimation(args.decimation, "--decimation")
        uncertain = uncertain_rotation_or_auto(args.uncertain_rotation, "--uncertain-rotation")
    except ValueError as exc:
        print(f"rsvo_replay: {exc}", file=sys.stderr)
        return EXIT_USAGE
    auto = args.line_delay == "auto"
    if auto and (args.model != "rs" or args.backend != "window"):
        print("rsvo_replay: --line-delay auto needs --model rs and --backend window",
              file=sys.stderr)
        return EXIT_USAGE
    if args.two_pass and not auto:
        print("rsvo_replay: --two-pass needs --line-delay auto", file=sys.stderr)
        return EXIT_USAGE
    if args.no_line_delay_rerun and not auto:
        print("rsvo_replay: --no-line-delay-rerun needs --line-delay auto", file=sys.stderr)
        return EXIT_USAGE
    if args.line_delay_refine_frames != PipelineOptions.line_delay_auto_refine_frames \
            and not auto:
        print("rsvo_replay: --line-delay-refine-frames needs --line-delay auto", file=sys.stderr)
        return EXIT_USAGE
    if not 0 <= args.line_delay_refine_frames <= 100_000:
        print("rsvo_replay: --line-delay-refine-frames must be in [0, 100000] (0: off)",
              file=sys.stderr)
        return EXIT_USAGE
    if 0 < args.line_delay_refine_frames < 30:
        print("rsvo_replay: --line-delay-refine-frames below 30 gives too few blocks of frames "
              "to refine from; use 0 (off) or at least 30", file=sys.stderr)
        return EXIT_USAGE
    if not 0 <= args.mapping_lag <= MAX_MAPPING_LAG_S:
        print(f"rsvo_replay: --mapping-lag must be in [0, {MAX_MAPPING_LAG_S:g}] s, got "
              f"{args.mapping_lag}", file=sys.stderr)
        return EXIT_USAGE
    if args.mapping_lag and args.backend != "window":
        print("rsvo_replay: --mapping-lag needs --backend window", file=sys.stderr)
        return EXIT_USAGE
    options = PipelineOptions(motion_prior=not args.no_motion_prior, backend=args.backend,
                              line_delay_auto=auto, readout=args.readout_direction,
                              line_delay_auto_refine_frames=args.line_delay_refine_frames)
    if args.no_line_delay_rerun:
        options.line_delay_rerun_max_frames = 0
    options.window.async_mapping = args.async_mapping
    options.window.mapping_lag_s = args.mapping_lag
    options.window.map.prior_acc_rad_s2 = args.angular_acceleration
    options.rotation_only_parallax_px = args.rotation_only_parallax
    options.uncertain_rotation_deg = uncertain
    options.tracker.photometric_compensation = not args.no_photometric_compensation
    options.tracker.shift_retry = not args.no_klt_shift_retry
    options.tracker.window_px = args.klt_window
    options.tracker.decimation = args.decimation
    set_window_options(options, args.window_option)
    cfg = ReplayConfig(args.bag, args.output, args.model, args.image_topic,
                       args.camera_info_topic, args.ground_truth_topic,
                       None if auto else args.line_delay,
                       args.max_features, args.overwrite, not args.no_progress,
                       options, args.max_frames, refine_window, args.camera_file,
                       args.camera_entry, args.rectified, args.debug_video,
                       args.uncalibrated_focal_factor)  # fmt: skip
    try:
        s = replay_two_pass(cfg) if args.two_pass else replay(cfg)
    except (ValueError, FileExistsError) as exc:
        print(f"rsvo_replay: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except ReplayError as exc:
        print(f"rsvo_replay: {exc}", file=sys.stderr)
        return EXIT_BAD_BAG
    acc = s.get("accuracy")
    line = (f"rsvo_replay: {s['frames_posed']}/{s['frames_in']} frames posed "
            f"({s['frames_estimated']} estimated, {s['frames_held']} held, "
            f"{s['frames_skipped']} skipped) at {s['frames_per_second']:.1f} frames/s")
    if acc:
        line += f"; ATE {acc['ate_m']['rmse']:.3f} m RMSE after Sim(3)"
        if "scale_rate" in acc:
            line += f", scale {acc['scale_rate']['percent_per_s']:+.1f} % per s"
    print(line)
    events = []
    if s.get("fault_resets"):
        events.append(f"{FAULT_RESET_AFTER} frames in a row failed (a fault of the package, "
                      f"summary.json skipped_reasons): the odometry reset "
                      f"{s['fault_resets']} time(s)")
    if s.get("time_resets"):
        events.append(f"time went back {s['time_resets']} time(s): the odometry reset and "
                      f"started {len(s['trajectories'])} trajectories")
    if s.get("map_refound"):
        events.append(f"the map was lost and re-found {s['map_refound']} time(s)")
    if s.get("frames_brightness_compensated"):
        events.append(f"the brightness changed on {s['frames_brightness_compensated']} "
                      "frame(s) (auto exposure): tracked in the previous image's grey levels")
    if s.get("frames_tracked_from_shift"):
        events.append(f"KLT lost its tracks on {s['frames_tracked_from_shift']} frame(s) (a "
                      "turn past its reach): tracked again from the images' shift")
    if events:
        print("rsvo_replay: " + "; ".join(events))
    if "line_delay_auto" in s:
        print(f"rsvo_replay: line delay auto: {_describe_estimate(s['line_delay_auto'])}")
        ref = s["line_delay_auto"].get("refinement")
        if ref is not None and ref["status"] == "refined":
            print(f"rsvo_replay: refined after {args.line_delay_refine_frames} frames from "
                  f"{ref['first_line_delay_s'] * 1e6:.2f} us/row (a second pass over them, "
                  f"{ref['time_ms'] / 1e3:.1f} s; --line-delay-refine-frames 0: without)")
        elif ref is not None:
            print(f"rsvo_replay: the estimate was not refined: {ref['reason']}")
    firsts = [h["frames"] for h in s.get("line_delay_auto", {}).get("history", [])
              if h["line_delay_s"] is not None]
    reruns = s.get("line_delay_auto", {}).get("reruns")
    if reruns and not args.two_pass:
        done = ", ".join(f"{r['frames']} frames with {r['line_delay_s'] * 1e6:.2f} us/row in "
                         f"{r['time_ms'] / 1e3:.1f} s" for r in reruns)
        pub = s.get("accuracy_as_published", {}).get("ate_m")
        pub = f", ATE {pub['rmse']:.3f} m" if pub else ""
        print(f"rsvo_replay: the frames before the first estimate were processed again with it "
              f"({done}) and revised in trajectory.tum and the accuracy; the odometry bag and "
              f"accuracy_as_published{pub} have them as a live node published them; "
              "--two-pass replays the bag with the final estimate")
    elif firsts and not args.two_pass:
        print(f"rsvo_replay: the {firsts[0]} frames before the first estimate ran with the "
              "starting line delay; --two-pass replays the bag with the estimate")
    if "two_pass" in s:
        tp = s["two_pass"]
        first_ate = ("" if tp["first_pass_ate_m"] is None
                     else f", ATE {tp['first_pass_ate_m']:.3f} m")
        if tp["second_pass"]:
            print(f"rsvo_replay: two passes: the figures above are the second pass's, with "
                  f"{s['line_delay_s'] * 1e6:.2f} us/row fixed; the first (online) pass in "
                  f"{args.output / tp['first_pass_dir']}{first_ate}")
        else:
            print(f"rsvo_replay: two passes: no second pass, {tp['reason']}; the figures "
                  "above are the first (online) pass's")
    print(f"rsvo_replay: wrote {args.output}/trajectory.tum, odometry/, summary.json, "
          "trajectory.png")
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
