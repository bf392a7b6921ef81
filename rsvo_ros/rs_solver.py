"""Search for the 17-DOF rolling-shutter relative motion: batched Levenberg-Marquardt (Sec. 6).

Pure numpy. Many hypotheses advance together (:class:`rsvo_ros.rs_model.RSBatch`), which is
what makes the paper's RANSAC of LM runs (Algorithm 1) affordable in Python.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rsvo_ros import rs_kernels
from rsvo_ros.geometry import so3_log
from rsvo_ros.rs_model import (
    NUM_PARAMS,
    Correspondences,
    RSBatch,
    tangent_basis,
)

MAX_STEP_ROTATION_RAD = 0.05  # largest rotation change of one LM step (trust region)
MAX_STEP_TRANSLATION_RAD = 0.2  # largest change of the translation direction of one step
CHEIRALITY_POINTS = 100  # points that vote on a hypothesis' depth consistency
# LM iterations of the GS alternative of the model selection: it converges in a few where there
# is no RS distortion, and where it has not by then the RS fit wins anyway
GS_SELECTION_ITERATIONS = 5
PRIOR_NOISE_REF_PX = 1.0  # feature noise (px) at which the velocity prior has its full weight
PRIOR_FOCAL_REF_PX = 1000.0  # focal length at which the prior's scales are given (the bench's)


@dataclass
class LMOptions:
    """Levenberg-Marquardt and search settings of the RS model (RANSAC options are separate).

    The velocity prior and bounds are in image-independent units: rotation (rad) and
    displacement (baselines, ``|t| = 1``) over half the readout, i.e. over the largest row time
    ``s_max`` of the points from the reference row.
    """

    max_iterations: int = 30  # final refinements
    sample_iterations: int = 8  # per RANSAC hypothesis (paper mode: Algorithm 1's LM)
    lambda_init: float = 1e-3
    rel_tol: float = 1e-7  # stop when a hypothesis improves by less than this fraction
    robust_scale_px: float = 2.0  # Cauchy loss scale of the all-points refinement
    max_angular_velocity: float = 5.0  # rad/s (286 deg/s): bound of the search
    max_readout_translation: float = 5.0  # baselines over half the readout: bound
    prior_rotation_rad: float = 0.3  # prior std of the rotation over half the readout
    prior_translation: float = 20.0  # prior std of the displacement over half the readout
    max_rotation_change_rad: float = 0.1  # how far (5.7 deg) a run may rotate from its start
    init_thresholds_px: tuple[float, ...] = (1.0, 8.0)  # extra GS starts (fast mode)
    samples_per_start: int = 8  # fast mode: LM runs on random samples from each GS start
    sample_size: int = 40  # fast mode: correspondences per sample
    sample_difference_iterations: int = 4  # fast mode: first with only velocity differences
    sample_full_iterations: int = 4  # fast mode: then all 17 DOF
    polish_rounds: int = 1  # final refinements on the inliers with the noise-scaled prior
    # With the frames' interval known (a video stream), the prior is centred on the constant
    # velocity of the pair's own motion instead of zero (the paper's source mentions, commented
    # out, taking the velocities from the nearest frames), with these scales of the departure
    # from it over half the readout, in the units of prior_* (at a 1000 px focal length): the
    # translation 130x tighter (on 16 synthetic vehicle sequences at 500 px a translation scale
    # of 0.05 to 0.15 did best, 0.5 clearly worse; a rotation scale of 0.015 worse, 0.05 to 0.5
    # alike). 0: keep the zero-mean prior.
    motion_prior_rotation_rad: float = 0.15
    motion_prior_translation: float = 0.15
    model_selection_aic: float = 2.0  # GS instead of RS unless the velocities earn this (0: off)


def velocity_prior(corr: Correspondences, sigma_rotation_rad: float,
                   sigma_translation: float) -> np.ndarray:
    """Inverse std (12,) of a prior on ``[w_p, v_p, w_c, v_c]`` (see LMOptions), in the units
    of the Sampson errors (pixels) at the focal length ``PRIOR_FOCAL_REF_PX``: it scales with
    the focal length, so the prior keeps its weight against the residuals at any resolution."""
    s_max = corr.s_max * corr.focal / PRIOR_FOCAL_REF_PX
    pw, pv = s_max / sigma_rotation_rad, s_max / sigma_translation
    return np.repeat([pw, pv, pw, pv], 3)


def constant_velocity(state: RSBatch, frame_interval: float) -> np.ndarray:
    """(B, 12) ``[w_p, v_p, w_c, v_c]`` of a camera that moves between the two frames'
    reference rows at constant velocity: ``X_curr = R X_prev + t`` over ``frame_interval`` s.

    The previous camera turns by ``R^T`` and moves its centre to ``-R^T t`` (its own frame);
    the body-frame rate is the same in both frames, the velocity of the centre is ``-R^T t``
    per interval in the previous frame and ``-t`` in the current one.
    """
    w = so3_log(np.transpose(state.R, (0, 2, 1))) / frame_interval
    v_c = -state.t / frame_interval
    v_p = np.einsum("bji,bj->bi", state.R, v_c)
    return np.concatenate([w, v_p, w, v_c], axis=1)


def difference_basis() -> np.ndarray:
    """(17, 11) basis that moves the two frames' velocities only in opposite directions.

    From two views the difference of the frames' velocities is well observed and their common
    part is not; solving for the difference first keeps LM in the right basin.
    """
    B = np.zeros((NUM_PARAMS, 11))
    B[:5, :5] = np.eye(5)
    B[5:11, 5:11] = 0.5 * np.eye(6)
    B[11:17, 5:11] = -0.5 * np.eye(6)
    return B


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
    :func:`rsvo_ros.rs_kernels.residuals_batch`; equal to
    :func:`rsvo_ros.rs_model.sampson_residuals`)."""
    return rs_kernels.residuals_batch(*_kernel_args(state, corr), _cam(corr))


def depths(state: RSBatch, corr: Correspondences) -> tuple[np.ndarray, np.ndarray]:
    """(B, N) depths in both frames (compiled; equal to :func:`rsvo_ros.rs_model.rs_depths`)."""
    return rs_kernels.depths_batch(*_kernel_args(state, corr))


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
    compiled kernel :func:`rsvo_ros.rs_kernels.lm_batch`. Returns the states, their costs
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
    R, t, vel, cost, iters = rs_kernels.lm_batch(
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
    (either sign: ``(t, v)`` and ``-(t, v)`` fit equally, see :func:`fix_sign`)."""
    front, behind = _depth_sign_counts(state, corr, mask)
    return np.maximum(front, behind) / np.maximum(mask.sum(axis=1), 1)


def fix_sign(state: RSBatch, corr: Correspondences, mask: np.ndarray) -> RSBatch:
    """Cheirality: ``E_i -> -E_i`` under ``(t, v_p, v_c) -> -(t, v_p, v_c)``; keep the sign
    that puts most of the (B, N) ``mask``'s points in front of both cameras."""
    front, behind = _depth_sign_counts(state, corr, mask)
    sign = np.where(behind > front, -1.0, 1.0)
    vel = state.vel.copy()
    vel[:, 3:6] *= sign[:, None]
    vel[:, 9:12] *= sign[:, None]
    return RSBatch(state.R.copy(), state.t * sign[:, None], vel)


def _random_samples(n: int, count: int, size: int, rng: np.random.Generator) -> np.ndarray:
    """(count, size) distinct indices per row."""
    return np.argsort(rng.random((count, n)), axis=1)[:, :size]


@dataclass
class SearchResult:
    state: RSBatch  # B = 1
    iterations: int
    hypotheses: int


def search_paper(corr: Correspondences, start: RSBatch, iterations: int, sample_size: int,
                 threshold_px: float, lm: LMOptions, rng: np.random.Generator) -> SearchResult:
    """Algorithm 1: from the GS pose with zero velocities, LM on ``iterations`` random samples
    of ``sample_size`` correspondences; the hypothesis with the most inliers (Sampson distance
    below ``threshold_px`` on all points) wins and is refined on its inliers."""
    limits = SearchLimits(lm.max_angular_velocity, lm.max_readout_translation / corr.s_max)
    idx = _random_samples(len(corr), iterations, sample_size, rng)
    hyps = start.take(np.zeros(iterations, dtype=int))
    hyps, _, it = levenberg_marquardt(hyps, corr, lm.sample_iterations, idx=idx,
                                      lambda_init=lm.lambda_init, limits=limits)
    e = residuals(hyps, corr)
    counts = np.count_nonzero(np.abs(e) < threshold_px, axis=1)
    best = hyps.take(int(np.argmax(counts)))
    inl = np.abs(e[int(np.argmax(counts))]) < threshold_px
    total = it
    if inl.sum() >= NUM_PARAMS + 3:
        best, _, it2 = levenberg_marquardt(best, corr.subset(inl), lm.max_iterations,
                                           lambda_init=lm.lambda_init, rel_tol=lm.rel_tol,
                                           limits=limits)
        total += it2
    return SearchResult(best, total, iterations)


def search_fast(corr: Correspondences, starts: RSBatch, threshold_px: float, lm: LMOptions,
                rng: np.random.Generator, frame_interval: float | None = None) -> SearchResult:
    """Multi-start search (the default).

    From each GS start, ``samples_per_start`` LM runs on random samples (first with only the
    difference of the frames' velocities free, then all 17 DOF), all advanced as one batch with
    the velocity prior and bounds and within ``max_rotation_change_rad`` of their start. The
    hypothesis with consistent depths and the lowest robust cost on all points wins; it is
    refined on all points (Cauchy loss), then on its inliers.

    The velocity prior is zero-mean (``prior_*``) for frames of unknown timing. With
    ``frame_interval`` (s between the frames of a video stream) it is centred on the constant
    velocity of each hypothesis' own motion (:func:`constant_velocity`, re-centred before every
    refinement) with the ``motion_prior_*`` stds, and every run starts there.
    """
    n_starts, k = len(starts), lm.samples_per_start
    scale = lm.robust_scale_px
    moving = (frame_interval is not None and frame_interval > 0
              and min(lm.motion_prior_rotation_rad, lm.motion_prior_translation) > 0)
    prior = None
    if moving:
        prior = np.sqrt(len(corr)) * velocity_prior(corr, lm.motion_prior_rotation_rad,
                                                    lm.motion_prior_translation)
    elif lm.prior_rotation_rad > 0 and lm.prior_translation > 0:
        prior = np.sqrt(len(corr)) * velocity_prior(corr, lm.prior_rotation_rad,
                                                    lm.prior_translation)

    def centre(state: RSBatch) -> np.ndarray | None:
        return constant_velocity(state, frame_interval) if moving else None

    size = min(lm.sample_size, len(corr))
    prior_s = None if prior is None else prior * np.sqrt(size / len(corr))
    origin = np.repeat(np.arange(n_starts), k)
    hyps = starts.take(origin)
    if moving:
        hyps.vel = centre(hyps)
    idx = _random_samples(len(corr), len(hyps), size, rng)
    limits = SearchLimits(lm.max_angular_velocity, lm.max_readout_translation / corr.s_max,
                          starts.R[origin], lm.max_rotation_change_rad)
    hyps, _, it1 = levenberg_marquardt(hyps, corr, lm.sample_difference_iterations, idx=idx,
                                       lambda_init=lm.lambda_init, robust_scale=scale,
                                       prior_inv_sigma=prior_s, basis=difference_basis(),
                                       limits=limits, prior_mean=centre(hyps))
    hyps, _, it2 = levenberg_marquardt(hyps, corr, lm.sample_full_iterations, idx=idx,
                                       lambda_init=lm.lambda_init, robust_scale=scale,
                                       prior_inv_sigma=prior_s, limits=limits,
                                       prior_mean=centre(hyps))
    e = residuals(hyps, corr)
    cost = cauchy_cost(e, scale)
    if prior is not None:
        mu = centre(hyps)
        cost = cost + ((hyps.vel if mu is None else hyps.vel - mu) ** 2) @ prior**2
    check = _random_samples(len(corr), 1, min(CHEIRALITY_POINTS, len(corr)), rng)[0]
    consistent = cheirality_fraction(hyps, corr.subset(check),
                                     np.abs(e[:, check]) < 3.0 * scale) >= 0.75
    order = np.lexsort((cost, ~consistent))
    b = int(order[0])
    best = hyps.take(b)
    final_limits = SearchLimits(limits.w_max, limits.v_max, starts.R[origin[b]][None],
                                lm.max_rotation_change_rad)
    best, _, it3 = levenberg_marquardt(best, corr, lm.max_iterations,
                                       lambda_init=lm.lambda_init, rel_tol=lm.rel_tol,
                                       robust_scale=scale, prior_inv_sigma=prior,
                                       limits=final_limits, prior_mean=centre(best))
    best, it4 = _polish(best, corr, threshold_px, lm, prior, final_limits, centre)
    if lm.model_selection_aic > 0:
        # Are the velocities supported by the data? The GS model (zero velocities, 5 DOF)
        # refined from the RS pose on all points; keep the RS fit only if it lowers the cost by
        # more than 12 extra parameters fitting noise would (Akaike: aic * 12 * sigma^2).
        gs = RSBatch(best.R.copy(), best.t.copy(), np.zeros_like(best.vel))
        gs, _, it5 = levenberg_marquardt(gs, corr, GS_SELECTION_ITERATIONS,
                                         lambda_init=lm.lambda_init,
                                         rel_tol=lm.rel_tol, robust_scale=scale,
                                         basis=np.eye(NUM_PARAMS)[:, :5], limits=final_limits)
        e_rs, e_gs = residuals(best, corr)[0], residuals(gs, corr)[0]
        sigma = 1.4826 * float(np.median(np.abs(e_rs)))
        gain = float(cauchy_cost(e_gs, scale) - cauchy_cost(e_rs, scale))
        if gain < lm.model_selection_aic * (NUM_PARAMS - 5) * sigma**2:
            best = gs
        it4 += it5
    total = it1 + it2 + it3 + it4
    return SearchResult(best, total, len(hyps))


def _polish(best: RSBatch, corr: Correspondences, threshold_px: float, lm: LMOptions,
            prior: np.ndarray | None, limits: SearchLimits,
            centre=lambda state: None) -> tuple[RSBatch, int]:  # fmt: skip
    """Refinements on the inliers of ``best`` with the prior scaled by the noise, centred on
    ``centre(best)`` (None: zero)."""
    it4 = 0
    for _ in range(lm.polish_rounds):
        # The prior matters in proportion to the noise (MAP: prior term ~ sigma^2): scale it by
        # the noise level the fit shows, so exact data is fitted exactly.
        e = residuals(best, corr)
        inl = np.abs(e[0]) < threshold_px
        if inl.sum() < NUM_PARAMS + 3:
            break
        sigma = 1.4826 * float(np.median(np.abs(e[0])))  # MAD of all residuals
        prior_i = None
        if prior is not None:
            noise = min(1.0, sigma / PRIOR_NOISE_REF_PX)
            prior_i = prior * np.sqrt(inl.sum() / len(corr)) * noise
        best, _, it = levenberg_marquardt(best, corr.subset(inl), lm.max_iterations,
                                          lambda_init=lm.lambda_init, rel_tol=lm.rel_tol,
                                          prior_inv_sigma=prior_i, limits=limits,
                                          prior_mean=centre(best))
        it4 += it
    return best, it4


def pose_covariance(state: RSBatch, corr: Correspondences, gs_only: bool = False) -> np.ndarray:
    """(6, 6) covariance of ``[rotation vector, t]`` of a single state (B = 1) from the
    Gauss-Newton Hessian of its Sampson errors on ``corr`` (the inliers), scaled by their
    residual variance: ``sigma^2 (J^T J)^-1``. The velocities are marginalised out (all 17 DOF)
    unless ``gs_only``. Infinite where the data cannot constrain the pose."""
    n = len(corr)
    dof = 5 if gs_only else NUM_PARAMS
    if n <= dof:
        return np.full((6, 6), np.inf)
    e, J = rs_kernels.residuals_and_jacobian(state.R[0], state.t[0], state.vel[0], corr.x_prev,
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
