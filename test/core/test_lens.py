"""Lens models: each CameraInfo model's undistortion inverts its distortion across the image."""

from __future__ import annotations

import numpy as np
import pytest

from rsvo_ros.core.lens import LensModel, as_lens, undistort_points
from rsvo_ros.sim.synth import LENSES

K = np.array([[420.0, 0, 320], [0, 420.0, 180], [0, 0, 1]])


@pytest.mark.parametrize("name", sorted(LENSES))
def test_undistort_inverts_distort_to_the_corners(name):
    lens = LENSES[name]
    u, v = np.meshgrid(np.linspace(0, 640, 17), np.linspace(0, 360, 9))
    pts = np.column_stack([u.ravel(), v.ravel()])  # undistorted pixels, corners included
    raw = lens.distort(pts, K)
    assert np.abs(raw - pts).max() > 5.0  # a real distortion: corners move by pixels
    assert np.allclose(lens.undistort(raw, K), pts, atol=1e-6)
    assert np.allclose(undistort_points(raw, K, lens), pts, atol=1e-6)


def test_lens_from_camera_info_fields():
    assert LensModel.create("plumb_bob", [0.0] * 5) is None
    assert LensModel.create("", []) is None
    assert LensModel.create("equidistant", [0.0] * 4) == LensModel("equidistant", (0.0,) * 4)
    assert as_lens([0.1, 0, 0, 0, 0]).model == "plumb_bob"
    assert as_lens([0.1] * 8).model == "rational_polynomial"
    with pytest.raises(ValueError, match="unsupported distortion model 'fov'"):
        LensModel("fov", (0.1,))
    with pytest.raises(ValueError, match="takes 4 coefficients, got 5"):
        LensModel("equidistant", (0.0,) * 5)
