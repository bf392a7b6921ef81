"""Message <-> numpy conversions shared by the node (rclpy messages) and the tools (rosbags
messages).

Both libraries' messages carry the same field names, so the readers here take either; writers
return plain values that each side puts into its own message class. Pure numpy, OpenCV and
scipy: nothing here imports rclpy or rosbags.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from rsvo_ros.core.geometry import quat_xyzw_from_matrix
from rsvo_ros.core.lens import LensModel

# sensor_msgs/image_encodings: (channels, bytes per channel) of each one taken
_LAYOUT = {"mono8": (1, 1), "8UC1": (1, 1), "mono16": (1, 2), "16UC1": (1, 2),
           "rgb8": (3, 1), "bgr8": (3, 1), "rgba8": (4, 1), "bgra8": (4, 1),
           # 4:2:2 YUV of USB cameras (v4l2_camera, usb_cam): 2 bytes per pixel, Y in one
           "yuv422": (2, 1), "uyvy": (2, 1), "yuv422_yuy2": (2, 1), "yuyv": (2, 1),
           "bayer_rggb8": (1, 1), "bayer_bggr8": (1, 1), "bayer_gbrg8": (1, 1),
           "bayer_grbg8": (1, 1)}  # fmt: skip
SUPPORTED_ENCODINGS = tuple(_LAYOUT)
# the luma byte of a YUV 4:2:2 pixel pair: UYVY (ROS "yuv422") odd, YUYV (YUY2) even
_LUMA_OFFSET = {"yuv422": 1, "uyvy": 1, "yuv422_yuy2": 0, "yuyv": 0}
# ROS names a Bayer pattern by its first two rows; OpenCV by the second row's middle pixels
# (cv_bridge's table)
_BAYER = {"bayer_rggb8": cv2.COLOR_BayerBG2GRAY, "bayer_bggr8": cv2.COLOR_BayerRG2GRAY,
          "bayer_gbrg8": cv2.COLOR_BayerGR2GRAY, "bayer_grbg8": cv2.COLOR_BayerGB2GRAY}
_COLOUR = {"rgb8": cv2.COLOR_RGB2GRAY, "bgr8": cv2.COLOR_BGR2GRAY, "rgba8": cv2.COLOR_RGBA2GRAY,
           "bgra8": cv2.COLOR_BGRA2GRAY}

COVARIANCE_UNKNOWN = 1e6  # what a non-finite covariance entry is published as


def to_gray(data: np.ndarray, encoding: str, height: int, width: int, step: int,
            bigendian: bool = False) -> np.ndarray:  # fmt: skip
    """uint8 (H, W) image from a sensor_msgs/Image payload (16-bit images keep their high
    byte; ``bigendian``: the message's ``is_bigendian``, for 16-bit data).

    Raises ValueError naming the problem (unsupported encoding, size/step mismatch, empty).
    """
    if encoding not in _LAYOUT:
        raise ValueError(f"unsupported encoding {encoding!r} (supported: "
                         f"{', '.join(SUPPORTED_ENCODINGS)})")  # fmt: skip
    if height <= 0 or width <= 0:
        raise ValueError(f"empty image ({width}x{height})")
    channels, itemsize = _LAYOUT[encoding]
    row_bytes = width * channels * itemsize
    if step < row_bytes:
        raise ValueError(f"step {step} is shorter than a row ({row_bytes} bytes)")
    buf = np.frombuffer(np.asarray(data, dtype=np.uint8).tobytes(), dtype=np.uint8)
    if buf.size < step * height:
        raise ValueError(f"image data has {buf.size} bytes, {step * height} expected "
                         f"({width}x{height}, step {step})")  # fmt: skip
    rows = buf[: step * height].reshape(height, step)[:, :row_bytes]
    if itemsize == 2:
        return (rows.copy().view(">u2" if bigendian else "<u2").reshape(height, width)
                >> 8).astype(np.uint8)  # fmt: skip
    if encoding in _LUMA_OFFSET:
        if width % 2:
            raise ValueError(f"a {encoding} image needs an even width, got {width}")
        return np.ascontiguousarray(rows[:, _LUMA_OFFSET[encoding]::2])
    if channels == 1:
        img = np.ascontiguousarray(rows)
        return cv2.cvtColor(img, _BAYER[encoding]) if encoding in _BAYER else img
    img = rows.reshape(height, width, channels)
    return cv2.cvtColor(np.ascontiguousarray(img), _COLOUR[encoding])


def compressed_to_gray(data: np.ndarray, fmt: str) -> np.ndarray:
    """uint8 (H, W) image from a sensor_msgs/CompressedImage payload (JPEG or PNG, as
    image_transport's ``compressed`` plugin writes it: ``format`` ``"jpeg"``, ``"png"`` or
    ``"bgr8; jpeg compressed bgr8"``; 16-bit PNG keeps its high byte, as mono16).

    Raises ValueError naming the problem (empty, a depth image, undecodable data).
    """
    buf = np.frombuffer(np.asarray(data, dtype=np.uint8).tobytes(), dtype=np.uint8)
    if buf.size == 0:
        raise ValueError(f"empty compressed image (format {fmt!r})")
    if "compresseddepth" in fmt.lower():
        raise ValueError(f"compressedDepth is a depth image, not a camera image (format {fmt!r})")
    img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise ValueError(f"cannot decode the compressed image ({buf.size} bytes, format "
                         f"{fmt!r}; JPEG and PNG are supported)")  # fmt: skip
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise ValueError(f"unsupported compressed pixel type {img.dtype} (format {fmt!r})")
    if img.ndim == 2:
        return np.ascontiguousarray(img)
    # OpenCV decodes colour as BGR; image_transport compresses bgr8, or rgb8 as if it were bgr8
    order = "rgb" if fmt.lower().rstrip().endswith(("rgb8", "rgba8")) else "bgr"
    return cv2.cvtColor(img, _COLOUR[order + ("a8" if img.shape[2] == 4 else "8")])


def image_to_gray(msg) -> np.ndarray:
    """uint8 (H, W) of a sensor_msgs/Image or sensor_msgs/CompressedImage (rclpy or rosbags);
    ValueError as :func:`to_gray` and :func:`compressed_to_gray`."""
    if not hasattr(msg, "encoding") and hasattr(msg, "format"):
        return compressed_to_gray(msg.data, msg.format)
    return to_gray(msg.data, msg.encoding, msg.height, msg.width, msg.step,
                   bool(getattr(msg, "is_bigendian", 0)))


def stamp_ns(header) -> int:
    """Integer nanoseconds of a std_msgs/Header's stamp."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


@dataclass
class CameraIntrinsics:
    """What the pipeline needs of a sensor_msgs/CameraInfo: ``K`` (3, 3), the lens (None when
    the image is not distorted) and the image size (0 when unset)."""

    K: np.ndarray
    lens: LensModel | None
    width: int
    height: int
    # sensor rows per image row (CameraInfo's binning_y; 1 without binning): the line delay is
    # per image row, so a binned camera's is this many times the sensor's row time
    binning_y: int = 1
    # K is assumed (an uncalibrated camera info and ``uncalibrated_focal_factor``), not measured
    assumed: bool = False


UNCALIBRATED_HINT = ("calibrate the camera (camera_calibration), or set "
                     "uncalibrated_focal_factor (rsvo_replay, rsvo_calibrate: "
                     "--uncalibrated-focal-factor) to "
                     "assume a focal length of that many image widths, e.g. 1.0")


def assumed_intrinsics(width: int, height: int, focal_factor: float) -> np.ndarray:
    """The K (3, 3) assumed for an uncalibrated camera: focal length ``focal_factor`` image
    widths (a fair guess for phones, webcams and dash cams: 0.7-1.2), square pixels, the
    principal point at the image centre."""
    f = float(focal_factor) * width
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def _info_field(msg, name: str):
    """A CameraInfo matrix by its ROS 2 name (``k``, ``d``, ``p``); ROS 1's CameraInfo (a ROS 1
    bag through rosbags) spells them in capitals."""
    return getattr(msg, name) if hasattr(msg, name) else getattr(msg, name.upper())


def camera_from_info(msg, rectified: bool = False,
                     uncalibrated_focal_factor: float = 0.0) -> CameraIntrinsics:  # fmt: skip
    """:class:`CameraIntrinsics` of a sensor_msgs/CameraInfo (rclpy or rosbags).

    ``rectified``: the images are already rectified (image_proc's ``image_rect``): the
    intrinsics are the projection ``P``'s left 3x3 and there is no lens to undo.
    ``uncalibrated_focal_factor`` > 0: a camera info whose K (or P) is all zero, as camera
    drivers publish without a calibration file, gives :func:`assumed_intrinsics` for its
    size (no lens; ``assumed`` set) instead of an error.

    Raises ValueError for a non-finite or non-positive focal length (an uncalibrated camera
    info says so and how to go on), and for a distortion model other than ``plumb_bob``,
    ``rational_polynomial`` or ``equidistant`` (or none) or the wrong number of coefficients
    for it.
    """
    if rectified:
        K, matrix = np.asarray(_info_field(msg, "p"), float).reshape(3, 4)[:, :3].copy(), \
            "P for rectified images"
    else:
        K, matrix = np.asarray(_info_field(msg, "k"), float).reshape(3, 3), "K"
    if np.isfinite(K).all() and not K.any():  # no calibration (a driver without its file)
        width, height = int(msg.width), int(msg.height)
        if uncalibrated_focal_factor <= 0 or width <= 0 or height <= 0:
            raise ValueError(f"camera info is uncalibrated ({matrix} all zero"
                             f"{'' if width > 0 and height > 0 else ', no image size'}): "
                             f"{UNCALIBRATED_HINT}")
        K, width, height, binning_y = _binned_roi(
            msg, assumed_intrinsics(width, height, uncalibrated_focal_factor))
        return CameraIntrinsics(K, None, width, height, binning_y, assumed=True)
    if not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"camera info with an invalid {matrix} (non-finite or non-positive "
                         "focal length)")
    lens = None if rectified else LensModel.create(str(msg.distortion_model),
                                                   np.asarray(_info_field(msg, "d"), float))
    K, width, height, binning_y = _binned_roi(msg, K)
    return CameraIntrinsics(K, lens, width, height, binning_y)


def _binned_roi(msg, K: np.ndarray) -> tuple[np.ndarray, int, int, int]:
    """REP 104: CameraInfo's K, P, width and height are the full-resolution calibration's; the
    images are its region of interest (``roi``; all zero: the whole image) binned by
    ``binning_x`` x ``binning_y`` (0 or 1: none). The intrinsics of the images as they come:
    ``fx / bx``, ``(cx - x_offset) / bx`` (and in y), which keep every pixel's normalised
    coordinates, so the lens (defined on those) stays as it is; and the images' size.
    Raises ValueError for a region outside the calibrated image."""
    bx, by = (max(int(getattr(msg, f"binning_{a}", 0) or 0), 1) for a in "xy")
    roi = getattr(msg, "roi", None)
    x0, y0, rw, rh = (0, 0, 0, 0) if roi is None else (
        int(roi.x_offset), int(roi.y_offset), int(roi.width), int(roi.height))
    width, height = int(msg.width), int(msg.height)
    if rw == 0 and rh == 0:  # the whole image (REP 104)
        x0 = y0 = 0
        rw, rh = width, height
    elif width and height and (x0 + rw > width or y0 + rh > height or rw <= 0 or rh <= 0):
        raise ValueError(f"camera info with a region of interest outside the image ({rw}x{rh} "
                         f"at {x0},{y0} in {width}x{height})")
    if bx == 1 and by == 1 and (x0, y0) == (0, 0) and (rw, rh) == (width, height):
        return K, width, height, 1
    K = K.copy()
    K[0, 0], K[0, 1], K[0, 2] = K[0, 0] / bx, K[0, 1] / bx, (K[0, 2] - x0) / bx
    K[1, 1], K[1, 2] = K[1, 1] / by, (K[1, 2] - y0) / by
    return K, rw // bx, rh // by, by


def pose_components(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position (3,) and unit quaternion ``quat_xyzw`` (4,) of a (4, 4) ``T`` (geometry_msgs
    order, w >= 0)."""
    return np.asarray(T[:3, 3], float), quat_xyzw_from_matrix(T[:3, :3])


def tum_line(stamp_ns: int, T: np.ndarray) -> str:
    """One TUM trajectory line: ``stamp x y z qx qy qz qw`` (s, m, Hamilton unit quaternion)."""
    (x, y, z), (qx, qy, qz, qw) = pose_components(T)
    return (f"{stamp_ns / 1e9:.9f} {x:.9f} {y:.9f} {z:.9f} {qx:.9f} {qy:.9f} {qz:.9f} "
            f"{qw:.9f}")


def fill_pose(pose, T: np.ndarray) -> None:
    """Write ``T`` into a geometry_msgs/Pose (any library whose fields can be assigned)."""
    p, q = pose_components(T)
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in p)
    pose.orientation.x, pose.orientation.y = float(q[0]), float(q[1])
    pose.orientation.z, pose.orientation.w = float(q[2]), float(q[3])


def covariance_for_msg(cov: np.ndarray) -> np.ndarray:
    """(36,) float covariance for a message: non-finite entries become ``COVARIANCE_UNKNOWN``."""
    cov = np.asarray(cov, float)
    return np.where(np.isfinite(cov), cov, COVARIANCE_UNKNOWN).ravel()


def fill_twist(twist, linear: np.ndarray, angular: np.ndarray) -> None:
    """Write ``linear``, ``angular`` (3,) into a geometry_msgs/Twist."""
    twist.linear.x, twist.linear.y, twist.linear.z = (float(v) for v in linear)
    twist.angular.x, twist.angular.y, twist.angular.z = (float(v) for v in angular)


def fill_transform(transform, T: np.ndarray) -> None:
    """Write ``T`` into a geometry_msgs/Transform (translation, rotation)."""
    p, q = pose_components(T)
    transform.translation.x, transform.translation.y, transform.translation.z = (float(v)
                                                                                 for v in p)
    transform.rotation.x, transform.rotation.y = float(q[0]), float(q[1])
    transform.rotation.z, transform.rotation.w = float(q[2]), float(q[3])


POINT_FIELD_FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32
XYZ_FIELDS = (("x", 0), ("y", 4), ("z", 8))  # (name, offset), FLOAT32, count 1
XYZ_POINT_STEP = 12


def xyz_cloud_data(points: np.ndarray) -> bytes:
    """Little-endian float32 x, y, z of (N, 3) points: a dense sensor_msgs/PointCloud2 payload
    (``XYZ_FIELDS``, point_step ``XYZ_POINT_STEP``, height 1, width N); non-finite points are
    left out."""
    pts = np.asarray(points, float).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    return pts.astype("<f4").tobytes()
