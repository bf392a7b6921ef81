"""Camera intrinsics from a calibration file, for cameras and datasets without a CameraInfo topic.

Two formats, told apart by their keys:

- ROS's camera calibration YAML (what ``camera_calibration`` writes and ``camera_info_manager``
  reads): ``image_width``, ``image_height``, ``camera_matrix: {data: [9]}``,
  ``distortion_model``, ``distortion_coefficients: {data: [...]}``.
- Kalibr's camchain YAML (``cam0:``, ``cam1:`` ...; the rolling-shutter datasets' usual
  format): ``camera_model: pinhole``, ``intrinsics: [fu, fv, pu, pv]``, ``distortion_model``
  ``radtan`` (plumb_bob k1, k2, p1, p2), ``equidistant`` or ``none``, ``distortion_coeffs``,
  ``resolution: [width, height]``. ``camera`` picks the entry (default: the only one, or
  ``cam0``).

Pure YAML and numpy; :class:`~rsvo_ros.ros.convert.CameraIntrinsics` out, as from a CameraInfo.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rsvo_ros.core.lens import LensModel
from rsvo_ros.ros.convert import CameraIntrinsics

KALIBR_DISTORTION = {"radtan": "plumb_bob", "equidistant": "equidistant", "none": "none"}


def _number_list(value, what: str, n: int | None = None) -> np.ndarray:
    try:
        a = np.asarray(value, float).ravel()
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a list of numbers, got {value!r}") from None
    if n is not None and a.size != n:
        raise ValueError(f"{what} must have {n} numbers, got {a.size}")
    if not np.isfinite(a).all():
        raise ValueError(f"{what} has non-finite numbers: {a.tolist()}")
    return a


def _checked(K: np.ndarray, lens: LensModel | None, width, height) -> CameraIntrinsics:
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"focal lengths must be positive, got {K[0, 0]}, {K[1, 1]}")
    try:
        w, h = int(width), int(height)
    except (TypeError, ValueError):
        raise ValueError(f"image size must be integers, got {width!r} x {height!r}") from None
    if w <= 0 or h <= 0:
        raise ValueError(f"image size must be positive, got {w} x {h}")
    return CameraIntrinsics(K, lens, w, h)


def _from_ros(doc: dict, rectified: bool) -> CameraIntrinsics:
    if rectified:  # image_rect: the projection's left 3x3, no lens (as from a CameraInfo's P)
        P = _number_list((doc.get("projection_matrix") or {}).get("data"),
                         "projection_matrix.data (rectified images)", 12)  # fmt: skip
        return _checked(P.reshape(3, 4)[:, :3].copy(), None, doc.get("image_width"),
                        doc.get("image_height"))  # fmt: skip
    K = _number_list((doc.get("camera_matrix") or {}).get("data"), "camera_matrix.data", 9)
    coeffs = _number_list((doc.get("distortion_coefficients") or {}).get("data", []),
                          "distortion_coefficients.data")  # fmt: skip
    lens = LensModel.create(str(doc.get("distortion_model", "plumb_bob")), coeffs)
    return _checked(K.reshape(3, 3), lens, doc.get("image_width"), doc.get("image_height"))


def _from_kalibr(entry: dict, name: str) -> CameraIntrinsics:
    if entry.get("camera_model", "pinhole") != "pinhole":
        raise ValueError(f"{name}: camera_model {entry['camera_model']!r} is not supported "
                         "(pinhole only)")
    fu, fv, pu, pv = _number_list(entry.get("intrinsics"), f"{name}.intrinsics", 4)
    model = str(entry.get("distortion_model", "none"))
    if model not in KALIBR_DISTORTION:
        raise ValueError(f"{name}: distortion_model {model!r} is not supported (supported: "
                         f"{', '.join(KALIBR_DISTORTION)})")  # fmt: skip
    coeffs = _number_list(entry.get("distortion_coeffs", []), f"{name}.distortion_coeffs")
    lens = LensModel.create(KALIBR_DISTORTION[model], coeffs)
    size = _number_list(entry.get("resolution"), f"{name}.resolution", 2)
    K = np.array([[fu, 0.0, pu], [0.0, fv, pv], [0.0, 0.0, 1.0]])
    return _checked(K, lens, size[0], size[1])


def load_camera_file(path: str | Path, camera: str | None = None,
                     rectified: bool = False) -> CameraIntrinsics:  # fmt: skip
    """The intrinsics in ``path`` (ROS camera calibration or Kalibr camchain YAML, see the
    module). ``rectified``: for rectified images, the ROS file's ``projection_matrix`` and no
    lens (a Kalibr camchain holds no rectified camera: an error). Raises ValueError naming
    what is wrong or missing (and OSError for an unreadable file)."""
    import yaml

    with open(Path(path).expanduser()) as f:
        try:
            doc = yaml.safe_load(f)
        except yaml.YAMLError as exc:
            raise ValueError(f"{path} is not YAML: {exc}") from None
    if not isinstance(doc, dict):
        raise ValueError(f"{path} holds no calibration (a YAML mapping is expected)")
    if "camera_matrix" in doc:
        return _from_ros(doc, rectified)
    cams = {k: v for k, v in doc.items() if isinstance(v, dict) and "intrinsics" in v}
    if not cams:
        raise ValueError(f"{path} is neither a ROS camera calibration (camera_matrix) nor a "
                         "Kalibr camchain (cam0: intrinsics)")
    if camera is None:
        camera = next(iter(cams)) if len(cams) == 1 else "cam0"
    if camera not in cams:
        raise ValueError(f"{path} has no camera {camera!r} (cameras: {', '.join(cams)})")
    if rectified:
        raise ValueError(f"{path} is a Kalibr camchain, which holds the raw camera only; for "
                         "rectified images give the rectified camera's calibration (ROS YAML "
                         "with projection_matrix)")
    return _from_kalibr(cams[camera], camera)
