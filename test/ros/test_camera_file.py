"""Camera intrinsics from calibration files (rsvo_ros.ros.camera_file): ROS and Kalibr YAML."""

from __future__ import annotations

import numpy as np
import pytest

from rsvo_ros.ros.camera_file import load_camera_file

ROS_YAML = """\
image_width: 640
image_height: 480
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [500.5, 0.0, 320.25, 0.0, 501.0, 240.75, 0.0, 0.0, 1.0]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.1, 0.02, 0.001, -0.002, 0.0]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [480.0, 0.0, 321.0, 0.0, 0.0, 482.0, 239.0, 0.0, 0.0, 0.0, 1.0, 0.0]
"""

KALIBR_YAML = """\
cam0:
  camera_model: pinhole
  distortion_coeffs: [0.01, -0.02, 0.003, 0.004]
  distortion_model: equidistant
  intrinsics: [190.9, 190.8, 254.9, 256.9]
  resolution: [512, 512]
  rostopic: /cam0/image_raw
cam1:
  T_cn_cnm1: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
  camera_model: pinhole
  distortion_coeffs: [-0.28, 0.07, 0.0002, 0.00002]
  distortion_model: radtan
  intrinsics: [458.6, 457.3, 367.2, 248.4]
  resolution: [752, 480]
  rostopic: /cam1/image_raw
"""


def _file(tmp_path, text, name="cam.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_a_ros_calibration_file_gives_k_the_lens_and_the_size(tmp_path):
    cam = load_camera_file(_file(tmp_path, ROS_YAML))
    assert np.array_equal(cam.K, [[500.5, 0, 320.25], [0, 501.0, 240.75], [0, 0, 1]])
    assert cam.lens.model == "plumb_bob"
    assert cam.lens.coeffs == (-0.1, 0.02, 0.001, -0.002, 0.0)
    assert (cam.width, cam.height) == (640, 480)
    no_lens = ROS_YAML.replace("[-0.1, 0.02, 0.001, -0.002, 0.0]", "[0, 0, 0, 0, 0]")
    assert load_camera_file(_file(tmp_path, no_lens)).lens is None


def test_rectified_images_take_the_files_projection_and_no_lens(tmp_path):
    cam = load_camera_file(_file(tmp_path, ROS_YAML), rectified=True)
    assert np.array_equal(cam.K, [[480.0, 0, 321.0], [0, 482.0, 239.0], [0, 0, 1]])
    assert cam.lens is None and (cam.width, cam.height) == (640, 480)
    no_p = ROS_YAML[:ROS_YAML.index("projection_matrix")]
    with pytest.raises(ValueError, match="projection_matrix.data"):
        load_camera_file(_file(tmp_path, no_p, "no_p.yaml"), rectified=True)
    with pytest.raises(ValueError, match="Kalibr camchain, which holds the raw camera only"):
        load_camera_file(_file(tmp_path, KALIBR_YAML, "k.yaml"), rectified=True)


def test_a_kalibr_camchain_gives_the_chosen_camera(tmp_path):
    path = _file(tmp_path, KALIBR_YAML)
    cam0 = load_camera_file(path)  # several cameras: cam0
    assert np.array_equal(cam0.K, [[190.9, 0, 254.9], [0, 190.8, 256.9], [0, 0, 1]])
    assert cam0.lens.model == "equidistant" and (cam0.width, cam0.height) == (512, 512)
    cam1 = load_camera_file(path, "cam1")
    assert cam1.lens.model == "plumb_bob"  # Kalibr's radtan
    assert cam1.lens.coeffs == (-0.28, 0.07, 0.0002, 0.00002)
    assert (cam1.width, cam1.height) == (752, 480)
    only = "cam3:\n" + "\n".join(KALIBR_YAML.splitlines()[1:7]).replace("equidistant", "none")
    cam = load_camera_file(_file(tmp_path, only.replace("[0.01, -0.02, 0.003, 0.004]", "[]"),
                                 "one.yaml"))  # fmt: skip
    assert cam.lens is None and cam.K[0, 0] == 190.9  # the only entry, whatever its name


@pytest.mark.parametrize("text, entry, message", [
    ("[1, 2, 3]", None, "YAML mapping"),
    ("a: [b\n", None, "not YAML"),
    ("foo: 1\n", None, "neither a ROS camera calibration"),
    (KALIBR_YAML, "cam7", "no camera 'cam7'"),
    (KALIBR_YAML.replace("intrinsics: [190.9, 190.8, 254.9, 256.9]", "intrinsics: [1, 2]"),
     None, "cam0.intrinsics must have 4 numbers"),
    (KALIBR_YAML.replace("distortion_model: equidistant", "distortion_model: fov"), None,
     "distortion_model 'fov' is not supported"),
    (KALIBR_YAML.replace("camera_model: pinhole\n  distortion_coeffs: [0.01",
                         "camera_model: omni\n  distortion_coeffs: [0.01"), None, "pinhole only"),
    (ROS_YAML.replace("500.5", "-500.5"), None, "focal lengths must be positive"),
    (ROS_YAML.replace("image_width: 640", "image_width: wide"), None, "image size"),
    (ROS_YAML.replace("[-0.1, 0.02, 0.001, -0.002, 0.0]", "[0.1, 0.2, 0.3]"), None,
     "takes 4 or 5 coefficients"),
    (ROS_YAML.replace("0.0, 0.0, 1.0]", "0.0, 1.0]"), None, "camera_matrix.data must have 9"),
])
def test_a_calibration_file_that_cannot_be_used_says_why(tmp_path, text, entry, message):
    with pytest.raises(ValueError, match=message):
        load_camera_file(_file(tmp_path, text), entry)
