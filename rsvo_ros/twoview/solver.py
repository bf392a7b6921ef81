"""The compiled RS model, as the search uses it: batched Levenberg-Marquardt on the Sampson
error (Sec. 6), residuals, depths, cheirality and the pose covariance.

Thin wrappers that hand :class:`rsvo_ros.twoview.state.RSBatch` states and
:class:`~rsvo_ros.twoview.state.Correspondences` to the numba kernels of
:mod:`rsvo_ros.twoview.kernels`. Many hypotheses advance together, which is what makes the
paper's RANSAC of LM runs (Algorithm 1) affordable in Python.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rsvo_ros.twoview import kernels
from rsvo_ros.twoview.state import NUM_PARAMS, Correspondences, RSBatch, tangent_basis

MAX_STEP_ROTATION_RAD = 0.05  # largest rotation change of one LM step (trust region)
MAX_STEP_TRANSLATION_RAD = 0.2  # largest change of the translation direction of one step
# Batches of fewer hypotheses run on the calling thread: a parallel loop waits for the other
# core's worker, and where that core is busy (the GS starts' OpenCV fits, the node's other
# thread) waking it cost more than its half of one hypothesis (data_scale's residuals on 500
# points: 1.3 ms parallel against 0.2 ms serial, README "Speed")
PARALLEL_MIN_BATCH = 2


def cauchy_cost(e: np.ndarray, scale: float | None) -> np.ndarray:
    """Sum over the last axis of the Cauchy loss ``c^2 log(1 + e^2/c^2)`` (squares if None)."""
    if scale is None:
        return np.sum(e**2, axis=-1)
    return np.sum(scale**2 * np.log1p((e / scale) ** 2), axis=-1)


def _kernel_args(state: RSBatch, corr: Correspondences) -> tuple:
    """The states and correspondences as the compiled kernels take them: C-contiguous
    float arrays, then ``x_prev, x_curr, s_prev, s_curr``."""
    return (np.ascontiguousarray(state.R, float), np.ascontiguousarray(state.t, float),
            np.ascontiguousarray(state.vel, float), corr.x_prev, corr.x_curr, corr.s_prev,
            corr.s_curr)  # fmt: skip


def _cam(corr: Correspondences) -> tuple[float, float]:
    """``(focal, ds_dy)`` for the kernels' Sampson error."""
    return float(corr.focal), float(corr.ds_dy)


def residuals(state: RSBatch, corr: Correspondences) -> np.ndarray:
    """(B, N) Sampson errors (px) of every hypothesis on every correspondence (compiled
    :func:`rsvo_ros.twoview.kernels.residuals_batch`; equal to
    :func:`rsvo_ros.twoview.reference.sampson_residuals`)."""
    run = kernels.residuals_batch if len(state) >= PARALLEL_MIN_BATCH else \
        kernels.residuals_serial
    return run(*_kernel_args(state, corr), _cam(corr))


def depths(state: RSBatch, corr: Correspondences) -> tuple[np.ndarray, np.ndarray]:
    """(B, N) depths in both frames (compiled; equal to
    :func:`rsvo_ros.twoview.reference.rs_depths`)."""
    return kernels.depths_batch(*_kernel_args(state, corr))


@dataclass
class SearchLimits:
    """What a step may not do: the physical bounds (``|w| <= w_max``, ``|v| <= v_max``) and
    the rotation away from ``anchor_R`` (B, 3, 3); plus, always, the trust region of one step
    (``MAX_STEP_ROTATION_RAD``, ``MAX_STEP_TRANSLATION_RAD``)."""

    w_max: float
    v_max: float
    anchor_R: np.ndarray | None = None  # (B, 3, 3)
    max_rotation_change: float = np.inf


def levenberg_marquardt(
    state: RSBatch,
    corr: Correspondences,
    iterations: int,
    idx: np.ndarray | None = None,
    lambda_init: float = 1e-3,
    rel_tol: float = 1e-9,
    robust_scale: float | None = None,
    prior_inv_sigma: np.ndarray | None = None,
    basis: np.ndarray | None = None,
    limits: SearchLimits | None = None,
    prior_mean: np.ndarray | None = None,
) -> tuple[RSBatch, np.ndarray, int]:
    """Minimise the (optionally Cauchy-robust) Sampson error of every hypothesis of a batch.

    Marquardt's damping ``(H + lambda diag(H)) d = -g`` per hypothesis, ``H = J^T W J``,
    ``g = J^T W e``, IRLS weights ``W`` of the robust loss, plus the velocity prior
    ``sum((p * (vel - prior_mean))^2)`` (``prior_mean`` (B, 12), default zero). ``basis``
    (17, k) restricts the steps to a subspace; ``limits`` rejects steps like a cost increase.
    Each hypothesis ``b`` uses all correspondences or the rows ``idx[b]``. Runs in the
    compiled kernel :func:`rsvo_ros.twoview.kernels.lm_batch`. Returns the states, their costs
    (B,) and the total iterations over the batch.
    """
    B = len(state)
    # fresh writable C arrays: one compiled signature of the kernel
    if idx is None:
        idx = np.tile(np.arange(len(corr), dtype=np.int64), (B, 1))
    idx = np.array(idx, dtype=np.int64, order="C")
    p2 = np.zeros(12) if prior_inv_sigma is None else np.asarray(prior_inv_sigma, float) ** 2
    mu = np.zeros((B, 12)) if prior_mean is None else prior_mean
    mu = np.array(np.broadcast_to(mu, (B, 12)), dtype=float, order="C")
    basis = np.eye(NUM_PARAMS) if basis is None else np.ascontiguousarray(basis, float)
    bounds = np.array([MAX_STEP_ROTATION_RAD, MAX_STEP_TRANSLATION_RAD, np.inf, np.inf, np.inf])
    anchor = state.R
    if limits is not None:
        bounds[2:4] = limits.w_max, limits.v_max
        if limits.anchor_R is not None:
            bounds[4] = limits.max_rotation_change
            anchor = np.broadcast_to(limits.anchor_R, state.R.shape)
    run = kernels.lm_batch if B >= PARALLEL_MIN_BATCH else kernels.lm_serial
    R, t, vel, cost, iters = run(
        *_kernel_args(state, corr), _cam(corr), idx, int(iterations),
        float(lambda_init), float(rel_tol),
        0.0 if robust_scale is None else float(robust_scale), p2, mu, basis, bounds,
        np.array(anchor, dtype=float, order="C"),
    )  # fmt: skip
    return RSBatch(R, t, vel), cost, int(iters.sum())


def _depth_sign_counts(state: RSBatch, corr: Correspondences,
                       mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(B,) counts of the (B, N) ``mask``'s points in front of / behind both cameras."""
    lam_p, lam_c = depths(state, corr)
    front = np.count_nonzero(mask & (lam_p > 0) & (lam_c > 0), axis=1)
    behind = np.count_nonzero(mask & (lam_p < 0) & (lam_c < 0), axis=1)
    return front, behind


def cheirality_fraction(state: RSBatch, corr: Correspondences, mask: np.ndarray) -> np.ndarray:
    """Fraction (B,) of the (B, N) ``mask``'s points whose depths agree in sign in both frames
    (either sign, point by point: ``(t, v)`` and ``-(t, v)`` fit equally, see
    :func:`fix_sign`, and where the velocities move the baseline of a row's cameras past zero,
    as at the paper's level 6, right solutions put some points behind both cameras; a wrong
    decomposition puts points in front of one camera and behind the other)."""
    front, behind = _depth_sign_counts(state, corr, mask)
    return (front + behind) / np.maximum(mask.sum(axis=1), 1)


def fix_sign(state: RSBatch, corr: Correspondences, mask: np.ndarray) -> RSBatch:
    """Cheirality: ``E_i -> -E_i`` under ``(t, v_p, v_c) -> -(t, v_p, v_c)``; keep the sign
    that puts most of the (B, N) ``mask``'s points in front of both cameras."""
    front, behind = _depth_sign_counts(state, corr, mask)
    sign = np.where(behind > front, -1.0, 1.0)
    vel = state.vel.copy()
    vel[:, 3:6] *= sign[:, None]
    vel[:, 9:12] *= sign[:, None]
    return RSBatch(state.R.copy(), state.t * sign[:, None], vel)


def pose_covariance(state: RSBatch, corr: Correspondences, gs_only: bool = False) -> np.ndarray:
    """(6, 6) covariance of ``[rotation vector, t]`` of a single state (B = 1) from the
    Gauss-Newton Hessian of its Sampson errors on ``corr`` (the inliers), scaled by their
    residual variance: ``sigma^2 (J^T J)^-1``. The velocities are marginalised out (all 17 DOF)
    unless ``gs_only``. Infinite where the data cannot constrain the pose."""
    n = len(corr)
    dof = 5 if gs_only else NUM_PARAMS
    if n <= dof:
        return np.full((6, 6), np.inf)
    e, J = kernels.residuals_and_jacobian(state.R[0], state.t[0], state.vel[0], corr.x_prev,
                                             corr.x_curr, corr.s_prev, corr.s_curr, _cam(corr))
    J = J[:, :dof]
    sigma2 = float(e @ e) / (n - dof)  # px^2; J is in px per parameter unit
    H = J.T @ J
    try:
        cov = np.linalg.inv(H + 1e-12 * np.trace(H) * np.eye(dof)) * max(sigma2, 1e-12)
    except np.linalg.LinAlgError:
        return np.full((6, 6), np.inf)
    B = tangent_basis(state.t)[0]  # t moves as B d (|t| = 1)
    out = np.zeros((6, 6))
    out[:3, :3] = cov[:3, :3]
    out[3:, 3:] = B @ cov[3:5, 3:5] @ B.T
    out[:3, 3:] = cov[:3, 3:5] @ B.T
    out[3:, :3] = out[:3, 3:].T
    return out if np.isfinite(out).all() else np.full((6, 6), np.inf)
