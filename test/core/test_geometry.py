"""Rotations and the RS camera model: invariants and known answers."""

import numpy as np
import pytest
from conftest import TOL

from rsvo_ros.core import geometry as geo


def test_exp_log_round_trip(rng):
    phi = rng.normal(size=(200, 3))
    phi *= (rng.uniform(0, 3.1, 200) / np.linalg.norm(phi, axis=1))[:, None]
    R = geo.so3_exp(phi)
    assert np.allclose(R @ np.swapaxes(R, -1, -2), np.eye(3), atol=TOL["roundtrip"])
    assert np.allclose(np.linalg.det(R), 1.0)
    assert np.allclose(geo.so3_log(R), phi, atol=1e-7)


def test_log_near_pi_and_zero():
    for axis in np.eye(3):
        R = geo.so3_exp(np.pi * axis)
        assert np.isclose(np.linalg.norm(geo.so3_log(R)), np.pi)
    assert np.allclose(geo.so3_log(np.eye(3)), 0.0)


def test_right_jacobian_first_order(rng):
    phi = rng.normal(size=3)
    d = 1e-7 * rng.normal(size=3)
    lhs = geo.so3_exp(phi + d)
    rhs = geo.so3_exp(phi) @ geo.so3_exp(geo.so3_right_jacobian(phi) @ d)
    assert np.abs(lhs - rhs).max() < 1e-12


def test_pose_at_row_round_trip(rng):
    R = geo.so3_exp(0.1 * rng.normal(size=3))
    t = rng.normal(size=3)
    w_p, v_p, w_c, v_c = rng.normal(size=(4, 3)) * [[1], [5], [1], [5]]
    R_m, t_m, vel_m = geo.pose_at_row(R, t, w_p, v_p, w_c, v_c, 359.5, 50e-6)
    R_0, t_0, vel_0 = geo.pose_from_row(R_m, t_m, *vel_m, 359.5, 50e-6)
    assert np.allclose(R_0, R, atol=TOL["roundtrip"])
    assert np.allclose(t_0, t, atol=TOL["roundtrip"])
    for a, b in zip(vel_0, (w_p, v_p, w_c, v_c), strict=True):
        assert np.allclose(a, b, atol=TOL["roundtrip"])


def test_pose_at_row_zero_is_identity(rng):
    R = geo.so3_exp(0.1 * rng.normal(size=3))
    t = rng.normal(size=3)
    R_m, t_m, _ = geo.pose_at_row(R, t, *rng.normal(size=(4, 3)), 0.0, 50e-6)
    assert np.allclose(R_m, R) and np.allclose(t_m, t)


def test_rs_projection_is_row_consistent(rng):
    """Each projected point was seen from the pose of the row it landed on (CONTRACTS.md)."""
    K = np.array([[1000.0, 0, 639.5], [0, 1000.0, 359.5], [0, 0, 1]])
    X = np.column_stack([rng.uniform(-5, 5, 300), rng.uniform(-3, 3, 300),
                         rng.uniform(4, 20, 300)])
    w, v = np.radians([40.0, -80.0, 30.0]), np.array([20.0, -30.0, 35.0])
    tau = 50e-6
    pts, _ = geo.project_rs(X, np.eye(3), np.zeros(3), K, tau, w, v, height=720)
    ok = np.isfinite(pts).all(axis=1)
    assert ok.sum() > 100
    R_r, t_r = geo.rs_row_pose(pts[ok, 1], tau, w, v)
    X_r = np.einsum("nji,nj->ni", R_r, X[ok] - t_r)  # X_row_r = R^T (X_row0 - t)
    proj = X_r[:, :2] / X_r[:, 2:] * 1000.0 + [639.5, 359.5]
    assert np.abs(proj - pts[ok]).max() < TOL["rs_projection_px"]


def test_rs_projection_without_motion_is_pinhole(rng):
    K = np.array([[800.0, 0, 320], [0, 800.0, 240], [0, 0, 1]])
    X = np.column_stack([rng.uniform(-1, 1, 50), rng.uniform(-1, 1, 50), rng.uniform(3, 6, 50)])
    pts, z = geo.project_rs(X, np.eye(3), np.zeros(3), K, 50e-6, np.zeros(3), np.zeros(3))
    assert np.allclose(pts, X[:, :2] / X[:, 2:] * 800 + [320, 240])
    assert np.allclose(z, X[:, 2])


@pytest.mark.parametrize("deg", [0.0, 1.0, 90.0, 179.0])
def test_rotation_angle(deg):
    R = geo.so3_exp(np.radians(deg) * np.array([0.0, 0.6, 0.8]))
    assert np.isclose(geo.rotation_angle_deg(R), deg, atol=1e-6)


def test_quaternion_from_matrix_is_scipys_canonical_quaternion(rng):
    """Every branch of Shepperd's method (random rotations, and rotations by ~pi about each
    axis, where the trace is smallest) against scipy, sign convention included."""
    from scipy.spatial.transform import Rotation

    mats = list(Rotation.random(300, random_state=1).as_matrix())
    for axis in np.eye(3):
        for angle in (np.pi, np.pi - 1e-3, -np.pi + 1e-3, 1e-9):
            mats.append(geo.so3_exp(axis * angle))
    mats.append(np.eye(3))
    for R in mats:
        q = geo.quat_xyzw_from_matrix(R)
        assert np.allclose(q, Rotation.from_matrix(R).as_quat(canonical=True), atol=1e-12)
    # a slightly non-orthonormal matrix (accumulated products) still gives a unit quaternion
    q = geo.quat_xyzw_from_matrix(geo.so3_exp(rng.normal(size=3)) * (1 + 1e-9))
    assert np.isclose(np.linalg.norm(q), 1.0)


def test_rigid_correction_is_rigid_even_when_chained_without_end(rng):
    """A window BA's correction, chained frame after frame (async mapping's pick-ups and the
    odometry frame): the plain product grew a rotation's departure from orthonormality about
    threefold per step; the correction's rotation is projected onto SO(3)."""
    T_from, T_to = np.eye(4), np.eye(4)
    T_from[:3, :3], T_from[:3, 3] = geo.so3_exp(rng.normal(size=3)), rng.normal(size=3)
    T_to[:3, :3], T_to[:3, 3] = geo.so3_exp(rng.normal(size=3)), rng.normal(size=3)
    D = geo.rigid_correction(T_from, T_to)
    assert np.allclose(D @ T_from, T_to, atol=1e-12)  # rigid inputs: the exact correction
    # a state corrected by the correction of its own last correction, 60 times (a pick-up
    # moves the state the next correction is measured from)
    state, plain = T_from.copy(), T_from.copy()
    for _ in range(60):
        step = np.eye(4)
        step[:3, :3], step[:3, 3] = geo.so3_exp(rng.normal(scale=0.01, size=3)), 0.01
        after, after_plain = step @ state, step @ plain
        state = geo.rigid_correction(state, after) @ state
        with np.errstate(over="ignore", invalid="ignore"):  # the plain product blows up
            plain = (after_plain @ geo.pose_inverse(plain)) @ plain
    drift = abs(np.linalg.det(state[:3, :3]) - 1.0)
    assert drift < 1e-12, drift
    # non-finite poses: no SVD failure, a non-finite correction the caller refuses
    bad = T_to.copy()
    bad[0, 0] = np.nan
    assert not np.isfinite(geo.rigid_correction(T_from, bad)).all()
    # the plain product: far from a rotation (NaN by now)
    with np.errstate(invalid="ignore"):
        assert not abs(np.linalg.det(plain[:3, :3]) - 1.0) < 1e-6


def test_interpolate_poses_between_stamps_and_not_across_gaps():
    R1 = geo.so3_exp(np.array([0.0, 0.0, 0.4]))
    T = np.stack([np.eye(4), np.eye(4), np.eye(4)])
    T[1, :3, :3], T[1, :3, 3] = R1, [1.0, 2.0, 0.0]
    T[2, :3, 3] = [5.0, 0.0, 0.0]
    stamps = np.array([100, 200, 1000])
    query = np.array([50, 100, 125, 150, 500, 1001])
    out = geo.interpolate_poses(stamps, T, query, max_gap_ns=300)
    assert sorted(out) == [100, 125, 150]  # before the first, in the gap, after the last: out
    assert np.array_equal(out[100], T[0])
    assert np.allclose(out[150][:3, 3], [0.5, 1.0, 0.0])
    assert np.allclose(geo.so3_log(out[150][:3, :3]), [0.0, 0.0, 0.2])  # half the turn
    assert np.allclose(geo.so3_log(out[125][:3, :3]), [0.0, 0.0, 0.1])
    assert np.allclose(out[125][:3, :3] @ out[125][:3, :3].T, np.eye(3))
