"""The odometry's twist (odometry/twist.py): body-frame velocities from consecutive poses, their
measured covariance, where there is none, and the twist of a rigidly attached frame."""

from __future__ import annotations

import numpy as np
import pytest

from rsvo_ros.core.geometry import pose_inverse, so3_exp
from rsvo_ros.odometry.twist import (
    Twist,
    TwistEstimator,
    TwistOptions,
    body_twist,
    twist_in_frame,
)


def _pose(R, p):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


def _moved(T, linear, angular, dt):
    """``T`` moved for ``dt`` s by a constant body twist (rotation and translation integrated
    separately, as body_twist reads them)."""
    R1 = T[:3, :3] @ so3_exp(np.asarray(angular) * dt)
    return _pose(R1, T[:3, 3] + R1 @ np.asarray(linear) * dt)


def test_body_twist_recovers_the_velocity_of_a_known_motion():
    rng = np.random.default_rng(0)
    for _ in range(20):
        T0 = _pose(so3_exp(rng.normal(size=3)), rng.normal(size=3))
        v, w, dt = rng.normal(size=3), rng.normal(size=3), 1 / 30
        linear, angular = body_twist(T0, _moved(T0, v, w, dt), dt)
        assert np.allclose(angular, w, atol=1e-9)
        assert np.allclose(linear, v, atol=1e-9)
    with pytest.raises(ValueError, match="dt must be positive"):
        body_twist(T0, T0, 0.0)


def test_a_frame_attached_to_the_camera_gets_the_twist_its_own_poses_give():
    """Base poses from camera poses through a fixed T_base_cam: their difference equals the
    camera twist carried over by twist_in_frame (to first order in dt)."""
    rng = np.random.default_rng(1)
    T_base_cam = _pose(so3_exp(np.array([-np.pi / 2, 0.0, -np.pi / 2]) * 0.7),
                       np.array([0.2, -0.1, 1.0]))  # fmt: skip
    T_cam_base = pose_inverse(T_base_cam)
    for _ in range(10):
        Tc0 = _pose(so3_exp(rng.normal(size=3)), rng.normal(size=3))
        v, w, dt = rng.normal(size=3), rng.normal(size=3), 1e-5
        Tc1 = _moved(Tc0, v, w, dt)
        lin_c, ang_c = body_twist(Tc0, Tc1, dt)
        Tb0, Tb1 = Tc0 @ T_cam_base, Tc1 @ T_cam_base  # the base's poses in the same world
        lin_b, ang_b = body_twist(Tb0, Tb1, dt)
        cov = np.diag(rng.uniform(0.1, 1.0, 6))
        out = twist_in_frame(Twist(lin_c, ang_c, cov), T_base_cam)
        assert np.allclose(out.angular, ang_b, atol=1e-4)
        assert np.allclose(out.linear, lin_b, atol=1e-4)
        # the covariance follows the same linear map: a rotation keeps its trace (angular)
        assert np.isclose(np.trace(out.covariance[3:, 3:]), np.trace(cov[3:, 3:]))
        assert np.allclose(out.covariance, out.covariance.T)
    unknown = twist_in_frame(Twist(), T_base_cam)
    assert not unknown.known


def test_the_estimator_says_unknown_until_it_has_measured_the_scatter():
    o = TwistOptions(min_samples=5)
    est = TwistEstimator(o)
    T = np.eye(4)
    dt_ns = 33_333_333
    v, w = np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.2, 0.0])
    out = []
    for k in range(10):
        out.append(est.update(k * dt_ns, T, continuous=k > 0))
        T = _moved(T, v, w, dt_ns * 1e-9)
    assert not out[0].known  # the first pose has no predecessor
    assert not any(t.known for t in out[1:o.min_samples + 1])
    assert all(t.known for t in out[o.min_samples + 1:])
    assert np.allclose(out[-1].angular, w, atol=1e-6)
    assert np.allclose(out[-1].linear, v, atol=1e-6)
    # a constant velocity has no scatter: the covariance is at its floor
    assert np.allclose(np.diag(out[-1].covariance), o.min_variance)


@pytest.mark.parametrize("break_kind", ["not continuous", "no pose", "gap", "backwards"])
def test_a_break_in_the_trajectory_gives_no_twist_across_it(break_kind):
    est = TwistEstimator(TwistOptions(min_samples=2, max_gap_s=0.5))
    T, dt_ns, stamp = np.eye(4), 33_333_333, 0
    v, w = np.array([0.1, 0.0, 1.0]), np.array([0.0, 0.1, 0.0])
    for k in range(6):
        assert est.update(stamp, T, continuous=k > 0).known == (k > 2)
        stamp += dt_ns
        T = _moved(T, v, w, dt_ns * 1e-9)
    if break_kind == "not continuous":  # a held, lost or re-found frame
        assert not est.update(stamp, T, continuous=False).known
    elif break_kind == "no pose":
        assert not est.update(stamp, None, continuous=True).known
    elif break_kind == "gap":
        stamp += 10**9
        assert not est.update(stamp, T, continuous=True).known
    else:
        stamp -= 3 * dt_ns
        assert not est.update(stamp, T, continuous=True).known
    # the next frames start over: unknown until the scatter is measured again
    stamp += dt_ns
    T = _moved(T, v, w, dt_ns * 1e-9)
    first_after = est.update(stamp, T, continuous=True)
    if break_kind == "no pose":
        assert not first_after.known  # the frame after a missing pose has no predecessor
    else:
        assert not first_after.known and np.isfinite(first_after.vector).all()


def test_the_covariance_measures_the_twists_noise():
    """Poses with white position noise: the published standard deviations follow the
    differences' scatter (within a factor of 2 of what the noise gives each twist)."""
    rng = np.random.default_rng(3)
    est = TwistEstimator(TwistOptions(window=200, min_samples=5))
    dt = 1 / 30
    sigma_p, sigma_r = 1e-3, 1e-3  # m, rad per pose
    out = []
    for k in range(200):
        R = so3_exp(rng.normal(0, sigma_r, 3))  # no turn: body and world axes agree
        p = np.array([0.0, 0.0, 1.0 * k * dt]) + rng.normal(0, sigma_p, 3)
        out.append(est.update(round(k * dt * 1e9), _pose(R, p), continuous=k > 0))
    std = np.sqrt(np.diag(out[-1].covariance))
    # the difference of two noisy poses: std sqrt(2) sigma / dt; consecutive twists share a pose,
    # so their change has variance 6 sigma^2 / dt^2 and half of it is 3 sigma^2 / dt^2
    expected_lin = np.sqrt(3.0) * sigma_p / dt
    expected_ang = np.sqrt(3.0) * sigma_r / dt
    assert np.all(std[:3] > 0.5 * expected_lin) and np.all(std[:3] < 2.0 * expected_lin)
    assert np.all(std[3:] > 0.5 * expected_ang) and np.all(std[3:] < 2.0 * expected_ang)
    # and the twist's own errors mostly fall within two of those standard deviations
    errs = np.array([t.vector - np.r_[0, 0, 1.0, 0, 0, 0] for t in out[20:]])
    assert np.mean(np.abs(errs) <= 2 * std) > 0.9
