"""The rolling-shutter essential matrix of Lee & Yoon (Sec. 5) and its Sampson error (Sec. 6).

Pure numpy. Convention: ``X_curr = R X_prev + t`` between the two frames' cameras at a reference
row, ``x_curr^T E_i x_prev = 0`` per correspondence ``i``. Inside the solver, row times are
measured from a reference row ``row_ref`` (the principal point's row, near the image centre):
``s = (r - row_ref) * tau``; :func:`rsvo_ros.geometry.pose_from_row` converts the result back to
the row-0 convention of CONTRACTS.md.

Per correspondence, with ``Rp = Exp(s_p w_p)``, ``Rc = Exp(s_c w_c)`` (exact exponential, not
the paper's first-order ``I + s[w]x``):

    E_i = Rc^T [t + R (s_p v_p) - s_c v_c]x R Rp          (paper Sec. 5, transposed convention)

The Sampson error is that of the paper's Sec. 6, ``e_i = x_c^T E_i x_p / sqrt((E_i x_p)_1^2 +
(E_i x_p)_2^2 + (E_i^T x_c)_1^2 + (E_i^T x_c)_2^2)``, in normalized coordinates; multiply by the
focal length for pixels. Like the paper it treats ``E_i`` as constant when differentiating with
respect to the image coordinates (the row dependence is O(tau)).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rsvo_ros.geometry import so3_exp, so3_right_jacobian

NUM_PARAMS = 17  # 3 rotation + 2 translation direction + 4 x 3 velocities (paper: 17 DOF)


@dataclass
class RSState:
    """A point of the 17-DOF RS relative-motion manifold at the solver's reference row.

    ``t`` has unit norm; ``v_*`` are in units of ``t`` per second.
    """

    R: np.ndarray
    t: np.ndarray
    w_prev: np.ndarray
    v_prev: np.ndarray
    w_curr: np.ndarray
    v_curr: np.ndarray

    def copy(self) -> RSState:
        return RSState(*(np.array(a, dtype=float) for a in self.as_tuple()))

    def as_tuple(self) -> tuple[np.ndarray, ...]:
        return (self.R, self.t, self.w_prev, self.v_prev, self.w_curr, self.v_curr)

    def retract(self, delta: np.ndarray) -> RSState:
        """Apply a 17-vector increment ``[dtheta(3), dt(2), dw_p, dv_p, dw_c, dv_c]``.

        Rotation: ``R <- R Exp(dtheta)``; translation: ``t <- normalize(t + B dt)`` with ``B``
        from :func:`tangent_basis`; velocities additive.
        """
        B = tangent_basis(self.t)
        t_new = self.t + B @ delta[3:5]
        return RSState(
            self.R @ so3_exp(delta[0:3]),
            t_new / np.linalg.norm(t_new),
            self.w_prev + delta[5:8],
            self.v_prev + delta[8:11],
            self.w_curr + delta[11:14],
            self.v_curr + delta[14:17],
        )


def tangent_basis(t: np.ndarray) -> np.ndarray:
    """Two orthonormal (3,) columns spanning the tangent plane of the unit sphere at ``t``."""
    t = t / np.linalg.norm(t)
    helper = np.eye(3)[np.argmin(np.abs(t))]
    b1 = np.cross(t, helper)
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(t, b1)
    return np.stack([b1, b2], axis=1)


@dataclass
class Correspondences:
    """Normalized bearings and row times of N correspondences, ready for the solver.

    ``x_prev``, ``x_curr``: (N, 3) ``K^-1 [u, v, 1]``; ``s_prev``, ``s_curr``: (N,) seconds from
    the reference row; ``focal``: pixels per normalized unit (for pixel-scaled residuals).
    """

    x_prev: np.ndarray
    x_curr: np.ndarray
    s_prev: np.ndarray
    s_curr: np.ndarray
    focal: float

    def subset(self, idx: np.ndarray) -> Correspondences:
        return Correspondences(
            self.x_prev[idx], self.x_curr[idx], self.s_prev[idx], self.s_curr[idx], self.focal
        )

    def __len__(self) -> int:
        return len(self.x_prev)


def make_correspondences(
    pts_prev: np.ndarray, pts_curr: np.ndarray, K: np.ndarray, line_delay: float, row_ref: float
) -> Correspondences:
    """Pixels (N, 2) to :class:`Correspondences`; rows are the pixel ``v`` coordinates."""
    K_inv = np.linalg.inv(K)
    ones = np.ones((len(pts_prev), 1))
    x_prev = np.hstack([pts_prev, ones]) @ K_inv.T
    x_curr = np.hstack([pts_curr, ones]) @ K_inv.T
    focal = 0.5 * (K[0, 0] + K[1, 1])
    return Correspondences(
        x_prev,
        x_curr,
        (pts_prev[:, 1] - row_ref) * line_delay,
        (pts_curr[:, 1] - row_ref) * line_delay,
        float(focal),
    )


def sampson_residuals(
    state: RSState, corr: Correspondences, jacobian: bool = False
) -> tuple[np.ndarray, np.ndarray | None]:
    """Signed Sampson errors (N,) in pixels and, optionally, their Jacobian (N, 17).

    The Jacobian is analytic, with respect to the increment of :meth:`RSState.retract`.
    """
    R, t = state.R, state.t
    s_p, s_c = corr.s_prev, corr.s_curr
    phi_p = s_p[:, None] * state.w_prev[None, :]
    phi_c = s_c[:, None] * state.w_curr[None, :]
    Rp = so3_exp(phi_p)
    Rc = so3_exp(phi_c)
    q = np.einsum("nij,nj->ni", Rp, corr.x_prev)  # Rp x_p
    a = q @ R.T  # R Rp x_p
    b = np.einsum("nij,nj->ni", Rc, corr.x_curr)  # Rc x_c
    tp = s_p[:, None] * state.v_prev[None, :]
    T = t[None, :] + tp @ R.T - s_c[:, None] * state.v_curr[None, :]
    g = np.cross(T, a)  # [T]x a
    h = np.cross(b, T)  # -[T]x b
    n = np.einsum("ni,ni->n", b, g)  # x_c^T E x_p
    Ex = np.einsum("nji,nj->ni", Rc, g)  # Rc^T g = E x_p
    Rth = h @ R  # R^T h
    ETx = np.einsum("nji,nj->ni", Rp, Rth)  # Rp^T R^T h = E^T x_c
    d2 = Ex[:, 0] ** 2 + Ex[:, 1] ** 2 + ETx[:, 0] ** 2 + ETx[:, 1] ** 2
    d2 = np.maximum(d2, 1e-300)
    inv_d = 1.0 / np.sqrt(d2)
    e = corr.focal * n * inv_d
    if not jacobian:
        return e, None

    # The Sampson error is e = f n / sqrt(d2), with n = b.(T x a), d2 = |P Ex|^2 + |P ETx|^2
    # (P keeps the first two components). Every parameter moves a, b, T, and rotates Ex / ETx
    # (through Rc^T, Rp^T, R^T); collect the gradient of e with respect to those as vectors.
    u = Ex.copy()
    u[:, 2] = 0.0
    z = ETx.copy()
    z[:, 2] = 0.0
    U = np.einsum("nij,nj->ni", Rc, u)  # dEx = Rc^T dg (+ rotation of Rc^T)
    A = R @ Rp
    Z = np.einsum("nij,nj->ni", A, z)  # dETx = (R Rp)^T dh (+ rotations)
    k = (corr.focal * n * inv_d**3)[:, None]
    f_inv_d = (corr.focal * inv_d)[:, None]
    c_a = f_inv_d * h - k * np.cross(U, T)  # multiplies da
    c_b = f_inv_d * g - k * np.cross(T, Z)  # multiplies db
    c_T = f_inv_d * np.cross(a, b) - k * (np.cross(a, U) + np.cross(Z, b))  # multiplies dT
    c_Ex = -k * u  # multiplies the rotation term of Ex
    c_ETx = -k * z  # multiplies the rotation terms of ETx

    J = np.empty((len(e), NUM_PARAMS))
    # rotation, R <- R Exp(d): da = -R [q]x d, dT = -R [tp]x d, ETx gains Rp^T [R^T h]x d
    J[:, 0:3] = (
        np.cross(q, c_a @ R)
        + np.cross(tp, c_T @ R)
        + np.cross(np.einsum("nij,nj->ni", Rp, c_ETx), Rth)
    )
    # translation direction: dT = B d
    J[:, 3:5] = c_T @ tangent_basis(t)
    # w_prev: dRp = Rp [M_p d]x with M_p = s_p J_r(s_p w_p)
    M_p = s_p[:, None, None] * so3_right_jacobian(phi_p)
    y_p = np.einsum("nji,nj->ni", A, c_a)  # (R Rp)^T c_a
    J[:, 5:8] = np.einsum(
        "nji,nj->ni", M_p, np.cross(corr.x_prev, y_p) + np.cross(c_ETx, ETx)
    )
    # v_prev: dT = s_p R d
    J[:, 8:11] = s_p[:, None] * (c_T @ R)
    # w_curr: dRc = Rc [M_c d]x
    M_c = s_c[:, None, None] * so3_right_jacobian(phi_c)
    y_c = np.einsum("nji,nj->ni", Rc, c_b)
    J[:, 11:14] = np.einsum(
        "nji,nj->ni", M_c, np.cross(corr.x_curr, y_c) + np.cross(c_Ex, Ex)
    )
    # v_curr: dT = -s_c d
    J[:, 14:17] = -s_c[:, None] * c_T
    return e, J
