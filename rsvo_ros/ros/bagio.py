"""ROS 2 messages and rosbag2 files with ``rosbags`` (no rclpy): the bag format of CONTRACTS.md.

Topics: ``/camera/image_raw`` (sensor_msgs/Image, stamp = row-0 time; written compressed:
``/camera/image_raw/compressed``, sensor_msgs/CompressedImage), ``/camera/camera_info``
(sensor_msgs/CameraInfo, same stamps), optional ``/ground_truth/odom`` (nav_msgs/Odometry,
``T_world_camera`` at the image stamps; its twist holds the frame's RS velocities ``(v, w)`` in
the row-0 camera frame). The line delay is bag metadata custom data ``rsvo.line_delay``.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from rsvo_ros.core.lens import LensModel
from rsvo_ros.ros.convert import pose_components

IMAGE_TOPIC = "/camera/image_raw"
CAMERA_INFO_TOPIC = "/camera/camera_info"
GROUND_TRUTH_TOPIC = "/ground_truth/odom"
CAMERA_FRAME = "camera_optical_frame"
WORLD_FRAME = "world"
LINE_DELAY_KEY = "rsvo.line_delay"
STORAGES = ("sqlite3", "mcap")
IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE_TYPE = "sensor_msgs/msg/CompressedImage"  # image_transport's compressed
IMAGE_TYPES = (IMAGE_TYPE, COMPRESSED_IMAGE_TYPE)
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
PATH_TYPE = "nav_msgs/msg/Path"


@lru_cache(maxsize=1)
def typestore():
    """The ROS 2 Jazzy message types of ``rosbags``."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def _t(name: str):
    return typestore().types[name]


def stamp_msg(stamp_ns: int):
    """builtin_interfaces/Time from integer nanoseconds."""
    return _t("builtin_interfaces/msg/Time")(sec=int(stamp_ns // 1_000_000_000),
                                             nanosec=int(stamp_ns % 1_000_000_000))  # fmt: skip


def header(stamp_ns: int, frame_id: str):
    return _t("std_msgs/msg/Header")(stamp=stamp_msg(stamp_ns), frame_id=frame_id)


def image_msg(stamp_ns: int, image: np.ndarray, frame_id: str = CAMERA_FRAME):
    """sensor_msgs/Image, mono8 for (H, W) uint8."""
    if image.dtype != np.uint8 or image.ndim != 2:
        raise ValueError(f"expected a (H, W) uint8 image, got {image.dtype} {image.shape}")
    h, w = image.shape
    return _t(IMAGE_TYPE)(header=header(stamp_ns, frame_id), height=h, width=w,
                          encoding="mono8", is_bigendian=0, step=w,
                          data=np.ascontiguousarray(image).reshape(-1))  # fmt: skip


COMPRESSIONS = ("png", "jpeg")
JPEG_QUALITY = 90  # image_transport's compressed plugin's default (jpeg_quality 95 in ROS 1)


def compressed_image_msg(stamp_ns: int, image: np.ndarray, compression: str,
                         frame_id: str = CAMERA_FRAME):
    """sensor_msgs/CompressedImage of a (H, W) uint8 image, as image_transport's compressed
    plugin writes a mono8 image (``format`` ``"mono8; png compressed mono8"`` or ``"mono8;
    jpeg compressed mono8"``)."""
    import cv2

    if image.dtype != np.uint8 or image.ndim != 2:
        raise ValueError(f"expected a (H, W) uint8 image, got {image.dtype} {image.shape}")
    if compression not in COMPRESSIONS:
        raise ValueError(f"compression must be one of {COMPRESSIONS}, got {compression!r}")
    params = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY] if compression == "jpeg" else []
    ok, buf = cv2.imencode("." + ("jpg" if compression == "jpeg" else "png"), image, params)
    if not ok:
        raise ValueError(f"OpenCV could not encode the image as {compression}")
    return _t(COMPRESSED_IMAGE_TYPE)(header=header(stamp_ns, frame_id),
                                     format=f"mono8; {compression} compressed mono8",
                                     data=buf.reshape(-1))  # fmt: skip


def camera_info_msg(stamp_ns: int, K: np.ndarray, width: int, height: int,
                    lens: LensModel | None = None, frame_id: str = CAMERA_FRAME):
    """sensor_msgs/CameraInfo with ``K``, the lens's model and coefficients (None: plumb_bob
    zeros), ``P = [K|0]``."""
    model = "plumb_bob" if lens is None else lens.model
    D = np.zeros(5) if lens is None else np.asarray(lens.coeffs, float)
    P = np.hstack([K, np.zeros((3, 1))])
    roi = _t("sensor_msgs/msg/RegionOfInterest")(x_offset=0, y_offset=0, height=0, width=0,
                                                 do_rectify=False)  # fmt: skip
    return _t(CAMERA_INFO_TYPE)(
        header=header(stamp_ns, frame_id), height=height, width=width,
        distortion_model=model, d=D, k=np.asarray(K, float).reshape(-1),
        r=np.eye(3).reshape(-1), p=P.reshape(-1), binning_x=0, binning_y=0, roi=roi,
    )  # fmt: skip


def pose_msg(R: np.ndarray, p: np.ndarray):
    """geometry_msgs/Pose from a rotation matrix and a position."""
    T = np.eye(4)
    T[:3, :3] = R
    _, (qx, qy, qz, qw) = pose_components(T)
    return _t("geometry_msgs/msg/Pose")(
        position=_t("geometry_msgs/msg/Point")(x=float(p[0]), y=float(p[1]), z=float(p[2])),
        orientation=_t("geometry_msgs/msg/Quaternion")(x=qx, y=qy, z=qz, w=qw),
    )


def rotation_of(q) -> np.ndarray:
    """(3, 3) of a geometry_msgs/Quaternion."""
    return Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()


def pose_of(pose_msg_) -> tuple[np.ndarray, np.ndarray]:
    """(R, p) of a geometry_msgs/Pose."""
    pos = pose_msg_.position
    return rotation_of(pose_msg_.orientation), np.array([pos.x, pos.y, pos.z])


def odometry_msg(stamp_ns: int, R: np.ndarray, p: np.ndarray, frame_id: str, child_frame_id: str,
                 linear: np.ndarray | None = None, angular: np.ndarray | None = None,
                 pose_covariance: np.ndarray | None = None,
                 twist_covariance: np.ndarray | None = None):  # fmt: skip
    """nav_msgs/Odometry; ``linear``/``angular`` (twist, child frame) zero if None; the
    covariances (36,) or (6, 6), zero if None."""
    vec = _t("geometry_msgs/msg/Vector3")
    lin = np.zeros(3) if linear is None else linear
    ang = np.zeros(3) if angular is None else angular
    twist = _t("geometry_msgs/msg/Twist")(linear=vec(x=float(lin[0]), y=float(lin[1]),
                                                     z=float(lin[2])),
                                          angular=vec(x=float(ang[0]), y=float(ang[1]),
                                                      z=float(ang[2])))  # fmt: skip
    cov = np.zeros(36) if pose_covariance is None else np.asarray(pose_covariance, float)
    return _t(ODOMETRY_TYPE)(
        header=header(stamp_ns, frame_id), child_frame_id=child_frame_id,
        pose=_t("geometry_msgs/msg/PoseWithCovariance")(pose=pose_msg(R, p),
                                                         covariance=cov.reshape(-1)),
        twist=_t("geometry_msgs/msg/TwistWithCovariance")(
            twist=twist, covariance=np.zeros(36) if twist_covariance is None
            else np.asarray(twist_covariance, float).reshape(-1)),
    )  # fmt: skip


def frame_connections(writer, ts, image_type: str = IMAGE_TYPE) -> tuple:
    """The connections of a recorded camera in ``rsvo_synth``'s layout, in this order: its
    images (``image_type`` on ``IMAGE_TOPIC``, or on ``IMAGE_TOPIC + "/compressed"`` for a
    CompressedImage), camera info and ground truth (typestore ``ts``)."""
    topic = IMAGE_TOPIC if image_type == IMAGE_TYPE else IMAGE_TOPIC + "/compressed"
    return (writer.add_connection(topic, image_type, typestore=ts),
            writer.add_connection(CAMERA_INFO_TOPIC, CAMERA_INFO_TYPE, typestore=ts),
            writer.add_connection(GROUND_TRUTH_TOPIC, ODOMETRY_TYPE, typestore=ts))


def write_frame(writer, connections: tuple, stamp_ns: int, image, K: np.ndarray, width: int,
                height: int, R: np.ndarray, p: np.ndarray, lens: LensModel | None = None,
                linear: np.ndarray | None = None, angular: np.ndarray | None = None) -> None:
    """One frame into :func:`frame_connections`: the image message ``image``, its camera info
    (``K``, the image size, ``lens``) and the ground truth (``R``, ``p`` world <- camera, the
    velocities where given), all stamped ``stamp_ns``."""
    c_img, c_info, c_gt = connections
    writer.write(c_img, stamp_ns, serialize(image))
    writer.write(c_info, stamp_ns, serialize(camera_info_msg(stamp_ns, K, width, height, lens)))
    writer.write(c_gt, stamp_ns, serialize(odometry_msg(stamp_ns, R, p, WORLD_FRAME, CAMERA_FRAME,
                                                        linear=linear, angular=angular)))


def serialize(msg) -> bytes:
    return typestore().serialize_cdr(msg, msg.__msgtype__)


def deserialize(raw: bytes, msgtype: str):
    return typestore().deserialize_cdr(raw, msgtype)


class BagReader:
    """A recorded bag for reading: a rosbag2 directory (sqlite3 or mcap) or a ROS 1 ``.bag``
    file (rosbags' AnyReader; ROS 1 message definitions come from the bag). ``connections``,
    ``messages(connections=...)`` as rosbags' readers, and ``deserialize(raw, msgtype)`` for
    the bag's own serialization. Raises whatever rosbags raises for an unreadable bag."""

    def __init__(self, path):
        path = Path(path)
        self.ros1 = path.is_file()
        if self.ros1:
            from rosbags.highlevel import AnyReader

            self._reader = AnyReader([path])
            self._reader.open()
            self.deserialize = self._reader.deserialize
        else:
            from rosbags.rosbag2 import Reader

            self._reader = Reader(path)
            self._reader.open()
            self.deserialize = deserialize
        self.connections = list(self._reader.connections)

    def messages(self, connections=()):
        return self._reader.messages(connections=connections)

    def close(self) -> None:
        self._reader.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def storage_plugin(storage: str):
    from rosbags.rosbag2 import StoragePlugin

    if storage not in STORAGES:
        raise ValueError(f"storage must be one of {STORAGES}, got {storage!r}")
    return StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP


def open_writer(path, storage: str):
    """A rosbags rosbag2 Writer (version 9, the Jazzy format), not yet opened."""
    from rosbags.rosbag2 import Writer

    return Writer(path, version=9, storage_plugin=storage_plugin(storage))


def custom_data(bag_path) -> dict[str, str]:
    """The custom_data of a rosbag2 directory's metadata.yaml ({} if none or unreadable).

    (rosbags writes it but its Reader does not expose it.)
    """
    import yaml

    try:
        with open(Path(bag_path) / "metadata.yaml") as f:
            info = (yaml.safe_load(f) or {}).get("rosbag2_bagfile_information", {})
    except (OSError, yaml.YAMLError):
        return {}
    return {str(k): str(v) for k, v in (info.get("custom_data") or {}).items()}
