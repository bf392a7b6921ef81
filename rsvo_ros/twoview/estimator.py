"""Two-view relative pose for global- and rolling-shutter cameras (Lee & Yoon, Secs. 5-6).

Public entry point: :func:`estimate_relative_pose` (input checks, the GS/MVO baselines, the
result object). Pure numpy + OpenCV, no ROS. Data flows down: this module -> the search
(:mod:`~rsvo_ros.twoview.search`: starts, sampling, model selection) -> the compiled model
(:mod:`~rsvo_ros.twoview.solver`, :mod:`~rsvo_ros.twoview.kernels`: residuals, Jacobians, LM,
depths); the GS geometry (:mod:`~rsvo_ros.twoview.essential`) serves both.

Convention: ``X_curr = R X_prev + t`` between the row-0 cameras of the two frames, ``|t| = 1``;
each frame's instantaneous RS motion ``(w, v)`` in its row-0 frame, ``X_row0 = Exp(r tau w)
X_row_r + r tau v`` (CONTRACTS.md).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from rsvo_ros.core.geometry import pose_from_row
from rsvo_ros.twoview.essential import (
    essential,
    estimate_gs_opencv,
    estimate_mvo,
    rotation_only_residual_px,
    sampson_gs_px,
)
from rsvo_ros.twoview.options import LMOptions, RansacOptions
from rsvo_ros.twoview.search import (
    INIT_METHOD,
    GSStarts,
    data_scale,
    rotation_start,
    search_fast,
    search_paper,
)
from rsvo_ros.twoview.solver import depths, fix_sign, pose_covariance, residuals
from rsvo_ros.twoview.state import RSBatch, make_correspondences

__all__ = ["LMOptions", "RansacOptions", "RelativePoseResult", "estimate_relative_pose",
           "warm_up"]

MODELS = ("rs", "gs", "mvo")
RS_MODES = ("fast", "paper")
MIN_POINTS = {"gs": 5, "mvo": 8, "rs": 20}  # 5-point, 8-point, the paper's 20-point samples
# the GS model and the GS fit the RS model is weighed against: OpenCV's USAC with MAGSAC++
# scoring and local optimisation (on real pairs 0.08 deg mean rotation error where plain
# RANSAC gave 0.42; README, "Real pairs and realistic pairs")
GS_METHOD = cv2.USAC_MAGSAC
PARALLAX_TO_NOISE = 3.0  # parallax below this many times the GS fit's noise: no translation
# a tolerant GS start whose robust scale is below this many times LMOptions.local_scale_px is
# checked by the best GS fit before the search turns global (the paper experiment's pairs: 36
# of 108, 5.8 ms each, none turned local; BS-RSC pair_3's tolerant fits: 1.6-2.4 px where the
# best one leaves 0.72-0.74 px, depending on the KLT window)
LOCAL_CHECK_FACTOR = 3.0


@dataclass
class RelativePoseResult:
    """Result of :func:`estimate_relative_pose`.

    ``R`` (3, 3), ``t`` (3,) unit: ``X_curr = R X_prev + t`` at row 0. ``inliers`` (N,) bool.
    ``w_*`` rad/s and ``v_*`` (units of ``t`` per second) in each frame's row-0 camera frame;
    zeros for the GS models. ``ok`` False means no pose could be trusted: ``reason`` says why and
    ``R``/``t`` are identity/zero, never a made-up pose. ``depths_*`` (N,): each point's depth
    along its bearing in the camera of its own row, in units of ``|t| = 1`` (nan where it cannot
    be triangulated). ``covariance`` (6, 6): of the rotation vector (rad) and ``t`` (units of
    ``|t| = 1``) from the inliers' Gauss-Newton Hessian scaled by their residual variance.
    """

    ok: bool
    model: str
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))
    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    w_prev: np.ndarray = field(default_factory=lambda: np.zeros(3))
    v_prev: np.ndarray = field(default_factory=lambda: np.zeros(3))
    w_curr: np.ndarray = field(default_factory=lambda: np.zeros(3))
    v_curr: np.ndarray = field(default_factory=lambda: np.zeros(3))
    reason: str = ""
    iterations: int = 0  # RANSAC hypotheses (GS) or LM iterations summed over runs (RS)
    cost: float = float("nan")  # final mean squared Sampson error of the inliers, px^2
    time_s: float = 0.0
    row_ref: float = 0.0  # the solver's internal reference row (informative)
    depths_prev: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (N,) see below
    depths_curr: np.ndarray = field(default_factory=lambda: np.zeros(0))
    covariance: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.inf))

    @property
    def num_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))

    @property
    def inlier_ratio(self) -> float:
        return self.num_inliers / len(self.inliers) if len(self.inliers) else 0.0


def _validate(pts_prev, pts_curr, K, line_delay, model) -> tuple[np.ndarray, ...]:
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    pts_prev = np.asarray(pts_prev, dtype=float)
    pts_curr = np.asarray(pts_curr, dtype=float)
    K = np.asarray(K, dtype=float)
    for name, pts in (("pts_prev", pts_prev), ("pts_curr", pts_curr)):
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise ValueError(f"{name} must have shape (N, 2), got {pts.shape}")
    if pts_prev.shape != pts_curr.shape:
        raise ValueError(
            f"pts_prev and pts_curr differ in shape: {pts_prev.shape} vs {pts_curr.shape}"
        )
    need = MIN_POINTS[model]
    if len(pts_prev) < need:
        raise ValueError(
            f"model {model!r} needs at least {need} correspondences, got {len(pts_prev)}"
        )
    for name, pts in (("pts_prev", pts_prev), ("pts_curr", pts_curr)):
        bad = ~np.isfinite(pts).all(axis=1)
        if bad.any():
            raise ValueError(
                f"{name} has {int(bad.sum())} non-finite (NaN/inf) rows, first at index "
                f"{int(np.argmax(bad))}"
            )
    if K.shape != (3, 3) or not np.isfinite(K).all():
        raise ValueError(f"K must be a finite (3, 3) matrix, got shape {K.shape}")
    if abs(np.linalg.det(K)) < 1e-12 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError("K is singular (focal lengths must be positive)")
    if not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise ValueError(f"K's last row must be [0, 0, 1], got {K[2].tolist()}")
    if not np.isfinite(line_delay) or line_delay < 0:
        raise ValueError(f"line_delay must be finite and >= 0 s/row, got {line_delay}")
    for name, pts in (("pts_prev", pts_prev), ("pts_curr", pts_curr)):
        if np.ptp(pts, axis=0).max() < 1e-9:
            raise ValueError(f"all points of {name} are identical")
    return pts_prev, pts_curr, K


def _validate_stream(frame_interval: float | None, predicted) -> None:
    """The video-stream arguments of :func:`estimate_relative_pose`."""
    if frame_interval is not None and not (np.isfinite(frame_interval) and frame_interval > 0):
        raise ValueError(f"frame_interval must be finite and > 0 s, got {frame_interval}")
    if predicted is None:
        return
    R, t = (np.asarray(x, float) for x in predicted)
    if (R.shape != (3, 3) or t.shape != (3,) or not np.isfinite(R).all()
            or not np.isfinite(t).all() or not np.linalg.norm(t) > 0):  # fmt: skip
        raise ValueError(f"predicted must be a finite (R (3, 3), t (3,)) with t != 0, got "
                         f"shapes {R.shape}, {t.shape}")


def estimate_relative_pose(
    pts_prev: np.ndarray,
    pts_curr: np.ndarray,
    K: np.ndarray,
    line_delay: float = 0.0,
    model: str = "rs",
    seed: int = 0,
    mode: str = "fast",
    ransac: RansacOptions | None = None,
    lm: LMOptions | None = None,
    min_inliers: int = 15,
    min_parallax_px: float = 0.5,
    rows_prev: np.ndarray | None = None,
    rows_curr: np.ndarray | None = None,
    frame_interval: float | None = None,
    predicted: tuple[np.ndarray, np.ndarray] | None = None,
) -> RelativePoseResult:
    """Relative pose of two frames from pixel correspondences.

    Convention: ``X_curr = R X_prev + t`` (row-0 cameras), ``|t| = 1``,
    ``x_curr^T E x_prev = 0``; the RS model's per-correspondence essential matrix is the paper's
    Sec. 5 ``E_rs`` (see :mod:`rsvo_ros.twoview.reference`).

    Args:
        pts_prev, pts_curr: (N, 2) float64 undistorted pixel coordinates; row = ``[:, 1]``.
        K: (3, 3) intrinsics.
        line_delay: seconds per image row (tau); 0 for a global shutter.
        model: ``"rs"`` (17-DOF RS essential matrix), ``"gs"`` (OpenCV 5-point USAC_MAGSAC +
            recoverPose) or ``"mvo"`` (the paper's baseline: normalized 8-point RANSAC).
        seed: seeds every random choice; equal inputs and seed give equal results.
        mode: RS only. ``"fast"`` (default): multi-start search from several GS fits
            (:func:`rsvo_ros.twoview.search.search_fast`). ``"paper"``: Algorithm 1,
            ``ransac.rs_iterations`` LM runs on random 20-point samples from the GS pose with
            zero velocities, inlier counting, then LM on the best hypothesis' inliers, with
            the paper's Sampson error (``E_i`` constant; fast mode adds its row dependence).
        min_inliers: fewer inliers than this gives ``ok=False``.
        min_parallax_px: median parallax (after removing the rotation) below this gives
            ``ok=False`` (pure rotation or no motion: the translation is undefined).
        rows_prev, rows_curr: (N,) sensor rows of the points when they differ from
            ``pts_*[:, 1]`` (points undistorted from a lens-distorted image keep the exposure
            time of their raw row).
        frame_interval: seconds between the frames (a video stream; RS fast mode only): the
            velocity prior is centred on the constant velocity of the pair's own motion
            (``LMOptions.motion_prior_*``) instead of zero. None: frames of unknown timing,
            velocities independent of the motion between them (the paper's experiment).
        predicted: RS fast mode: a motion ``(R, t)`` of the reference-row cameras (the
            principal point's row) expected for this pair, e.g. the previous pair's in a video
            stream: one more start of the search.

    Raises:
        ValueError: bad input (too few points, NaN/inf, shape mismatch, singular K, all points
            identical, unknown model or mode, a non-positive frame interval, a non-finite
            predicted motion).
    """
    t_start = time.perf_counter()
    pts_prev, pts_curr, K = _validate(pts_prev, pts_curr, K, line_delay, model)
    _validate_stream(frame_interval, predicted)
    if mode not in RS_MODES:
        raise ValueError(f"mode must be one of {RS_MODES}, got {mode!r}")
    ransac = ransac or RansacOptions()
    lm = lm or LMOptions()
    rng = np.random.default_rng(seed)
    row_ref = float(K[1, 2])  # the principal point's row, ~ the image centre
    corr = make_correspondences(pts_prev, pts_curr, K, line_delay, row_ref,
                                _rows(rows_prev, pts_prev), _rows(rows_curr, pts_curr))
    if mode == "paper":
        corr.ds_dy = 0.0  # the paper's Sampson error treats E_i as constant in the image
    n = len(corr)

    def finish(res: RelativePoseResult) -> RelativePoseResult:
        res.time_s = time.perf_counter() - t_start
        res.row_ref = row_ref if model == "rs" else 0.0
        if res.ok and not np.isfinite(np.concatenate([res.R.ravel(), res.t])).all():
            res.ok, res.reason = False, "non-finite pose"
        if not res.ok:
            res.R, res.t = np.eye(3), np.zeros(3)
        return res

    def failed(reason: str, inliers=None, iterations=0) -> RelativePoseResult:
        inl = np.zeros(n, bool) if inliers is None else inliers
        return finish(RelativePoseResult(False, model, inliers=inl, reason=reason,
                                         iterations=iterations))

    more_starts = None
    if model == "rs" and mode == "fast":
        # the global search's extra GS starts (four OpenCV fits), begun at once on a worker
        # thread while this one fits the tolerant GS start below; where that start shows the
        # RS distortion small (a local search), those the worker has not begun are dropped.
        # Where the last two estimates needed the best GS fit (below), it is begun first,
        # beside the tolerant fit (a video's pairs and the bench's cells come in runs alike)
        def best_fit() -> tuple:
            return estimate_gs_opencv(corr, ransac.threshold_px, ransac.confidence,
                                      ransac.null_max_iterations, seed, GS_METHOD)

        more_starts = GSStarts(corr, pts_prev[:, 1] - row_ref, ransac, lm, seed, min_inliers,
                               best_fit, speculate=_BEST_FIT_HINT.expected)
    if model == "mvo":
        R, t, mask, iters = estimate_mvo(corr, ransac.threshold_px, ransac.confidence,
                                          ransac.max_iterations, rng)
        E = essential(R, t)
    else:
        thr = ransac.threshold_px if model == "gs" else ransac.init_threshold_px
        max_it = ransac.max_iterations if model == "gs" else ransac.init_max_iterations
        method = GS_METHOD if model == "gs" else INIT_METHOD
        R, t, mask, iters, E = estimate_gs_opencv(corr, thr, ransac.confidence, max_it, seed,
                                                   method)
    has_pose = np.linalg.norm(t) > 0
    start = RSBatch.from_pose(R, t) if has_pose else None  # (a zero t: no pose, failed below)
    start_scale = None
    if more_starts is not None and has_pose:
        # where even the tolerant GS fit leaves the points far off (strong RS distortion), the
        # search is global and needs the extra starts
        start_scale = data_scale(start, corr, np.inf)
    if more_starts is not None and (start_scale is None or start_scale < lm.local_scale_px
                                    or mask.sum() < min_inliers):  # fmt: skip
        more_starts.cancel()
    # the tolerant start near the local search's scale: the best GS fit decides (below)
    needs_best = start_scale is not None and start_scale < LOCAL_CHECK_FACTOR * lm.local_scale_px
    if more_starts is not None and start_scale is not None:
        _BEST_FIT_HINT.note(needs_best)
        if not needs_best:
            more_starts.drop_best()
    if mask.sum() < min_inliers:
        return failed(f"too few inliers for a GS essential matrix ({int(mask.sum())})", mask,
                      iters)
    parallax, R_rot = rotation_only_residual_px(corr, rng)
    # the noise of the model RANSAC fitted (an upper bound: RS distortion adds to it)
    e_fit = sampson_gs_px(E, corr.x_prev, corr.x_curr, corr.focal)
    noise_px = float(np.median(e_fit[mask])) if has_pose else 0.0
    if parallax < max(min_parallax_px, PARALLAX_TO_NOISE * noise_px):
        if more_starts is not None:
            more_starts.cancel()
        return failed(f"insufficient parallax ({parallax:.2f} px after the best rotation, "
                      f"noise {noise_px:.2f} px): pure rotation or no motion", mask, iters)
    if not has_pose:
        return failed("no decomposition of the essential matrix puts the points in front of "
                      "both cameras", mask, iters)

    if model in ("gs", "mvo"):
        e_gs = sampson_gs_px(essential(R, t), corr.x_prev, corr.x_curr, corr.focal)
        depths_p, depths_c = depths(start, corr)
        return finish(RelativePoseResult(
            True, model, R, t, mask, iterations=iters, cost=float(np.mean(e_gs[mask] ** 2)),
            depths_prev=depths_p[0], depths_curr=depths_c[0],
            covariance=pose_covariance(start, corr.subset(mask), gs_only=True),
        ))  # fmt: skip

    null_start = None
    if mode == "fast":
        # the best GS fit (as model="gs"), where the model without free velocities starts;
        # where even the tolerant fit leaves the points far off (strong RS distortion: the
        # global search), that one does (MAGSAC then takes its iteration cap, ~5 ms). Where the
        # tolerant fit is near the local search's scale (below LOCAL_CHECK_FACTOR times it),
        # the best GS fit is made too and decides: on real tracks with a fifth of outliers a
        # tolerant fit can leave 2.2-3.3x the best one's scale (BS-RSC pair_3 with 13-19-px
        # KLT tracks: 1.6-2.4 against 0.72-0.74 px), and the global search then found RS fits
        # 4-5.4 deg off
        null_start = start
        if needs_best:
            R_g, t_g, mask_g, _, _ = more_starts.best()
            if mask_g.sum() >= min_inliers and np.linalg.norm(t_g) > 0:
                best = RSBatch.from_pose(R_g, t_g)
                if start_scale < lm.local_scale_px:
                    null_start = best
                elif data_scale(best, corr, np.inf) < lm.local_scale_px:
                    null_start = best  # local after all (search_fast decides by its scale)
                    if more_starts is not None:
                        more_starts.cancel()
    if mode == "paper":
        found = search_paper(corr, start, ransac.rs_iterations, ransac.rs_sample_size,
                             ransac.threshold_px, lm, rng)
    else:
        local = None if predicted is None else RSBatch.from_pose(*predicted)

        def starts() -> RSBatch:  # the global search's: several GS fits and a rotation fit
            extra = more_starts.result()  # dropped ones are fitted here if need be
            found = [start] + ([] if null_start is start else [null_start]) + extra + [
                rotation_start(corr, R_rot)] + ([] if local is None else [local])
            return RSBatch(*(np.concatenate([getattr(s, f) for s in found])
                             for f in ("R", "t", "vel")))  # fmt: skip

        found = search_fast(corr, starts, ransac.threshold_px, lm, rng, frame_interval,
                            null_start, local)
    lm_iters = found.iterations
    e = residuals(found.state, corr)
    inliers = np.abs(e[0]) < ransac.threshold_px
    state = fix_sign(found.state, corr, inliers[None])
    if inliers.sum() < min_inliers:
        return failed(f"too few RS inliers ({int(inliers.sum())})", inliers, lm_iters)
    vel = state.vel[0]
    R0, t0, (w_p, v_p, w_c, v_c) = pose_from_row(
        state.R[0], state.t[0], vel[0:3], vel[3:6], vel[6:9], vel[9:12], row_ref, line_delay
    )
    scale = np.linalg.norm(t0)
    if not np.isfinite(scale) or scale < 1e-12:
        return failed("degenerate RS solution (zero translation at row 0)", inliers, lm_iters)
    depths_p, depths_c = depths(state, corr)
    cov = pose_covariance(state, corr.subset(inliers))
    cov[3:, 3:] /= scale**2
    return finish(RelativePoseResult(
        True, "rs", R0, t0 / scale, inliers, w_p, v_p / scale, w_c, v_c / scale,
        iterations=lm_iters, cost=float(np.mean(e[0, inliers] ** 2)),
        depths_prev=depths_p[0] / scale, depths_curr=depths_c[0] / scale, covariance=cov,
    ))  # fmt: skip


class _BestFitHint:
    """Whether the last two RS estimates in this process needed the best GS fit (their
    tolerant starts near the local search's scale): the next one then begins it early, beside
    its tolerant fit. A fit begun and not needed holds the worker (1.7 ms on the bench's
    pairs, where levels mix; 1.2 ms gained where needed), so one estimate alone does not
    decide. It moves only where a fit runs, never what an estimate gives."""

    def __init__(self) -> None:
        self.last_two = (True, True)  # video: nearly every pair needs it

    @property
    def expected(self) -> bool:
        return all(self.last_two)

    def note(self, needed: bool) -> None:
        self.last_two = (self.last_two[1], needed)  # one assignment: threads may share it


_BEST_FIT_HINT = _BestFitHint()


def warm_up() -> float:
    """Compile (first run after an install, ~25 s on 2 cores) or load from numba's cache
    (~0.5 s) every solver kernel, by estimating one small synthetic RS pair. Returns seconds."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(0)
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    X = np.column_stack([rng.uniform(-4, 4, (120, 2)), rng.uniform(4, 12, 120)])
    pts = []
    for t in (np.zeros(3), np.array([0.3, 0.0, 0.1])):
        x = (X - t) @ K.T
        pts.append(x[:, :2] / x[:, 2:])
    estimate_relative_pose(pts[0], pts[1], K, 1e-5, model="rs", seed=0)
    return time.perf_counter() - t0


def _rows(rows: np.ndarray | None, pts: np.ndarray) -> np.ndarray:
    if rows is None:
        return pts[:, 1]
    rows = np.asarray(rows, dtype=float)
    if rows.shape != (len(pts),) or not np.isfinite(rows).all():
        raise ValueError(f"rows must be finite with shape ({len(pts)},), got {rows.shape}")
    return rows
