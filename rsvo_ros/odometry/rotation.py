"""A rolling-shutter camera that mostly turns: the rotation (and turn rate) of a frame against a
posed one from their shared tracks, what is left of the image motion (the translation
parallax), and the baseline direction that rotation implies.

Between consecutive frames of a hand-held walk (3 cm apart, points 2-8 m away) the pair
estimator has almost no baseline: its rotation came out 1-2.7 deg off per frame on rendered
walks and its translation direction 70-95 deg off, while a turning camera's fit of the same
tracks was 0.1-0.4 deg off. A global-shutter rotation fit cannot tell such pairs from ones with
parallax (a shake that changes the turn rate between frames leaves pixels of wobble), so each
frame's rows turn here: ``R(s) = R Exp(s w)`` at row time ``s`` (optionally
``Exp(s w + s^2/2 a)``, the rate changing over the readout, for a strong shake), the posed
frame's rows as its state has them. The pairwise chain (odometry/pairwise.py) takes this fit
for pairs under a parallax threshold. Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rsvo_ros.core.geometry import so3_exp
from rsvo_ros.odometry.frame import FrameState


@dataclass
class RotationFit:
    R: np.ndarray  # (3, 3) world-from-camera at the reference row
    w: np.ndarray  # (3,) turn rate (rad/s) in the camera frame
    residual_px: np.ndarray  # (n,) image distance per shared track after the fit
    ok: bool
    a: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) change of the turn rate

    def row_rotations(self, s: np.ndarray) -> np.ndarray:
        """(n, 3, 3) world-from-camera of the rows at row times ``s`` (n,)."""
        s = np.asarray(s, float)[:, None]
        return self.R @ so3_exp(s * (self.w + 0.5 * s * self.a))

    @property
    def parallax_px(self) -> float:
        """Median residual: the image motion a turning camera cannot explain."""
        return float(np.median(self.residual_px)) if len(self.residual_px) else np.inf


def _skew(u: np.ndarray) -> np.ndarray:
    """(n, 3, 3) cross-product matrices of (n, 3) vectors."""
    out = np.zeros(u.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -u[..., 2], u[..., 1], -u[..., 0]
    out[..., 1, 0], out[..., 2, 0], out[..., 2, 1] = u[..., 2], -u[..., 1], u[..., 0]
    return out


def fit_rotation(posed: FrameState, x_posed: np.ndarray, s_posed: np.ndarray,
                 x: np.ndarray, s: np.ndarray, R0: np.ndarray, w0: np.ndarray, focal: float,
                 robust_px: float = 1.5, iterations: int = 6,
                 acceleration: bool = False) -> RotationFit:  # fmt: skip
    """Rotation and turn rate of a frame that sees the tracks ``x`` (n, 2, normalized) at row
    times ``s`` (n,), seen by the ``posed`` frame at ``x_posed`` / ``s_posed``, if it only
    turned since (its position is not a parameter). Gauss-Newton with a Cauchy loss of scale
    ``robust_px``, started from ``R0`` / ``w0`` (Jacobians to first order in the turn over
    the readout, a few degrees). ``acceleration``: the frame's turn rate may also change over
    its readout (``a``, the rows at ``Exp(s w + s^2/2 a)``); against the posed frame's rows
    that is the change of the two frames' accelerations."""
    R_rows, _ = posed.row_cameras(s_posed)
    rays = np.einsum("nij,nj->ni", R_rows, np.column_stack([x_posed, np.ones(len(x_posed))]))
    s = np.asarray(s, float)
    R, w = np.asarray(R0, float).copy(), np.asarray(w0, float).copy()
    a = np.zeros(3)
    n_par = 9 if acceleration else 6

    def project(R: np.ndarray, w: np.ndarray, a: np.ndarray):
        u = rays @ R  # the rays in the frame's reference-row camera (R^T ray)
        E = so3_exp(s[:, None] * (w + 0.5 * s[:, None] * a))  # (n, 3, 3): -> each row's
        q = np.einsum("nji,nj->ni", E, u)
        z = np.where(q[:, 2] > 1e-9, q[:, 2], np.nan)
        return (q[:, :2] / z[:, None] - x) * focal, u, E, q, z

    r, u, E, q, z = project(R, w, a)
    for _ in range(iterations):
        good = np.isfinite(r).all(axis=1)
        if good.sum() < n_par:
            return RotationFit(R, w, np.full(len(x), np.inf), False, a)
        # q = E^T Exp(-d) u: dq/dd = E^T [u]x, and the turn rate's dq/dw = s E^T [u]x
        dq = np.einsum("nji,njk->nik", E, _skew(u))
        zz = np.where(good, z, 1.0)
        dpi = np.zeros((len(x), 2, 3))
        dpi[:, 0, 0] = dpi[:, 1, 1] = focal / zz
        dpi[:, :, 2] = -focal * np.where(good[:, None], q[:, :2], 0.0) / zz[:, None] ** 2
        J_rot = np.einsum("nij,njk->nik", dpi, dq)
        blocks = [J_rot, J_rot * s[:, None, None]]
        if acceleration:
            blocks.append(J_rot * (0.5 * s**2)[:, None, None])
        J = np.concatenate(blocks, axis=2)
        e2 = np.sum(np.where(good[:, None], r, 0.0) ** 2, axis=1)
        wt = np.where(good, 1.0 / (1.0 + e2 / robust_px**2), 0.0)
        Jw = J * wt[:, None, None]
        H = np.einsum("nai,naj->ij", Jw, J) + 1e-9 * np.eye(n_par)
        g = np.einsum("nai,na->i", Jw, np.where(good[:, None], r, 0.0))
        step = -np.linalg.solve(H, g)
        if not np.isfinite(step).all():
            return RotationFit(R, w, np.full(len(x), np.inf), False, a)
        R, w = R @ so3_exp(step[:3]), w + step[3:6]
        if acceleration:
            a = a + step[6:]
        r, u, E, q, z = project(R, w, a)
        if np.linalg.norm(step[:3]) < 1e-5:  # 0.01 px at 1000 px focal
            break
    res = np.linalg.norm(r, axis=1)
    res[~np.isfinite(res)] = np.inf
    ok = bool(np.isfinite(R).all() and np.isfinite(w).all() and np.isfinite(a).all())
    return RotationFit(R, w, res, ok, a)


def direction_given_rotation(w_prev: np.ndarray, x_prev: np.ndarray, s_prev: np.ndarray,
                             fit: RotationFit, x: np.ndarray, s: np.ndarray,
                             robust_px: float, focal: float,
                             max_residual_px: float | None = None,
                             ) -> tuple[np.ndarray, float] | None:  # fmt: skip
    """The unit position of the second camera in the first one's frame (reference rows), its
    rotation known (``fit``, the first camera at the identity turning at ``w_prev``): each
    track's two rays and the baseline are coplanar, ``c . (a x b) = 0`` (least squares with a
    Cauchy loss), and most points lie in front of the first camera; with the share of tracks
    that do (the wrong direction of an ill-posed pair leaves many behind). None when
    degenerate. Good for a step along the view (a walker's); a step across it is mostly taken
    up by the fitted rotation (the small-baseline ambiguity) and its direction is not
    recovered. Tracks whose residual under the rotation fit is over ``max_residual_px`` (3x
    ``robust_px`` by default: with little translation a large one is an outlier) are left out;
    a pair with real translation parallax needs them all (inf)."""
    ones = np.ones((len(x), 1))
    a = np.einsum("nij,nj->ni", so3_exp(np.asarray(s_prev, float)[:, None] * w_prev),
                  np.hstack([x_prev, ones]))  # fmt: skip
    b = np.einsum("nij,nj->ni", fit.row_rotations(s), np.hstack([x, ones]))
    ab = np.cross(a, b)
    n = ab / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))[:, None]
    keep = fit.residual_px < (3.0 * robust_px if max_residual_px is None else max_residual_px)
    if keep.sum() < 8:
        return None
    wt = np.ones(len(x))
    for _ in range(4):
        A = n[keep] * wt[keep, None]
        c = np.linalg.svd(A, full_matrices=False)[2][-1]
        r = (n @ c) * focal  # about the image distance off the epipolar plane (px)
        wt = 1.0 / np.sqrt(1.0 + (r / robust_px) ** 2)
    depth_a = np.einsum("ni,ni->n", np.cross(c, b), ab) / np.maximum(
        np.einsum("ni,ni->n", ab, ab), 1e-300)  # fmt: skip
    front = float(np.mean(depth_a[keep] > 0))
    if front < 0.5:
        c, front = -c, 1.0 - front
    return (c, front) if np.isfinite(c).all() else None
