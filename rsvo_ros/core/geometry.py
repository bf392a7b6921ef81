"""Rotations and the rolling-shutter camera model, vectorized over leading axes.

Pure numpy. Conventions (``CONTRACTS.md``): camera optical frame (x right, y down, z forward);
a frame's instantaneous RS motion ``(w, v)`` is expressed in its row-0 camera frame and the
camera at image row ``r`` satisfies ``X_row0 = Exp(r*tau*w) @ X_row_r + r*tau*v``.
"""

from __future__ import annotations

import numpy as np

SMALL_ANGLE = 1e-8  # rad; below this the series expansions are used


def hat(phi: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrices ``[phi]x`` of (..., 3) vectors, shape (..., 3, 3)."""
    phi = np.asarray(phi, dtype=float)
    out = np.zeros(phi.shape[:-1] + (3, 3))
    out[..., 0, 1] = -phi[..., 2]
    out[..., 0, 2] = phi[..., 1]
    out[..., 1, 0] = phi[..., 2]
    out[..., 1, 2] = -phi[..., 0]
    out[..., 2, 0] = -phi[..., 1]
    out[..., 2, 1] = phi[..., 0]
    return out


def _sinc_terms(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``sin(t)/t``, ``(1-cos t)/t^2`` and ``(t - sin t)/t^3`` with safe small-angle limits."""
    small = theta < 1e-4
    t = np.where(small, 1.0, theta)
    t2 = t * t
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(t) / t)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(t)) / t2)
    c = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (t - np.sin(t)) / (t2 * t))
    return a, b, c


def so3_exp(phi: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation matrices ``Exp(phi)`` of (..., 3) rotation vectors, (..., 3, 3)."""
    phi = np.asarray(phi, dtype=float)
    theta = np.linalg.norm(phi, axis=-1)
    a, b, _ = _sinc_terms(theta)
    K = hat(phi)
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye + a[..., None, None] * K + b[..., None, None] * (K @ K)


def so3_right_jacobian(phi: np.ndarray) -> np.ndarray:
    """Right Jacobian ``J_r(phi)``: ``Exp(phi + d) ~= Exp(phi) Exp(J_r(phi) d)``, (..., 3, 3)."""
    phi = np.asarray(phi, dtype=float)
    theta = np.linalg.norm(phi, axis=-1)
    _, b, c = _sinc_terms(theta)
    K = hat(phi)
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye - b[..., None, None] * K + c[..., None, None] * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vectors of (..., 3, 3) rotation matrices (inverse of :func:`so3_exp`)."""
    R = np.asarray(R, dtype=float)
    flat = R.reshape(-1, 3, 3)
    cos = np.clip((np.trace(flat, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos)
    vee = np.stack(
        [
            flat[:, 2, 1] - flat[:, 1, 2],
            flat[:, 0, 2] - flat[:, 2, 0],
            flat[:, 1, 0] - flat[:, 0, 1],
        ],
        axis=-1,
    )
    sin = np.sin(theta)
    near_pi = (sin < 1e-6) & (theta > 1.0)
    scale = np.where(theta < 1e-8, 0.5, theta / (2.0 * np.where(sin < 1e-12, 1.0, sin)))
    phi = scale[:, None] * vee
    for i in np.nonzero(near_pi)[0]:  # theta ~ pi: the axis is a column of (R + I) / 2
        B = (flat[i] + np.eye(3)) / 2.0
        axis = B[:, np.argmax(np.diag(B))]
        phi[i] = np.pi * axis / np.linalg.norm(axis)
    return phi.reshape(R.shape[:-1])


def quat_xyzw_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(x, y, z, w)`` of a rotation matrix, ``w >= 0`` (for ``w = 0`` the
    first non-zero of x, y, z positive: scipy's canonical form). Shepperd's method: the
    largest of ``trace, R00, R11, R22`` picks the component divided by, so no division is
    by a small number. One matrix in ~10 us (scipy's ``Rotation`` takes ~140 us)."""
    m = np.asarray(R, float)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    k = int(np.argmax([tr, m[0, 0], m[1, 1], m[2, 2]]))
    if k == 0:
        w = 0.5 * np.sqrt(max(1.0 + tr, 0.0))
        f = 0.25 / w
        q = [(m[2, 1] - m[1, 2]) * f, (m[0, 2] - m[2, 0]) * f, (m[1, 0] - m[0, 1]) * f, w]
    elif k == 1:
        x = 0.5 * np.sqrt(max(1.0 + m[0, 0] - m[1, 1] - m[2, 2], 0.0))
        f = 0.25 / x
        q = [x, (m[0, 1] + m[1, 0]) * f, (m[0, 2] + m[2, 0]) * f, (m[2, 1] - m[1, 2]) * f]
    elif k == 2:
        y = 0.5 * np.sqrt(max(1.0 - m[0, 0] + m[1, 1] - m[2, 2], 0.0))
        f = 0.25 / y
        q = [(m[0, 1] + m[1, 0]) * f, y, (m[1, 2] + m[2, 1]) * f, (m[0, 2] - m[2, 0]) * f]
    else:
        z = 0.5 * np.sqrt(max(1.0 - m[0, 0] - m[1, 1] + m[2, 2], 0.0))
        f = 0.25 / z
        q = [(m[0, 2] + m[2, 0]) * f, (m[1, 2] + m[2, 1]) * f, z, (m[1, 0] - m[0, 1]) * f]
    q = np.array(q)
    q /= np.linalg.norm(q)
    lead = q[3] if q[3] != 0.0 else q[np.flatnonzero(q[:3])[0]]
    return -q if lead < 0 else q


def pose_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a (4, 4) rigid transform."""
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


def rigid_correction(T_from: np.ndarray, T_to: np.ndarray) -> np.ndarray:
    """(4, 4) ``T_to T_from^-1`` (the world-frame motion taking ``T_from`` to ``T_to``) with
    its rotation projected onto SO(3). Corrections like this are chained without end (each
    window BA's, frame after frame): an unprojected one grows a rotation's departure from
    orthonormality about threefold per step, measured 1e-16 to 1e-2 in 30 corrections.
    Non-finite inputs give the non-finite product, unprojected, for the caller to refuse."""
    D = T_to @ pose_inverse(T_from)
    if not np.isfinite(D).all():
        return D
    U, _, Vt = np.linalg.svd(D[:3, :3])
    D[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return D


def interpolate_poses(stamps_ns: np.ndarray, T: np.ndarray, query_ns: np.ndarray,
                      max_gap_ns: int) -> dict[int, np.ndarray]:  # fmt: skip
    """Poses (4, 4) at ``query_ns`` from ``T`` (N, 4, 4) at sorted ``stamps_ns``: the position
    linearly and the rotation along the geodesic between the two stamps around each query (a
    stamp equal to a query gives its pose as is). Queries outside the stamps, or between two
    more than ``max_gap_ns`` apart, are left out."""
    stamps = np.asarray(stamps_ns, np.int64)
    out: dict[int, np.ndarray] = {}
    if len(stamps) == 0:
        return out
    for q in np.asarray(query_ns, np.int64).tolist():
        j = int(np.searchsorted(stamps, q))
        if j < len(stamps) and stamps[j] == q:
            out[q] = np.array(T[j], float)
            continue
        if j == 0 or j == len(stamps) or stamps[j] - stamps[j - 1] > max_gap_ns:
            continue
        a = (q - stamps[j - 1]) / (stamps[j] - stamps[j - 1])
        T0, T1 = T[j - 1], T[j]
        Ti = np.eye(4)
        Ti[:3, :3] = T0[:3, :3] @ so3_exp(a * so3_log(T0[:3, :3].T @ T1[:3, :3]))
        Ti[:3, 3] = (1 - a) * T0[:3, 3] + a * T1[:3, 3]
        out[q] = Ti
    return out


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """Angle of (..., 3, 3) rotations in degrees (the paper's Rodrigues error metric)."""
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    return np.degrees(np.arccos(cos))


def angle_between_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two 3-vectors in degrees (nan if either is zero)."""
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na == 0.0 or nb == 0.0:
        return float("nan")
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b) / (na * nb), -1.0, 1.0))))


def rs_row_pose(
    rows: np.ndarray, line_delay: float, w: np.ndarray, v: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pose of the camera at image rows ``rows`` relative to row 0.

    Convention: ``X_row0 = R_row0_rowr @ X_row_r + t_row0_rowr`` with
    ``R_row0_rowr = Exp(r*tau*w)``, ``t_row0_rowr = r*tau*v`` (CONTRACTS.md).

    Returns ``R`` (N, 3, 3) and ``t`` (N, 3).
    """
    s = np.asarray(rows, dtype=float) * line_delay
    return so3_exp(s[:, None] * w[None, :]), s[:, None] * v[None, :]


def pose_at_row(
    R_curr_prev: np.ndarray,
    t_curr_prev: np.ndarray,
    w_prev: np.ndarray,
    v_prev: np.ndarray,
    w_curr: np.ndarray,
    v_curr: np.ndarray,
    row: float,
    line_delay: float,
) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, ...]]:
    """Re-express a row-0 relative RS motion at another reference row.

    Given ``X_curr0 = R X_prev0 + t`` and each frame's ``(w, v)`` in its row-0 frame, returns the
    relative pose between the two frames' cameras at ``row`` (``X_curr_m = R_m X_prev_m + t_m``)
    and the velocities expressed in those row frames: ``w`` unchanged (a rotation about its own
    axis), ``v_m = Exp(-row*tau*w) v``.
    """
    s = row * line_delay
    Rp = so3_exp(s * w_prev)
    Rc = so3_exp(s * w_curr)
    tp, tc = s * v_prev, s * v_curr
    # X_prev0 = Rp X_prev_m + tp ; X_curr0 = Rc X_curr_m + tc
    R_m = Rc.T @ R_curr_prev @ Rp
    t_m = Rc.T @ (R_curr_prev @ tp + t_curr_prev - tc)
    return R_m, t_m, (w_prev, Rp.T @ v_prev, w_curr, Rc.T @ v_curr)


def pose_from_row(
    R_m: np.ndarray,
    t_m: np.ndarray,
    w_prev: np.ndarray,
    v_prev_m: np.ndarray,
    w_curr: np.ndarray,
    v_curr_m: np.ndarray,
    row: float,
    line_delay: float,
) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, ...]]:
    """Inverse of :func:`pose_at_row`: from a reference-row relative motion back to row 0."""
    s = row * line_delay
    Rp = so3_exp(s * w_prev)
    Rc = so3_exp(s * w_curr)
    v_prev = Rp @ v_prev_m
    v_curr = Rc @ v_curr_m
    tp, tc = s * v_prev, s * v_curr
    R = Rc @ R_m @ Rp.T
    t = Rc @ t_m + tc - R @ tp
    return R, t, (w_prev, v_prev, w_curr, v_curr)


def project_rs_rows(
    X_world: np.ndarray,
    row_pose,
    K: np.ndarray,
    height: int | None = None,
    iterations: int = 50,
    tol_px: float = 1e-10,
) -> tuple[np.ndarray, np.ndarray]:
    """Exact rolling-shutter projection by fixed-point iteration on the row.

    ``row_pose(rows)`` gives the camera pose ``T_world_camera`` of image rows (n,) as
    ``R`` (n, 3, 3), ``p`` (n, 3). Finds ``r`` with ``row(project(X, pose(r))) = r``.

    Args:
        X_world: (N, 3) points.
        K: (3, 3) intrinsics.
        height: optional image height; rows are clipped to [0, height-1] during the iteration
            so points far outside the image do not diverge, and points outside are nan.

    Returns:
        ``pts`` (N, 2) pixel coordinates (nan where behind the camera, outside the rows or not
        converged) and ``depth`` (N,) the depth in the row's camera frame.
    """
    X_world = np.asarray(X_world, float)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    R0, p0 = row_pose(np.zeros(1))
    X_r = (X_world - p0[0]) @ R0[0]  # the row-0 camera frame: R^T (X - p)
    z = X_r[:, 2]
    rows = np.where(z > 1e-9, fy * X_r[:, 1] / np.where(z > 1e-9, z, 1.0) + cy, 0.0)
    converged = np.zeros(len(X_world), dtype=bool)
    active = np.flatnonzero(z > 1e-9)  # only points still moving are iterated
    for _ in range(iterations):
        if not len(active):
            break
        r = rows[active]
        if height is not None:
            r = np.clip(r, 0.0, height - 1.0)
        R_r, p_r = row_pose(r)
        X_a = np.einsum("nji,nj->ni", R_r, X_world[active] - p_r)  # R_r^T (X - p_r)
        X_r[active] = X_a
        z_a = X_a[:, 2]
        new_rows = fy * X_a[:, 1] / np.where(z_a > 1e-9, z_a, 1.0) + cy
        done = np.abs(new_rows - r) < tol_px
        rows[active] = new_rows
        converged[active] = done
        active = active[~done & (z_a > 1e-9)]
    z = X_r[:, 2]
    safe_z = np.where(z > 1e-9, z, 1.0)
    pts = np.stack([fx * X_r[:, 0] / safe_z + cx, fy * X_r[:, 1] / safe_z + cy], axis=1)
    bad = (z <= 1e-9) | ~converged
    if height is not None:
        bad |= (pts[:, 1] < 0) | (pts[:, 1] > height - 1)
    pts[bad] = np.nan
    return pts, z


def project_rs(
    X_world: np.ndarray,
    R_world_cam: np.ndarray,
    p_world_cam: np.ndarray,
    K: np.ndarray,
    line_delay: float,
    w: np.ndarray,
    v: np.ndarray,
    height: int | None = None,
    iterations: int = 30,
    tol_px: float = 1e-10,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`project_rs_rows` for a camera whose row-0 pose is ``(R_world_cam,
    p_world_cam)`` and whose row ``r`` sees the world from ``X_row0 = Exp(r*tau*w) X_row_r +
    r*tau*v`` (CONTRACTS.md)."""

    def row_pose(rows):
        R_0r, t_0r = rs_row_pose(rows, line_delay, w, v)
        return R_world_cam @ R_0r, p_world_cam + t_0r @ R_world_cam.T

    return project_rs_rows(X_world, row_pose, K, height, iterations, tol_px)
