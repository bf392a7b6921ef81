"""Message <-> numpy conversions shared by the node and the tools (rsvo_ros.ros.convert)."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from rsvo_ros.core.lens import undistort_points
from rsvo_ros.ros import bagio
from rsvo_ros.ros.convert import (
    assumed_intrinsics,
    camera_from_info,
    compressed_to_gray,
    covariance_for_msg,
    image_to_gray,
    pose_components,
    to_gray,
)
from rsvo_ros.sim.synth import SynthConfig, render_sequence


@pytest.fixture(scope="module")
def textured():
    return render_sequence(SynthConfig(frames=1, width=320, height=180))[0].image


def test_to_gray_accepts_the_supported_encodings(textured):
    h, w = textured.shape
    rgb = np.dstack([textured, textured, textured])
    assert np.array_equal(to_gray(textured.ravel(), "mono8", h, w, w), textured)
    assert np.array_equal(to_gray(rgb.ravel(), "rgb8", h, w, 3 * w), textured)
    assert np.array_equal(to_gray(rgb.ravel(), "bgr8", h, w, 3 * w), textured)
    m16 = (textured.astype("<u2") << 8).view(np.uint8).ravel()
    assert np.array_equal(to_gray(m16, "mono16", h, w, 2 * w), textured)
    padded = np.hstack([textured, np.zeros((h, 4), np.uint8)])  # step > width
    assert np.array_equal(to_gray(padded.ravel(), "mono8", h, w, w + 4), textured)
    big = (textured.astype(np.uint16) << 8).astype(">u2").view(np.uint8).ravel()  # is_bigendian
    assert np.array_equal(to_gray(big, "mono16", h, w, 2 * w, bigendian=True), textured)
    alpha = np.full_like(textured, 77)
    for enc in ("rgba8", "bgra8"):
        assert np.array_equal(to_gray(np.dstack([rgb, alpha]).ravel(), enc, h, w, 4 * w),
                              textured)
    # 4:2:2 YUV of USB cameras: the luma bytes are the grey image, whatever the chroma
    chroma = np.full_like(textured, 128) ^ (textured & 7)
    uyvy = np.dstack([chroma, textured]).ravel()  # U Y V Y ...
    yuyv = np.dstack([textured, chroma]).ravel()  # Y U Y V ...
    assert np.array_equal(to_gray(uyvy, "yuv422", h, w, 2 * w), textured)
    assert np.array_equal(to_gray(yuyv, "yuv422_yuy2", h, w, 2 * w), textured)
    with pytest.raises(ValueError, match="even width"):
        to_gray(uyvy, "yuv422", h, w - 1, 2 * w)


def test_bayer_images_are_demosaicked_by_their_own_pattern(textured):
    """A colour image sampled through each ROS Bayer pattern (named by its first two rows)
    comes back as its grey image; another pattern's reading is far off."""
    g = textured.astype(float)
    bgr = cv2.GaussianBlur(np.clip(np.dstack([0.3 * g, 0.9 * g, 255 - 0.8 * g]), 0, 255)
                           .astype(np.uint8), (5, 5), 1.5)  # fmt: skip
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY).astype(float)
    h, w = textured.shape
    channel = {"b": 0, "g": 1, "r": 2}
    for pattern in ("rggb", "bggr", "gbrg", "grbg"):
        mosaic = np.zeros((h, w), np.uint8)
        for (dy, dx), c in zip([(0, 0), (0, 1), (1, 0), (1, 1)], pattern, strict=True):
            mosaic[dy::2, dx::2] = bgr[dy::2, dx::2, channel[c]]
        errors = {}
        for other in ("rggb", "bggr", "gbrg", "grbg"):
            out = to_gray(mosaic.ravel(), f"bayer_{other}8", h, w, w).astype(float)
            errors[other] = np.abs(out - grey)[4:-4, 4:-4].mean()
        assert errors[pattern] < 1.0, errors
        assert min(e for p, e in errors.items() if p != pattern) > 10.0, errors


@pytest.mark.parametrize("args, message", [
    (("32FC1", 10, 10, 40), "unsupported encoding"),
    (("mono8", 0, 10, 10), "empty"),
    (("mono8", 10, 10, 5), "shorter than a row"),
    (("mono8", 10, 10, 10), "bytes"),  # data too short below
])
def test_to_gray_rejects_bad_images(args, message):
    with pytest.raises(ValueError, match=message):
        to_gray(np.zeros(50, np.uint8), *args)


def _info(k, d=(), model="plumb_bob", width=320, height=180):
    return SimpleNamespace(k=list(k), d=list(d), distortion_model=model, width=width,
                           height=height)


def _encoded(ext, img, params=()):
    ok, buf = cv2.imencode(ext, img, list(params))
    assert ok
    return buf.reshape(-1)


def test_compressed_images_decode_as_image_transport_writes_them(textured):
    """sensor_msgs/CompressedImage: PNG exactly, JPEG within its artefacts, colour and 16 bit
    as the raw encodings; the message dispatch (rosbags' CompressedImage has no encoding)."""
    png = bagio.compressed_image_msg(0, textured, "png")
    assert png.format == "mono8; png compressed mono8"
    assert np.array_equal(image_to_gray(png), textured)
    jpeg = image_to_gray(bagio.compressed_image_msg(0, textured, "jpeg"))
    assert jpeg.shape == textured.shape
    assert 0 < np.abs(jpeg.astype(int) - textured).mean() < 3.0
    bgr = np.dstack([textured, textured // 2, textured // 3])  # not grey: the channel order counts
    assert np.array_equal(compressed_to_gray(_encoded(".png", bgr), "bgr8; png compressed bgr8"),
                          to_gray(bgr.ravel(), "bgr8", *textured.shape, 3 * textured.shape[1]))
    rgb = bgr[..., ::-1]  # image_transport compresses rgb8 as it is: OpenCV reads it as BGR
    assert np.array_equal(compressed_to_gray(_encoded(".png", np.ascontiguousarray(rgb)),
                                             "rgb8; png compressed rgb8"),
                          to_gray(rgb.ravel(), "rgb8", *textured.shape, 3 * textured.shape[1]))
    m16 = textured.astype(np.uint16) << 8 | 0x7F
    assert np.array_equal(compressed_to_gray(_encoded(".png", m16), "mono16; png compressed "
                                             "mono16"), textured)  # fmt: skip


@pytest.mark.parametrize("data, fmt, message", [
    (np.zeros(0, np.uint8), "jpeg", "empty compressed image"),
    (np.arange(200, dtype=np.uint8), "jpeg", "cannot decode the compressed image"),
    (np.arange(200, dtype=np.uint8), "16UC1; compressedDepth png", "depth image"),
])
def test_compressed_images_that_cannot_be_used_say_why(data, fmt, message):
    with pytest.raises(ValueError, match=message):
        compressed_to_gray(data, fmt)


def test_camera_from_info_reads_k_d_and_size():
    K = np.array([[400.0, 0, 160], [0, 410.0, 90], [0, 0, 1]])
    cam = camera_from_info(_info(K.ravel(), [0.1, 0, 0, 0, 0]))
    assert np.array_equal(cam.K, K) and cam.lens.model == "plumb_bob"
    assert np.allclose(cam.lens.coeffs, [0.1, 0, 0, 0, 0])
    assert (cam.width, cam.height) == (320, 180)
    assert camera_from_info(_info(K.ravel(), [0.0] * 5)).lens is None  # zeros: no distortion
    rational = camera_from_info(_info(K.ravel(), [0.1] * 8, "rational_polynomial")).lens
    assert rational.model == "rational_polynomial" and len(rational.coeffs) == 8
    # a fisheye with zero coefficients is still a fisheye (r = f theta, not f tan theta)
    assert camera_from_info(_info(K.ravel(), [0.0] * 4, "equidistant")).lens.model \
        == "equidistant"


def test_camera_from_info_of_rectified_images_takes_p_and_no_lens():
    K = np.array([[400.0, 0, 160], [0, 410.0, 90], [0, 0, 1]])
    info = _info(K.ravel(), [0.1, 0, 0, 0, 0])
    info.p = [380.0, 0, 150, 0, 0, 385.0, 92, 0, 0, 0, 1, 0]  # the rectified camera
    cam = camera_from_info(info, rectified=True)
    assert np.array_equal(cam.K, [[380.0, 0, 150], [0, 385.0, 92], [0, 0, 1]])
    assert cam.lens is None and (cam.width, cam.height) == (320, 180)
    info.p = [0.0] * 12  # a CameraInfo without P cannot describe rectified images
    with pytest.raises(ValueError, match="uncalibrated .P for rectified images all zero"):
        camera_from_info(info, rectified=True)


def _roi(x=0, y=0, w=0, h=0):
    return SimpleNamespace(x_offset=x, y_offset=y, width=w, height=h)


@pytest.mark.parametrize("bx, by, roi", [(2, 2, _roi()), (1, 1, _roi(100, 40, 400, 200)),
                                         (2, 4, _roi(64, 32, 512, 256)), (0, 0, _roi())])
def test_binning_and_roi_give_the_intrinsics_of_the_images_as_they_come(bx, by, roi):
    """REP 104: K, D, width and height are the full-resolution calibration's; an image pixel of
    the binned region is the full-resolution pixel ``(u bx + x_offset, v by + y_offset)``, so
    its normalised (undistorted) coordinates must come out the same either way."""
    K = np.array([[800.0, 0.5, 330.0], [0, 790.0, 190.0], [0, 0, 1]])
    d = [-0.2, 0.05, 0.001, -0.002, 0.0]
    info = _info(K.ravel(), d, width=640, height=360)
    info.binning_x, info.binning_y, info.roi = bx, by, roi
    cam = camera_from_info(info)
    full = camera_from_info(_info(K.ravel(), d, width=640, height=360))
    bx, by = max(bx, 1), max(by, 1)
    rw, rh = (roi.width, roi.height) if roi.width else (640, 360)
    assert (cam.width, cam.height) == (rw // bx, rh // by) and cam.binning_y == by
    rng = np.random.default_rng(0)
    uv = rng.uniform([0, 0], [cam.width, cam.height], (50, 2))
    uv_full = uv * [bx, by] + [roi.x_offset, roi.y_offset]

    def normalised(c, px):
        und = undistort_points(px, c.K, c.lens)
        return np.column_stack([und, np.ones(len(und))]) @ np.linalg.inv(c.K).T

    assert np.allclose(normalised(cam, uv), normalised(full, uv_full), atol=1e-9)


def test_a_region_of_interest_outside_the_image_is_refused():
    info = _info([800.0, 0, 320, 0, 800.0, 180, 0, 0, 1], width=640, height=360)
    info.roi = _roi(400, 0, 300, 100)
    with pytest.raises(ValueError, match="region of interest outside the image"):
        camera_from_info(info)


@pytest.mark.parametrize("k, d, model, message", [
    ([0.0] * 9, [], "plumb_bob", "uncalibrated .K all zero.*uncalibrated_focal_factor"),
    ([0.0] * 8 + [1.0], [], "plumb_bob", "invalid K"),
    ([np.nan] + [0.0] * 8, [], "plumb_bob", "invalid K"),
    ([400.0, 0, 160, 0, 400.0, 90, 0, 0, 1], [0.1], "kannala_brandt_9", "unsupported"),
    ([400.0, 0, 160, 0, 400.0, 90, 0, 0, 1], [0.1] * 5, "equidistant", "takes 4"),
    ([400.0, 0, 160, 0, 400.0, 90, 0, 0, 1], [0.1] * 5, "rational_polynomial", "takes 8"),
    ([400.0, 0, 160, 0, 400.0, 90, 0, 0, 1], [np.nan] * 5, "plumb_bob", "non-finite"),
])
def test_camera_from_info_rejects_bad_intrinsics(k, d, model, message):
    with pytest.raises(ValueError, match=message):
        camera_from_info(_info(k, d, model))


def test_an_uncalibrated_camera_info_gets_assumed_intrinsics_only_when_asked():
    """Camera drivers without a calibration file (usb_cam, v4l2_camera) publish K all zero.
    Refused with the way out named; with uncalibrated_focal_factor the pinhole of that many
    image widths, centred, without a lens, marked as assumed (binning applies as to any K)."""
    info = _info([0.0] * 9, [0.1, 0.0, 0.0, 0.0, 0.0], width=640, height=360)
    with pytest.raises(ValueError, match="uncalibrated"):
        camera_from_info(info)
    cam = camera_from_info(info, uncalibrated_focal_factor=0.9)
    assert cam.assumed and cam.lens is None and (cam.width, cam.height) == (640, 360)
    assert np.allclose(cam.K, [[576.0, 0, 319.5], [0, 576.0, 179.5], [0, 0, 1]])
    assert np.array_equal(cam.K, assumed_intrinsics(640, 360, 0.9))
    info.binning_x = info.binning_y = 2
    half = camera_from_info(info, uncalibrated_focal_factor=0.9)
    assert (half.width, half.height) == (320, 180) and half.K[0, 0] == 288.0
    # a calibrated camera info is not touched by the factor
    calibrated = _info([400.0, 0, 160, 0, 400.0, 90, 0, 0, 1], [], width=320, height=180)
    cam = camera_from_info(calibrated, uncalibrated_focal_factor=0.9)
    assert not cam.assumed and cam.K[0, 0] == 400.0
    # nor is a broken one, and an uncalibrated one without an image size stays refused
    with pytest.raises(ValueError, match="invalid K"):
        camera_from_info(_info([-1.0, 0, 160, 0, 400.0, 90, 0, 0, 1], []),
                         uncalibrated_focal_factor=0.9)
    with pytest.raises(ValueError, match="no image size"):
        camera_from_info(_info([0.0] * 9, [], width=0, height=0), uncalibrated_focal_factor=0.9)


def test_pose_components_and_covariance():
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    T[:3, :3] = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])  # 90 deg about z
    p, q = pose_components(T)
    assert np.allclose(p, [1, 2, 3]) and np.allclose(q, [0, 0, np.sqrt(0.5), np.sqrt(0.5)])
    cov = np.full((6, 6), np.inf)
    cov[0, 0] = 2.0
    out = covariance_for_msg(cov)
    assert out.shape == (36,) and out[0] == 2.0 and np.all(out[1:] == 1e6)
