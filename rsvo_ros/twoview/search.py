"""The search for the 17-DOF rolling-shutter relative motion: starts, sampling, the velocity
prior and the model selection (Sec. 6 and Algorithm 1, and the fast multi-start mode).

Calls down to the GS fits (:mod:`rsvo_ros.twoview.essential`) for its starts and to the compiled
model (:mod:`rsvo_ros.twoview.solver`) for Levenberg-Marquardt, residuals and depths.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
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
# threads that fit the GS starts beside the caller, which fits the tolerant start meanwhile and
# then those no worker has begun (the machine class has 2 cores; 1 and 2 workers measured alike
# on the bench's pairs, and one leaves the other core to the node's tracking)
GS_START_WORKERS = 1
CANDIDATE_SEPARATION_DEG = 1.0  # sample hypotheses this far apart are distinct candidates
CHEIRALITY_POINTS = 100  # points that vote on a hypothesis' depth consistency
# LM iterations of the GS alternative of the model selection: it converges in a few where there
# is no RS distortion, and where it has not by then the RS fit wins anyway
GS_SELECTION_ITERATIONS = 5
AIC_FACTOR = 2.0  # model_selection "aic": Akaike's 2 per parameter
NULL_ITERATIONS = 8  # LM iterations of the null model's refinement (5 DOF, from a GS fit)
HELD_OUT_FOLDS = 3  # cross-validation folds of the test that decides RS against the null
HELD_OUT_MIN_POINTS = 10  # per fold
SELECTION_ITERATIONS = 5  # LM iterations of the refits without a fold, from the full fits
# robust scale of the selection: this many sigmas of the GS fit (the Cauchy loss's constant for
# 95 % efficiency under Gaussian noise)
SELECTION_SCALE_SIGMAS = 2.385
SELECTION_SCALE_MIN_PX = 0.25
SELECTION_Z = 2.0  # RS wins when its held-out cost is lower by this many standard errors
# ... and by at least this much per point (px^2, robust): a gain that matters. Held-out gains
# measured (README): 0.002-0.008 on the real pairs and below 0.04 on the realistic synthetic
# pairs, where the RS fit moved the pose away from the truth; 0.097 and more in the paper's
# experiment from level 2 on
MIN_GAIN_PX2 = 0.05
CLEAR_GAIN_PX2 = 0.5  # an in-sample gain this large on ...
CLEAR_SHARE = 0.6  # ... this share of the points decides for RS without cross-validation
CLEAR_MARGIN = 3.0  # against the unrefined GS start, the clear gain times this
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
    """(count, size) distinct indices per row: the ``size`` smallest of ``n`` uniform draws
    per row, in the order of their draws (``argsort(draws)[:, :size]``, selected first)."""
    draws = rng.random((count, n))
    if size >= n:
        return np.argsort(draws, axis=1)[:, :size]
    part = np.argpartition(draws, size - 1, axis=1)[:, :size]
    order = np.argsort(np.take_along_axis(draws, part, axis=1), axis=1)
    return np.take_along_axis(part, order, axis=1)


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


def search_fast(corr: Correspondences, starts: Callable[[], RSBatch], threshold_px: float,
                lm: LMOptions, rng: np.random.Generator, frame_interval: float | None = None,
                null_start: RSBatch | None = None,
                local_starts: RSBatch | None = None) -> SearchResult:
    """The default search: where the RS distortion is small, a local one; else multi-start.

    ``null_start`` is a GS fit (the best one where the search is local). Where it explains
    the data to the tracks' noise
    (its robust scale, :func:`data_scale`, below ``lm.local_scale_px``: smooth real video,
    where both frames carry nearly the same distortion), the RS fit is refined on all points
    from it and from ``local_starts`` (e.g. the previous pair's motion), at that scale.
    Otherwise (:func:`_global_search`), from each of ``starts()`` (built only then: several GS
    fits), ``samples_per_start`` LM runs on random samples, the best few refined on all
    points.

    The velocity prior is zero-mean (``prior_*``) for frames of unknown timing. With
    ``frame_interval`` (s between the frames of a video stream) it is centred on the constant
    velocity of each hypothesis' own motion (:func:`constant_velocity`, re-centred before every
    refinement) with the ``motion_prior_*`` stds, and every run starts there.

    Model selection (``lm.model_selection``): ``"held_out"`` keeps the RS fit only if it
    predicts held-out points better than the model without free velocities fitted from
    ``null_start`` (:func:`fit_null`, :func:`rs_earns_its_velocities`); ``"aic"``: Akaike
    against a GS fit from the RS pose with the noise level of the RS fit; ``"off"``.
    """
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

    scale = lm.robust_scale_px
    sel_scale = scale if null_start is None else data_scale(null_start, corr, scale)
    limits = SearchLimits(lm.max_angular_velocity, lm.max_readout_translation / corr.s_max)
    local = null_start is not None and sel_scale < lm.local_scale_px
    if local:
        cands = null_start if local_starts is None else _stack([null_start, local_starts])
        best, anchor, it1 = _refine_candidates(cands, corr, lm, sel_scale, prior, limits,
                                               centre)
        hypotheses = len(cands)
    else:
        best, anchor, it1, hypotheses = _global_search(corr, starts(), lm, rng, prior, limits,
                                                       centre)
    final_limits = SearchLimits(limits.w_max, limits.v_max, anchor,
                                lm.max_rotation_change_rad)
    best, it2 = _polish(best, corr, threshold_px, lm, prior, final_limits, centre)
    it3 = 0
    if lm.model_selection == "held_out":
        # Are the velocities supported by the data, beyond what the model without free
        # velocities explains? (GS for a lone pair, the pair's own constant velocity for a
        # stream.) At the data's robust scale: real tracks are good to a few tenths of a
        # pixel, and a moving object's points 1-5 px off must not pull the fits.
        if local or null_start is not None and _clearly_rs(best, null_start, corr, sel_scale,
                                                           CLEAR_MARGIN):
            # the best GS fit (USAC_MAGSAC, with its own local optimisation) as it is; or the
            # GS start unrefined where the RS fit beats it by CLEAR_MARGIN x the clear gain
            # (refining it could not close that gap: the choice below is the same)
            null = null_start.take(0)
            null.vel = np.zeros_like(null.vel) if not moving else constant_velocity(
                null, frame_interval)
        else:
            null = fit_null(best if null_start is None else _stack([null_start, best]), corr,
                            lm, frame_interval, final_limits, sel_scale)
        if not (_clearly_rs(best, null, corr, sel_scale)
                or rs_earns_its_velocities(best, null, corr, lm, rng, frame_interval, prior,
                                           final_limits, sel_scale)):
            best = null
    elif lm.model_selection == "aic":
        # Akaike with the noise level of the RS fit: keep the RS fit only if it lowers the cost
        # by more than 12 extra parameters fitting noise would (aic * 12 * sigma^2).
        gs = RSBatch(best.R.copy(), best.t.copy(), np.zeros_like(best.vel))
        gs, _, it3 = levenberg_marquardt(gs, corr, GS_SELECTION_ITERATIONS,
                                         lambda_init=lm.lambda_init,
                                         rel_tol=lm.rel_tol, robust_scale=scale,
                                         basis=np.eye(NUM_PARAMS)[:, :5], limits=final_limits)
        e_rs, e_gs = residuals(best, corr)[0], residuals(gs, corr)[0]
        sigma = 1.4826 * float(np.median(np.abs(e_rs)))
        gain = float(cauchy_cost(e_gs, scale) - cauchy_cost(e_rs, scale))
        if gain < AIC_FACTOR * (NUM_PARAMS - 5) * sigma**2:
            best = gs
    return SearchResult(best, it1 + it2 + it3, hypotheses)


def data_scale(state: RSBatch, corr: Correspondences, ceiling: float) -> float:
    """The robust scale the data support around ``state`` (px): ``SELECTION_SCALE_SIGMAS``
    times the MAD-estimated sigma of its residuals, within [``SELECTION_SCALE_MIN_PX``,
    ``ceiling``]."""
    sigma = 1.4826 * float(np.median(np.abs(residuals(state, corr)[0])))
    return float(np.clip(SELECTION_SCALE_SIGMAS * sigma, SELECTION_SCALE_MIN_PX, ceiling))


def _stack(states: list[RSBatch]) -> RSBatch:
    return RSBatch(*(np.concatenate([getattr(s, f) for s in states]) for f in ("R", "t", "vel")))


def _refine_candidates(cands: RSBatch, corr: Correspondences, lm: LMOptions,
                       robust_scale: float, prior: np.ndarray | None, limits: SearchLimits,
                       centre) -> tuple[RSBatch, np.ndarray, int]:  # fmt: skip
    """Refine candidates on all points in one batch (each within the rotation bound around
    itself, the velocity prior centred by ``centre``); the lowest robust cost plus prior wins.
    Returns it, its anchor rotation (1, 3, 3) and the LM iterations."""
    cands = cands.take(np.arange(len(cands)))
    mu = centre(cands)
    if mu is not None:
        cands.vel = np.where(np.any(cands.vel, axis=1, keepdims=True), cands.vel, mu)
    return _refine_on_all(cands, cands.R.copy(), corr, lm, robust_scale, prior, limits, centre)


def _refine_on_all(cands: RSBatch, anchors: np.ndarray, corr: Correspondences, lm: LMOptions,
                   robust_scale: float, prior: np.ndarray | None, limits: SearchLimits,
                   centre) -> tuple[RSBatch, np.ndarray, int]:  # fmt: skip
    """LM on all points from each candidate, each within the rotation bound around its anchor
    ``anchors`` (B, 3, 3); the lowest robust cost plus prior wins. Returns it, its anchor
    (1, 3, 3) and the LM iterations."""
    lim = SearchLimits(limits.w_max, limits.v_max, anchors, lm.max_rotation_change_rad)
    refined, cost, it = levenberg_marquardt(cands, corr, lm.max_iterations,
                                            lambda_init=lm.lambda_init,
                                            rel_tol=lm.refine_rel_tol,
                                            robust_scale=robust_scale, prior_inv_sigma=prior,
                                            limits=lim, prior_mean=centre(cands))
    k = int(np.argmin(cost))
    return refined.take(k), anchors[k:k + 1], it


def _global_search(corr: Correspondences, starts: RSBatch, lm: LMOptions,
                   rng: np.random.Generator, prior: np.ndarray | None, limits: SearchLimits,
                   centre) -> tuple[RSBatch, np.ndarray, int, int]:  # fmt: skip
    """From each start, ``samples_per_start`` LM runs on random samples (first with only the
    difference of the frames' velocities free, then all 17 DOF), all advanced as one batch with
    the velocity prior and bounds and within ``max_rotation_change_rad`` of their start; the
    best ``final_candidates`` distinct ones with consistent depths are refined on all points
    (Cauchy loss) and the lowest cost wins. Returns it, its anchor (1, 3, 3), the LM iterations
    and the number of hypotheses."""
    n_starts, k = len(starts), lm.samples_per_start
    scale = lm.robust_scale_px
    size = min(lm.sample_size, len(corr))
    prior_s = None if prior is None else prior * np.sqrt(size / len(corr))
    origin = np.repeat(np.arange(n_starts), k)
    hyps = starts.take(origin)
    mu = centre(hyps)
    if mu is not None:
        hyps.vel = mu
    idx = _random_samples(len(corr), len(hyps), size, rng)
    lim = SearchLimits(limits.w_max, limits.v_max, starts.R[origin], lm.max_rotation_change_rad)
    hyps, _, it1 = levenberg_marquardt(hyps, corr, lm.sample_difference_iterations, idx=idx,
                                       lambda_init=lm.lambda_init, robust_scale=scale,
                                       prior_inv_sigma=prior_s, basis=difference_basis(),
                                       limits=lim, prior_mean=centre(hyps))
    hyps, _, it2 = levenberg_marquardt(hyps, corr, lm.sample_full_iterations, idx=idx,
                                       lambda_init=lm.lambda_init, robust_scale=scale,
                                       prior_inv_sigma=prior_s, limits=lim,
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
    # the sample runs are not converged: refine the best few distinct ones on all points
    eligible = order[consistent[order]] if consistent[order[0]] else order
    picks = [int(eligible[0])]
    cos_min = np.cos(np.radians(CANDIDATE_SEPARATION_DEG))
    far = np.ones(len(eligible), bool)
    while len(picks) < lm.final_candidates:
        # cos of the angle of R_i R_j^T: (trace - 1) / 2
        far &= (np.einsum("nij,ij->n", hyps.R[eligible], hyps.R[picks[-1]]) - 1) / 2 < cos_min
        if not far.any():
            break
        picks.append(int(eligible[np.argmax(far)]))
    best, anchor, it3 = _refine_on_all(hyps.take(np.array(picks)), starts.R[origin[picks]],
                                       corr, lm, scale, prior, limits, centre)  # fmt: skip
    return best, anchor, it1 + it2 + it3, len(hyps)


def fit_null(start: RSBatch, corr: Correspondences, lm: LMOptions,
             frame_interval: float | None, limits: SearchLimits | None = None,
             robust_scale: float | None = None) -> RSBatch:
    """The model without free velocities, refined from each of ``start`` (B states; the lowest
    robust cost wins): the GS model (zero velocities; Cauchy loss of ``robust_scale`` px,
    default ``lm.robust_scale_px``, on all of ``corr``) at the reference row. For a video
    stream (``frame_interval``) it carries the constant velocity of that motion
    (:func:`constant_velocity`): with smooth motion both frames have nearly the same
    distortion, which cancels in the reference-row motion (a GS fit is unbiased there), while
    the velocities follow from the motion over the interval. A fit with the velocities locked
    to the pose instead is biased when the line delay is off (on the real pairs with the
    assumed readout: 0.15 deg mean rotation error against 0.08)."""
    state, cost = _refit_null(start, corr, lm, frame_interval, limits,
                              robust_scale or lm.robust_scale_px, NULL_ITERATIONS)
    return state.take(int(np.argmin(cost)))


def _refit_null(start: RSBatch, corr: Correspondences, lm: LMOptions,
                frame_interval: float | None, limits: SearchLimits | None, robust_scale: float,
                iterations: int, idx: np.ndarray | None = None) -> tuple[RSBatch, np.ndarray]:
    """:func:`fit_null`'s refinement of every state of ``start`` (each on all of ``corr`` or on
    its rows ``idx[b]``, within the rotation bound around ``limits``' first anchor): the
    refined states (velocities zero, or the constant velocity of a stream) and their costs."""
    state = start.take(np.arange(len(start)))
    state.vel = np.zeros_like(state.vel)
    if limits is not None and limits.anchor_R is not None:
        limits = SearchLimits(limits.w_max, limits.v_max,
                              np.repeat(limits.anchor_R[:1], len(state), axis=0),
                              limits.max_rotation_change)  # fmt: skip
    state, cost, _ = levenberg_marquardt(state, corr, iterations, idx=idx,
                                         lambda_init=lm.lambda_init, rel_tol=lm.rel_tol,
                                         robust_scale=robust_scale,
                                         basis=np.eye(NUM_PARAMS)[:, :5], limits=limits)
    if frame_interval:
        state.vel = constant_velocity(state, frame_interval)
    return state, cost


def _clearly_rs(rs: RSBatch, null: RSBatch, corr: Correspondences, robust_scale: float,
                margin: float = 1.0) -> bool:
    """Whether the RS fit is so much better on most points that no cross-validation is
    needed: a mean robust gain of ``margin x CLEAR_GAIN_PX2`` per point (10 x what the test
    asks) on more than ``CLEAR_SHARE`` of the points, far beyond what 12 parameters fitted to
    noise give (in the paper's experiment from level 2 on, nearly always; on smooth real
    video, never)."""
    e_rs, e_null = residuals(rs, corr)[0], residuals(null.take(0), corr)[0]
    d = robust_scale**2 * (np.log1p((e_null / robust_scale) ** 2)
                           - np.log1p((e_rs / robust_scale) ** 2))
    return float(d.mean()) > margin * CLEAR_GAIN_PX2 and float(np.mean(d > 0)) > CLEAR_SHARE


def rs_earns_its_velocities(rs: RSBatch, null: RSBatch, corr: Correspondences, lm: LMOptions,
                            rng: np.random.Generator, frame_interval: float | None,
                            prior: np.ndarray | None, limits: SearchLimits,
                            robust_scale: float | None = None) -> bool:
    """Cross-validated test between the full RS fit and the null model (:func:`fit_null`).

    ``HELD_OUT_FOLDS``-fold cross-validation: both models are refitted without each fold
    (``SELECTION_ITERATIONS`` from their fits on all points) and judged on it, so every point
    is predicted once by fits that did not see it. The RS fit wins only if (1) its mean robust
    (Cauchy) cost per held-out point is lower by more than ``SELECTION_Z`` standard errors of
    the paired differences and by at least ``MIN_GAIN_PX2``, and (2) it predicts more than
    half of the points better, by as many standard errors (a sign test). No noise level is
    assumed. On real video, whose consecutive frames carry nearly the same distortion, the 12
    extra parameters mostly fit noise, and (2) keeps a cluster of structured outliers (a thin
    near object's edges, a moving object) from deciding: a real RS effect moves points all
    over the image.
    """
    n = len(corr)
    if n < HELD_OUT_FOLDS * HELD_OUT_MIN_POINTS:
        return True  # too few points to judge: keep what the search found
    scale = robust_scale or lm.robust_scale_px
    fold = rng.permutation(n) % HELD_OUT_FOLDS
    # the RS refits of all folds in one batch: each hypothesis sees its own training points
    # (as many for each fold: the smallest training set's size)
    size = n - int(np.bincount(fold).max())
    idx = np.stack([np.flatnonzero(fold != k)[:size] for k in range(HELD_OUT_FOLDS)])
    prior_t = None if prior is None else prior * np.sqrt(size / n)
    rs_k = rs.take(np.zeros(HELD_OUT_FOLDS, dtype=int))
    centre = constant_velocity(rs_k, frame_interval) if frame_interval else None
    lim = SearchLimits(limits.w_max, limits.v_max,
                       None if limits.anchor_R is None else
                       np.repeat(limits.anchor_R[:1], HELD_OUT_FOLDS, axis=0),
                       limits.max_rotation_change)  # fmt: skip
    rs_k, _, _ = levenberg_marquardt(rs_k, corr, SELECTION_ITERATIONS, idx=idx,
                                     lambda_init=lm.lambda_init, rel_tol=lm.rel_tol,
                                     robust_scale=scale, prior_inv_sigma=prior_t, limits=lim,
                                     prior_mean=centre)
    # the null refits likewise, in one batch
    null_k, _ = _refit_null(null.take(np.zeros(HELD_OUT_FOLDS, dtype=int)), corr, lm,
                            frame_interval, limits, scale, SELECTION_ITERATIONS, idx)
    # each point judged by the fits of the fold that did not see it
    own = (fold, np.arange(n))
    e_rs, e_null = residuals(rs_k, corr)[own], residuals(null_k, corr)[own]
    d = scale**2 * (np.log1p((e_null / scale) ** 2) - np.log1p((e_rs / scale) ** 2))
    gain = float(d.mean())
    lower_cost = gain > max(SELECTION_Z * float(d.std(ddof=1)) / np.sqrt(n), MIN_GAIN_PX2)
    most = float(np.mean(d > 0)) > 0.5 + SELECTION_Z * 0.5 / np.sqrt(n)
    return lower_cost and most


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


class GSStarts:
    """More GS starting points for the RS search, fitted on a worker thread from the start of
    an estimate while the caller fits the tolerant GS start and the rotation (OpenCV releases
    the GIL; the four fits take ~3 ms on one core): the RS distortion makes GS fits depend on
    the threshold and on which rows they see, and at strong distortion any one of them can be
    several degrees off.
    Fits with ``lm.init_thresholds_px`` on all points and with ``ransac.init_threshold_px`` on
    three row bands. :meth:`result` collects them, fitting itself those no worker has started
    (rather than wait idle), also after :meth:`cancel`, which drops those not started (a
    local search needs none, unless its best GS fit turns out worse than the tolerant one).

    ``best_fit`` (no arguments, a GS fit's ``(R, t, mask, ...)``) is the estimator's best GS
    fit, which it needs where the tolerant start leaves the points near the local search's
    scale (on video nearly always). With ``speculate`` it is begun first, beside the caller's
    tolerant fit, and :meth:`best` waits for it fitting extra starts meanwhile;
    :meth:`drop_best` drops it where it is not needed after all. Without, :meth:`best` fits it
    on the caller. The same fits either way: only where they run differs."""

    def __init__(self, corr: Correspondences, rows_from_ref: np.ndarray, ransac: RansacOptions,
                 lm: LMOptions, seed: int, min_inliers: int,
                 best_fit: Callable[[], tuple] | None = None, speculate: bool = False) -> None:
        jobs = [(np.ones(len(corr), bool), thr) for thr in lm.init_thresholds_px]
        height = max(float(np.ptp(rows_from_ref)), 1.0)
        edges = np.min(rows_from_ref) + height * np.array([0.0, 1 / 3, 2 / 3, 1.0 + 1e-9])
        for lo, hi in zip(edges[:-1], edges[1:], strict=True):
            jobs.append(((rows_from_ref >= lo) & (rows_from_ref < hi),
                         ransac.init_threshold_px))
        jobs = [(mask, thr) for mask, thr in jobs
                if mask.sum() >= max(min_inliers, 2 * MIN_POINTS_GS)]

        def fit(mask: np.ndarray, thr: float) -> RSBatch | None:
            # cv2.setRNGSeed inside is per thread in OpenCV: the same fits as sequentially
            R, t, inl, _, _ = estimate_gs_opencv(corr.subset(mask), thr, ransac.confidence,
                                                  ransac.init_max_iterations, seed, INIT_METHOD)
            return RSBatch.from_pose(R, t) if inl.sum() >= min_inliers and np.linalg.norm(
                t) > 0 else None

        pool = _gs_pool()
        self._best_fit = best_fit
        self._best = pool.submit(best_fit) if speculate and best_fit is not None else None
        self._jobs = [(fit, mask, thr) for mask, thr in jobs]
        self._futures = [pool.submit(*job) for job in self._jobs]
        self._fitted_here: dict[int, RSBatch | None] = {}

    def _fit_one_here(self) -> bool:
        """Fit the last start no worker has begun on the caller; False: none left."""
        for i in reversed(range(len(self._futures))):
            if i not in self._fitted_here and self._futures[i].cancel():
                fit, mask, thr = self._jobs[i]
                self._fitted_here[i] = fit(mask, thr)
                return True
        return False

    def best(self) -> tuple:
        """The best GS fit: the speculative one (fitting starts here while it runs, rather
        than wait idle), or fitted here."""
        if self._best_fit is None:
            raise ValueError("GSStarts was made without a best fit")
        if self._best is None or self._best.cancel():
            return self._best_fit()
        while not self._best.done() and self._fit_one_here():
            pass
        return self._best.result()

    def drop_best(self) -> None:
        if self._best is not None:
            self._best.cancel()

    def result(self) -> list[RSBatch]:
        # a fit still waiting for a worker runs here (from the last, while the workers take
        # the first ones): the same fits, in the caller's time that waiting would have spent
        while self._fit_one_here():
            pass
        fits = (self._fitted_here[i] if i in self._fitted_here else f.result()
                for i, f in enumerate(self._futures))
        return [s for s in fits if s is not None]

    def cancel(self) -> None:
        """Drop the extra starts no worker has begun (not the best fit)."""
        for i, f in enumerate(self._futures):
            if i not in self._fitted_here:
                f.cancel()


_GS_POOL: ThreadPoolExecutor | None = None
_GS_POOL_LOCK = threading.Lock()


def _gs_pool() -> ThreadPoolExecutor:
    global _GS_POOL
    with _GS_POOL_LOCK:
        if _GS_POOL is None:
            _GS_POOL = ThreadPoolExecutor(GS_START_WORKERS, thread_name_prefix="rsvo_gs_start")
        return _GS_POOL


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
