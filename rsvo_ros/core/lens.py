"""Lens distortion models of sensor_msgs/CameraInfo, with OpenCV doing the maths.

``plumb_bob`` (k1, k2, p1, p2[, k3]), ``rational_polynomial`` (k1, k2, p1, p2, k3, k4, k5, k6)
and ``equidistant`` (fisheye: k1, k2, k3, k4 of ``theta_d = theta (1 + k1 theta^2 + ...)``).
A rolling-shutter camera keeps its *sensor* rows: undistortion moves a point's coordinates, not
the time its row was exposed, so callers take row times from the raw pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

# CameraInfo distortion_model -> accepted numbers of coefficients
DISTORTION_MODELS = {
    "plumb_bob": (4, 5),
    "rational_polynomial": (8,),
    "equidistant": (4,),
}
# the iterative inverse, run to convergence (OpenCV's default stops after 5 steps, which leaves
# wide-angle corners pixels off)
_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


@dataclass(frozen=True)
class LensModel:
    """A distortion model and its coefficients (CameraInfo's ``distortion_model`` and ``d``)."""

    model: str
    coeffs: tuple[float, ...]

    def __post_init__(self):
        if self.model not in DISTORTION_MODELS:
            raise ValueError(f"unsupported distortion model {self.model!r} (supported: "
                             f"{', '.join(DISTORTION_MODELS)})")  # fmt: skip
        counts = DISTORTION_MODELS[self.model]
        if len(self.coeffs) not in counts:
            raise ValueError(f"distortion model {self.model} takes "
                             f"{' or '.join(map(str, counts))} coefficients, got "
                             f"{len(self.coeffs)}")  # fmt: skip
        if not np.isfinite(self.coeffs).all():
            raise ValueError(f"non-finite distortion coefficients {list(self.coeffs)}")

    @staticmethod
    def create(model: str, coeffs) -> LensModel | None:
        """The lens of a CameraInfo; None when there is no distortion (all zeros, or model
        ``""``/``none`` with no coefficients). An equidistant lens with zero coefficients is
        still a fisheye (``r = f theta``), so it is kept."""
        c = tuple(float(x) for x in np.asarray(coeffs, float).ravel())
        if model in ("", "none") and not any(c):
            return None
        if model != "equidistant" and not any(c):
            return None
        return LensModel(model, c)

    @property
    def _coeffs(self) -> np.ndarray:
        return np.asarray(self.coeffs, np.float64)

    def undistort(self, pts: np.ndarray, K: np.ndarray) -> np.ndarray:
        """Raw pixels (N, 2) -> undistorted pixels (N, 2) of the pinhole camera ``K``."""
        src = np.asarray(pts, np.float64).reshape(-1, 1, 2)
        if not len(src):
            return np.zeros((0, 2))
        if self.model == "equidistant":
            out = cv2.fisheye.undistortPoints(src, K, self._coeffs, P=K, criteria=_CRITERIA)
        else:
            out = cv2.undistortPoints(src, K, self._coeffs, P=K, criteria=_CRITERIA)
        return out.reshape(-1, 2)

    def distort(self, pts: np.ndarray, K: np.ndarray) -> np.ndarray:
        """Undistorted pixels (N, 2) of ``K`` -> the raw pixels the lens images them at."""
        pts = np.asarray(pts, np.float64).reshape(-1, 2)
        xn = (pts - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])
        if self.model == "equidistant":
            out = cv2.fisheye.distortPoints(xn.reshape(-1, 1, 2), K, self._coeffs)
            return out.reshape(-1, 2)
        rays = np.column_stack([xn, np.ones(len(xn))])
        out, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, self._coeffs)
        return out.reshape(-1, 2)


def as_lens(D) -> LensModel | None:
    """A :class:`LensModel` of a lens, or of bare plumb_bob / rational_polynomial coefficients
    (4/5 or 8 numbers, OpenCV's order); None for no distortion."""
    if D is None or isinstance(D, LensModel):
        return D
    D = np.asarray(D, float).ravel()
    if not len(D) or not np.any(D):
        return None
    return LensModel("rational_polynomial" if len(D) == 8 else "plumb_bob", tuple(D))


def undistort_points(pts: np.ndarray, K: np.ndarray, lens) -> np.ndarray:
    """Raw pixels (N, 2) to undistorted pixels of the same ``K`` (unchanged without a lens)."""
    lens = as_lens(lens)
    return np.asarray(pts, float) if lens is None else lens.undistort(pts, K)
