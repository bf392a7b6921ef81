"""The data of the two-view RS problem: correspondences and states of the 17-DOF manifold.

Plain containers (pure numpy), shared by every layer of the two-view estimator: what the
compiled kernels take, what the search advances and what the numpy reference model checks.
Convention: ``X_curr = R X_prev + t`` between the two frames' cameras at the solver's reference
row (the principal point's row): row times are ``s = (r - row_ref) * tau``;
:func:`rsvo_ros.core.geometry.pose_from_row` converts results back to the row-0 convention of
CONTRACTS.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rsvo_ros.core.geometry import so3_exp

NUM_PARAMS = 17  # 3 rotation + 2 translation direction + 4 x 3 velocities (paper: 17 DOF)


@dataclass
class RSBatch:
    """B points of the 17-DOF RS relative-motion manifold at the solver's reference row.

    ``R`` (B, 3, 3); ``t`` (B, 3) unit norm; ``vel`` (B, 12) = ``[w_p, v_p, w_c, v_c]``
    (rad/s and units of ``t`` per second).
    """

    R: np.ndarray
    t: np.ndarray
    vel: np.ndarray

    @staticmethod
    def from_pose(R: np.ndarray, t: np.ndarray, vel: np.ndarray | None = None) -> RSBatch:
        R = np.asarray(R, float).reshape(-1, 3, 3)
        t = np.asarray(t, float).reshape(-1, 3)
        t = t / np.linalg.norm(t, axis=1, keepdims=True)
        v = np.zeros((len(R), 12)) if vel is None else np.asarray(vel, float).reshape(-1, 12)
        return RSBatch(R.copy(), t.copy(), v.copy())

    def __len__(self) -> int:
        return len(self.R)

    def take(self, idx) -> RSBatch:
        idx = np.atleast_1d(idx)
        return RSBatch(self.R[idx].copy(), self.t[idx].copy(), self.vel[idx].copy())

    def where(self, mask: np.ndarray, other: RSBatch) -> RSBatch:
        """Entries of ``other`` where ``mask`` (B,) is True, else ours."""
        return RSBatch(
            np.where(mask[:, None, None], other.R, self.R),
            np.where(mask[:, None], other.t, self.t),
            np.where(mask[:, None], other.vel, self.vel),
        )

    def retract(self, delta: np.ndarray) -> RSBatch:
        """Apply (B, 17) increments ``[dtheta(3), dt(2), dvel(12)]``.

        ``R <- R Exp(dtheta)``; ``t <- normalize(t + B dt)`` with ``B`` from
        :func:`tangent_basis`; velocities additive.
        """
        dR = so3_exp(delta[:, 0:3])
        t_new = self.t + np.einsum("bij,bj->bi", tangent_basis(self.t), delta[:, 3:5])
        t_new /= np.linalg.norm(t_new, axis=1, keepdims=True)
        return RSBatch(self.R @ dR, t_new, self.vel + delta[:, 5:17])


def tangent_basis(t: np.ndarray) -> np.ndarray:
    """(B, 3, 2) orthonormal bases of the unit sphere's tangent planes at (B, 3) ``t``."""
    t = t / np.linalg.norm(t, axis=-1, keepdims=True)
    helper = np.eye(3)[np.argmin(np.abs(t), axis=-1)]
    b1 = np.cross(t, helper)
    b1 /= np.linalg.norm(b1, axis=-1, keepdims=True)
    b2 = np.cross(t, b1)
    return np.stack([b1, b2], axis=-1)


@dataclass
class Correspondences:
    """Normalized bearings and row times of N correspondences, ready for the solver.

    ``x_prev``, ``x_curr``: (N, 3) ``K^-1 [u, v, 1]``; ``s_prev``, ``s_curr``: (N,) seconds from
    the reference row; ``focal``: pixels per normalized unit (for pixel-scaled residuals);
    ``ds_dy``: how a point's row time changes with its normalized ``y`` (``f_y tau``, s), which
    makes the Sampson error account for ``E_i`` moving with the point's row (0: the paper's
    constant ``E_i``).
    """

    x_prev: np.ndarray
    x_curr: np.ndarray
    s_prev: np.ndarray
    s_curr: np.ndarray
    focal: float
    ds_dy: float = 0.0

    def subset(self, idx: np.ndarray) -> Correspondences:
        return Correspondences(self.x_prev[idx], self.x_curr[idx], self.s_prev[idx],
                               self.s_curr[idx], self.focal, self.ds_dy)  # fmt: skip

    def __len__(self) -> int:
        return len(self.x_prev)

    @property
    def s_max(self) -> float:
        """Largest |row time| of the points from the reference row (s), at least 1e-12."""
        return max(float(np.max(np.abs(np.concatenate([self.s_prev, self.s_curr])))), 1e-12)


def make_correspondences(
    pts_prev: np.ndarray, pts_curr: np.ndarray, K: np.ndarray, line_delay: float, row_ref: float,
    rows_prev: np.ndarray | None = None, rows_curr: np.ndarray | None = None,
) -> Correspondences:  # fmt: skip
    """Pixels (N, 2) to :class:`Correspondences`; rows default to the pixel ``v`` coordinates
    (give the raw sensor rows when the points were undistorted)."""
    rows_prev = pts_prev[:, 1] if rows_prev is None else rows_prev
    rows_curr = pts_curr[:, 1] if rows_curr is None else rows_curr
    K_inv = np.linalg.inv(K)
    ones = np.ones((len(pts_prev), 1))
    x_prev = np.hstack([pts_prev, ones]) @ K_inv.T
    x_curr = np.hstack([pts_curr, ones]) @ K_inv.T
    focal = 0.5 * (K[0, 0] + K[1, 1])
    return Correspondences(
        x_prev,
        x_curr,
        (np.asarray(rows_prev, float) - row_ref) * line_delay,
        (np.asarray(rows_curr, float) - row_ref) * line_delay,
        float(focal),
        float(K[1, 1] * line_delay),
    )
