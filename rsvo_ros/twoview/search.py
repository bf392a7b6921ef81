"""The search for the 17-DOF rolling-shutter relative motion: starts, sampling, the velocity
prior and the model selection (Sec. 6 and Algorithm 1, and the fast multi-start mode).

Calls down to the GS fits (:mod:`rsvo_ros.twoview.essential`) for its starts and to the compiled
model (:mod:`rsvo_ros.twoview.solver`) for Levenberg-Marquardt, residuals and depths.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from rsvo_ros.core.geometry import so3_log
from rsvo_ros.twoview.essential import MIN_POINTS_GS, estimate_gs_opencv
from rsvo_ros.twoview.options import LMOptions, RansacOptions
from rsvo_ros.twoview.solver import (
    SearchLimits,
    cauchy_cost,
    cheirality_fraction,
    levenberg_marquardt,
    residuals,
)
from rsvo_ros.twoview.state import NUM_PARAMS, Correspondences, RSBatch

# GS starts of the RS model: OpenCV's USAC with local optimisation finds a good GS fit of RS
# data (inlier ratio ~35-75 %) in 1-2 ms where plain RANSAC takes 7-35 ms.
INIT_METHOD = cv2.USAC_FAST
CHEIRALITY_POINTS = 100  # points that vote on a hypothesis' depth consistency
# LM iterations of the GS alternative of the model selection: it converges in a few where there
# is no RS distortion, and where it has not by then the RS fit wins anyway
GS_SELECTION_ITERATIONS = 5
PRIOR_NOISE_REF_PX = 1.0  # feature noise (px) at which the velocity prior has its full weight
PRIOR_FOCAL_REF_PX = 1000.0  # focal length at which the prior's scales are given (the bench's)


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


def gs_starts(corr: Correspondences, rows_from_ref: np.ndarray, ransac: RansacOptions,
               lm: LMOptions, seed: int, min_inliers: int) -> list[RSBatch]:
    """More GS starting points for the RS search: the RS distortion makes GS fits depend on
    the threshold and on which rows they see, and at strong distortion any one of them can be
    several degrees off. Fits with other thresholds and on three row bands."""
    starts = []
    jobs = [(np.ones(len(corr), bool), thr) for thr in lm.init_thresholds_px]
    height = max(float(np.ptp(rows_from_ref)), 1.0)
    edges = np.min(rows_from_ref) + height * np.array([0.0, 1 / 3, 2 / 3, 1.0 + 1e-9])
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        jobs.append(((rows_from_ref >= lo) & (rows_from_ref < hi), ransac.init_threshold_px))
    for mask, thr in jobs:
        if mask.sum() < max(min_inliers, 2 * MIN_POINTS_GS):
            continue
        R, t, inl, _, _ = estimate_gs_opencv(corr.subset(mask), thr, ransac.confidence,
                                              ransac.init_max_iterations, seed, INIT_METHOD)
        if inl.sum() >= min_inliers and np.linalg.norm(t) > 0:
            starts.append(RSBatch.from_pose(R, t))
    return starts


def rotation_start(corr: Correspondences, R: np.ndarray) -> RSBatch:
    """A start that does not come from a GS essential matrix: the rotation-only fit's rotation
    (under strong RS distortion GS fits can be several degrees off) and, given it, the
    translation of least algebraic epipolar error, ``t . (R x_p  x  x_c) = 0`` (IRLS)."""
    M = np.cross(corr.x_prev @ R.T, corr.x_curr)
    w = np.ones(len(M))
    for _ in range(3):
        _, _, Vt = np.linalg.svd(M * w[:, None], full_matrices=False)
        t = Vt[-1]
        r = np.abs(M @ t)
        w = 1.0 / np.maximum(r, np.median(r) + 1e-12)
    return RSBatch.from_pose(R, t)
