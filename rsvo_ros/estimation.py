"""Two-view relative pose for global- and rolling-shutter cameras (Lee & Yoon, Secs. 5-6).

Public entry point: :func:`estimate_relative_pose`. Pure numpy + OpenCV, no ROS.

Convention: ``X_curr = R X_prev + t`` between the row-0 cameras of the two frames, ``|t| = 1``;
each frame's instantaneous RS motion ``(w, v)`` in its row-0 frame, ``X_row0 = Exp(r tau w)
X_row_r + r tau v`` (CONTRACTS.md).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from rsvo_ros.geometry import pose_from_row, so3_exp, so3_log
from rsvo_ros.rs_model import (
    NUM_PARAMS,
    Correspondences,
    RSState,
    make_correspondences,
    sampson_residuals,
)

MODELS = ("rs", "gs", "mvo")
RS_MODES = ("fast", "paper")
MIN_POINTS = {"gs": 5, "mvo": 8, "rs": 20}  # 5-point, 8-point, the paper's 20-point samples
PAPER_RANSAC_ITERATIONS = 500  # Algorithm 1
PAPER_SAMPLE_SIZE = 20  # Sec. 6: "20 feature point correspondences as the input of RANSAC"


@dataclass
class RansacOptions:
    """Robust-estimation settings, kept apart from the optimizer's (PoseLib style)."""

    threshold_px: float = 1.0  # Sampson distance of an inlier, pixels
    max_iterations: int = 1000  # hypotheses of the GS baselines (OpenCV, MVO)
    confidence: float = 0.999
    rs_iterations: int = PAPER_RANSAC_ITERATIONS  # paper mode: LM runs on random 20-point samples
    rs_sample_size: int = PAPER_SAMPLE_SIZE
    init_threshold_px: float = 3.0  # GS initialisation of the RS model tolerates RS distortion
    init_max_iterations: int = 200


@dataclass
class LMOptions:
    """Levenberg-Marquardt settings of the RS model's Sampson-error minimisation."""

    max_iterations: int = 30
    sample_iterations: int = 8  # per 20-point RANSAC hypothesis (paper mode)
    lambda_init: float = 1e-3
    rel_tol: float = 1e-9  # stop when the cost decreases by less than this fraction
    robust_scale_px: float = 2.0  # Cauchy loss scale of the all-points refinement
    max_angular_velocity: float = 5.0  # rad/s (286 deg/s); bounds the search, see _solve_rs
    max_readout_translation: float = 5.0  # baselines (|t| = 1) over half the readout
    prior_rotation_rad: float = 0.03  # velocity prior: rotation over half the readout
    prior_translation: float = 1.0  # velocity prior: baselines over half the readout
    max_rotation_change_rad: float = 0.35  # how far (20 deg) LM may rotate away from a GS start
    subsample: int = 150  # correspondences used to compare the starting points (fast mode)
    init_thresholds_px: tuple[float, ...] = (1.0, 8.0)  # extra GS starts (fast mode)


@dataclass
class RelativePoseResult:
    """Result of :func:`estimate_relative_pose`.

    ``R`` (3, 3), ``t`` (3,) unit: ``X_curr = R X_prev + t`` at row 0. ``inliers`` (N,) bool.
    ``w_*`` rad/s and ``v_*`` (units of ``t`` per second) in each frame's row-0 camera frame;
    zeros for the GS models. ``ok`` False means no pose could be trusted: ``reason`` says why and
    ``R``/``t`` are identity/zero, never a made-up pose.
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

    @property
    def num_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))

    @property
    def inlier_ratio(self) -> float:
        return self.num_inliers / len(self.inliers) if len(self.inliers) else 0.0


# --------------------------------------------------------------------------- input checks


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


# --------------------------------------------------------------------------- GS baselines


def _sampson_gs_px(E: np.ndarray, x_prev: np.ndarray, x_curr: np.ndarray, focal: float):
    """Sampson distances (…, N) of normalized points for (…, 3, 3) essential matrices."""
    Ex = x_prev @ np.swapaxes(E, -1, -2)  # (…, N, 3): E x_p
    ETx = x_curr @ E  # E^T x_c
    num = np.einsum("...ni,ni->...n", Ex, x_curr)
    den = Ex[..., 0] ** 2 + Ex[..., 1] ** 2 + ETx[..., 0] ** 2 + ETx[..., 1] ** 2
    return focal * np.abs(num) / np.sqrt(np.maximum(den, 1e-300))


def _pose_from_essential(
    E: np.ndarray, x_prev: np.ndarray, x_curr: np.ndarray, mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray, int]:
    """Cheirality check of the four decompositions (OpenCV recoverPose on normalized points)."""
    p = x_prev[mask, :2].astype(np.float64)
    c = x_curr[mask, :2].astype(np.float64)
    n_good, R, t, _ = cv2.recoverPose(E, p, c, np.eye(3))
    return R, t.ravel() / max(np.linalg.norm(t), 1e-300), int(n_good)


def _estimate_gs_opencv(corr: Correspondences, threshold_px: float, confidence: float,
                        max_iterations: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:  # noqa: E501
    """OpenCV's 5-point RANSAC on normalized points, then recoverPose. Returns R, t, mask, n."""
    cv2.setRNGSeed(int(seed))
    p = np.ascontiguousarray(corr.x_prev[:, :2])
    c = np.ascontiguousarray(corr.x_curr[:, :2])
    E, mask = cv2.findEssentialMat(
        p, c, np.eye(3), method=cv2.RANSAC, prob=confidence,
        threshold=threshold_px / corr.focal, maxIters=max_iterations,
    )  # fmt: skip
    if E is None or E.shape[0] < 3:
        return np.eye(3), np.zeros(3), np.zeros(len(corr), bool), 0
    E = E[:3]
    mask = mask.ravel().astype(bool)
    R, t, _ = _pose_from_essential(E, corr.x_prev, corr.x_curr, mask)
    return R, t, mask, max_iterations


def _normalized_eight_point(x_prev: np.ndarray, x_curr: np.ndarray) -> np.ndarray:
    """Batched normalized 8-point essential matrices (Hartley), (S, 8, 3) inputs -> (S, 3, 3)."""

    def normalize(x):
        mean = x[..., :2].mean(axis=-2, keepdims=True)
        d = np.linalg.norm(x[..., :2] - mean, axis=-1).mean(axis=-1)
        s = np.sqrt(2.0) / np.maximum(d, 1e-300)
        T = np.zeros(x.shape[:-2] + (3, 3))
        T[..., 0, 0] = s
        T[..., 1, 1] = s
        T[..., 0, 2] = -s * mean[..., 0, 0]
        T[..., 1, 2] = -s * mean[..., 0, 1]
        T[..., 2, 2] = 1.0
        return x @ np.swapaxes(T, -1, -2), T

    xp, Tp = normalize(x_prev)
    xc, Tc = normalize(x_curr)
    A = (xc[..., :, None] * xp[..., None, :]).reshape(xp.shape[:-1] + (9,))  # x_c^T E x_p
    _, _, Vt = np.linalg.svd(A)
    E = Vt[..., -1, :].reshape(xp.shape[:-2] + (3, 3))
    U, _, Vt = np.linalg.svd(E)
    E = U @ (np.array([1.0, 1.0, 0.0])[:, None] * Vt)  # closest essential matrix
    return np.swapaxes(Tc, -1, -2) @ E @ Tp


def _estimate_mvo(corr: Correspondences, threshold_px: float, confidence: float,
                  max_iterations: int, rng: np.random.Generator):
    """The paper's MVO baseline: normalized 8-point in RANSAC, then pose by cheirality."""
    n = len(corr)
    best_mask, best_count, iters, batch = None, -1, 0, 50
    needed = max_iterations
    while iters < min(needed, max_iterations):
        idx = np.argsort(rng.random((batch, n)), axis=1)[:, :8]
        E = _normalized_eight_point(corr.x_prev[idx], corr.x_curr[idx])
        d = _sampson_gs_px(E, corr.x_prev, corr.x_curr, corr.focal)  # (batch, n)
        counts = (d < threshold_px).sum(axis=1)
        k = int(np.argmax(counts))
        if counts[k] > best_count:
            best_count, best_mask = int(counts[k]), d[k] < threshold_px
            ratio = max(best_count / n, 1e-9)
            needed = np.log(1 - confidence) / np.log(max(1 - ratio**8, 1e-12))
        iters += batch
    if best_count < 8:
        return np.eye(3), np.zeros(3), np.zeros(n, bool), iters
    E = _normalized_eight_point(corr.x_prev[best_mask][None], corr.x_curr[best_mask][None])[0]
    mask = _sampson_gs_px(E, corr.x_prev, corr.x_curr, corr.focal) < threshold_px
    R, t, _ = _pose_from_essential(E, corr.x_prev, corr.x_curr, mask)
    return R, t, mask, iters


# --------------------------------------------------------------------------- RS model


def _cauchy_weights(e: np.ndarray, scale: float) -> np.ndarray:
    return 1.0 / (1.0 + (e / scale) ** 2)


def _robust_cost(e: np.ndarray, scale: float | None) -> float:
    if scale is None:
        return float(np.sum(e**2))
    return float(np.sum(scale**2 * np.log1p((e / scale) ** 2)))


MAX_STEP_ROTATION_RAD = 0.05  # largest rotation change of one LM step
MAX_STEP_TRANSLATION_RAD = 0.2  # largest change of the translation direction of one step
VELOCITY_SLICE = slice(5, 17)  # w_prev, v_prev, w_curr, v_curr in the 17-vector


def _velocities(state: RSState) -> np.ndarray:
    return np.concatenate([state.w_prev, state.v_prev, state.w_curr, state.v_curr])


def levenberg_marquardt(
    state: RSState,
    corr: Correspondences,
    max_iterations: int,
    lambda_init: float = 1e-3,
    rel_tol: float = 1e-9,
    robust_scale: float | None = None,
    prior_inv_sigma: np.ndarray | None = None,
    marquardt: bool = True,
    basis: np.ndarray | None = None,
    bounds: tuple[float, float] | None = None,
    max_rotation_change: float = np.inf,
    anchor_R: np.ndarray | None = None,
) -> tuple[RSState, float, int]:
    """Minimise the (optionally Cauchy-robust) Sampson error over the 17-DOF RS state.

    Damped normal equations ``(H + lambda D) d = -g`` with ``H = J^T W J``, ``g = J^T W e``,
    IRLS weights ``W`` for the robust loss, and ``D = diag(H)`` (Marquardt) or ``max diag(H) I``
    (Levenberg). ``prior_inv_sigma`` (12,) adds the zero-mean prior ``sum((p * vel)^2)`` on the
    velocities ``[w_p, v_p, w_c, v_c]``. Returns the state, its cost and the iterations run.
    """
    p2 = None if prior_inv_sigma is None else np.asarray(prior_inv_sigma, float) ** 2

    def total_cost(e, st):
        prior = 0.0 if p2 is None else float(p2 @ _velocities(st) ** 2)
        return _robust_cost(e, robust_scale) + prior

    R_start = state.R if anchor_R is None else anchor_R
    e, J = sampson_residuals(state, corr, jacobian=True)
    cost = total_cost(e, state)
    lam = lambda_init
    it = 0
    for it in range(1, max_iterations + 1):  # noqa: B007
        w = np.ones_like(e) if robust_scale is None else _cauchy_weights(e, robust_scale)
        Jw = J * w[:, None]
        H = Jw.T @ J
        g = Jw.T @ e
        if p2 is not None:
            H[VELOCITY_SLICE, VELOCITY_SLICE] += np.diag(p2)
            g[VELOCITY_SLICE] += p2 * _velocities(state)
        if basis is not None:
            H = basis.T @ H @ basis
            g = basis.T @ g
        hmax = max(np.max(np.diag(H)), 1e-300)
        diag = np.maximum(np.diag(H), 1e-12 * hmax) if marquardt else np.full(len(g), hmax)
        improved = False
        for _ in range(10):
            try:
                delta = np.linalg.solve(H + lam * np.diag(diag), -g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            full = delta if basis is None else basis @ delta
            if np.linalg.norm(full[:3]) > MAX_STEP_ROTATION_RAD or (
                np.linalg.norm(full[3:5]) > MAX_STEP_TRANSLATION_RAD
            ):  # trust region on the pose: keeps LM in the basin it started in
                lam *= 4.0
                continue
            cand = state.retract(full)
            if np.isfinite(max_rotation_change) and (
                np.linalg.norm(so3_log(R_start.T @ cand.R)) > max_rotation_change
            ):
                lam *= 4.0
                continue
            if bounds is not None and not _within_bounds(cand, bounds):
                lam *= 4.0
                continue
            e_new, _ = sampson_residuals(cand, corr)
            cost_new = total_cost(e_new, cand)
            if np.isfinite(cost_new) and cost_new < cost:
                improved = True
                break
            lam *= 4.0
        if not improved:
            break
        rel = (cost - cost_new) / max(cost, 1e-300)
        state, cost = cand, cost_new
        lam = max(lam / 3.0, 1e-12)
        if rel < rel_tol:
            break
        e, J = sampson_residuals(state, corr, jacobian=True)
    return state, cost, it


def _within_bounds(state: RSState, bounds: tuple[float, float]) -> bool:
    """``bounds = (max |w| rad/s, max |v| in units of t per second)``."""
    w_max, v_max = bounds
    return bool(
        np.linalg.norm(state.w_prev) <= w_max and np.linalg.norm(state.w_curr) <= w_max
        and np.linalg.norm(state.v_prev) <= v_max and np.linalg.norm(state.v_curr) <= v_max
    )  # fmt: skip


def difference_basis() -> np.ndarray:
    """(17, 11) basis that moves the two frames' velocities only in opposite directions.

    From two views the difference of the frames' velocities is well observed and their common
    part is not; solving for the difference first keeps LM in the right basin.
    """
    B = np.zeros((17, 11))
    B[:5, :5] = np.eye(5)
    B[5:11, 5:11] = 0.5 * np.eye(6)
    B[11:17, 5:11] = -0.5 * np.eye(6)
    return B


def velocity_prior(corr: Correspondences, sigma_rotation_rad: float,
                   sigma_translation: float) -> np.ndarray:
    """Inverse std (12,) of a prior on the velocities, set in image-independent units.

    ``sigma_rotation_rad``: rotation over the half readout ``max|s| |w|``;
    ``sigma_translation``: displacement over the half readout ``max|s| |v|``, in baselines
    (``|t| = 1``). ``max|s|`` is the largest row time of the points from the reference row.
    """
    s_max = max(float(np.max(np.abs(np.concatenate([corr.s_prev, corr.s_curr])))), 1e-12)
    pw, pv = s_max / sigma_rotation_rad, s_max / sigma_translation
    return np.repeat([pw, pv, pw, pv], 3)


def _gs_state(R: np.ndarray, t: np.ndarray) -> RSState:
    z = np.zeros(3)
    return RSState(R.copy(), t / np.linalg.norm(t), z.copy(), z.copy(), z.copy(), z.copy())


# --------------------------------------------------------------------------- entry point


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
) -> RelativePoseResult:
    """Relative pose of two frames from pixel correspondences.

    Convention: ``X_curr = R X_prev + t`` (row-0 cameras), ``|t| = 1``,
    ``x_curr^T E x_prev = 0``; the RS model's per-correspondence essential matrix is the paper's
    Sec. 5 ``E_rs`` (see :mod:`rsvo_ros.rs_model`).

    Args:
        pts_prev, pts_curr: (N, 2) float64 undistorted pixel coordinates; row = ``[:, 1]``.
        K: (3, 3) intrinsics.
        line_delay: seconds per image row (tau); 0 for a global shutter.
        model: ``"rs"`` (17-DOF RS essential matrix), ``"gs"`` (OpenCV 5-point RANSAC +
            recoverPose) or ``"mvo"`` (the paper's baseline: normalized 8-point RANSAC).
        seed: seeds every random choice; equal inputs and seed give equal results.
        mode: RS only. ``"fast"`` (default): GS initialisation, Cauchy-robust LM on all points,
            LM on the inliers. ``"paper"``: Algorithm 1, ``ransac.rs_iterations`` LM runs on
            random 20-point samples from the GS pose with zero velocities, inlier counting, then
            LM on the best hypothesis' inliers.
        min_inliers: fewer inliers than this gives ``ok=False``.
        min_parallax_px: median parallax (after removing the rotation) below this gives
            ``ok=False`` (pure rotation or no motion: the translation is undefined).

    Raises:
        ValueError: bad input (too few points, NaN/inf, shape mismatch, singular K, all points
            identical, unknown model or mode).
    """
    t_start = time.perf_counter()
    pts_prev, pts_curr, K = _validate(pts_prev, pts_curr, K, line_delay, model)
    if mode not in RS_MODES:
        raise ValueError(f"mode must be one of {RS_MODES}, got {mode!r}")
    ransac = ransac or RansacOptions()
    lm = lm or LMOptions()
    rng = np.random.default_rng(seed)
    row_ref = float(K[1, 2])  # the principal point's row, ~ the image centre
    corr = make_correspondences(pts_prev, pts_curr, K, line_delay, row_ref)
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

    if model == "mvo":
        R, t, mask, iters = _estimate_mvo(corr, ransac.threshold_px, ransac.confidence,
                                          ransac.max_iterations, rng)
    else:
        thr = ransac.threshold_px if model == "gs" else ransac.init_threshold_px
        max_it = ransac.max_iterations if model == "gs" else ransac.init_max_iterations
        R, t, mask, iters = _estimate_gs_opencv(corr, thr, ransac.confidence, max_it, seed)
    if mask.sum() < min_inliers or np.linalg.norm(t) == 0:
        return failed(f"too few inliers for a GS essential matrix ({int(mask.sum())})", mask,
                      iters)
    parallax = _median_parallax_px(R, corr, mask)
    if parallax < min_parallax_px:
        return failed(f"insufficient parallax ({parallax:.2f} px): pure rotation or no motion",
                      mask, iters)

    if model in ("gs", "mvo"):
        e = _sampson_gs_px(_essential(R, t), corr.x_prev, corr.x_curr, corr.focal)
        return finish(RelativePoseResult(True, model, R, t, mask, iterations=iters,
                                         cost=float(np.mean(e[mask] ** 2))))

    inits = [_gs_state(R, t)]
    if mode == "fast":
        inits += _gs_starts(corr, pts_prev[:, 1] - row_ref, ransac, lm, seed, min_inliers)
    state, lm_iters = _solve_rs(corr, inits, mode, ransac, lm, rng)
    e, _ = sampson_residuals(state, corr)
    inliers = np.abs(e) < ransac.threshold_px
    state = _choose_sign(state, corr, inliers)
    if inliers.sum() < min_inliers:
        return failed(f"too few RS inliers ({int(inliers.sum())})", inliers, lm_iters)
    R0, t0, (w_p, v_p, w_c, v_c) = pose_from_row(*state.as_tuple(), row_ref, line_delay)
    scale = np.linalg.norm(t0)
    if not np.isfinite(scale) or scale < 1e-12:
        return failed("degenerate RS solution (zero translation at row 0)", inliers, lm_iters)
    return finish(RelativePoseResult(
        True, "rs", R0, t0 / scale, inliers, w_p, v_p / scale, w_c, v_c / scale,
        iterations=lm_iters, cost=float(np.mean(e[inliers] ** 2)),
    ))  # fmt: skip


def _gs_starts(corr: Correspondences, rows_from_ref: np.ndarray, ransac: RansacOptions,
               lm: LMOptions, seed: int, min_inliers: int) -> list[RSState]:
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
        if mask.sum() < max(min_inliers, 2 * MIN_POINTS["gs"]):
            continue
        R, t, inl, _ = _estimate_gs_opencv(corr.subset(mask), thr, ransac.confidence,
                                           ransac.init_max_iterations, seed)
        if inl.sum() >= min_inliers and np.linalg.norm(t) > 0:
            starts.append(_gs_state(R, t))
    return starts


def _essential(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return tx @ R


def _median_parallax_px(R: np.ndarray, corr: Correspondences, mask: np.ndarray) -> float:
    """Median image distance between curr points and prev points rotated by R (pixels)."""
    rp = corr.x_prev[mask] @ R.T
    rp = rp[:, :2] / rp[:, 2:3]
    return float(np.median(np.linalg.norm(rp - corr.x_curr[mask, :2], axis=1)) * corr.focal)


def rs_depths(state: RSState, corr: Correspondences) -> tuple[np.ndarray, np.ndarray]:
    """Depths (along the bearings) of each correspondence in both frames, by least squares.

    Solves ``lam_c Rc x_c = lam_p R Rp x_p + T`` per point (the rows' own camera poses).
    """
    Rp = so3_exp(corr.s_prev[:, None] * state.w_prev[None, :])
    Rc = so3_exp(corr.s_curr[:, None] * state.w_curr[None, :])
    a = np.einsum("nij,nj->ni", Rp, corr.x_prev) @ state.R.T
    b = np.einsum("nij,nj->ni", Rc, corr.x_curr)
    T = (state.t[None, :] + (corr.s_prev[:, None] * state.v_prev[None, :]) @ state.R.T
         - corr.s_curr[:, None] * state.v_curr[None, :])  # fmt: skip
    # minimise |lam_p a - lam_c b + T|^2 over (lam_p, lam_c)
    aa, bb, ab = (a * a).sum(1), (b * b).sum(1), (a * b).sum(1)
    aT, bT = (a * T).sum(1), (b * T).sum(1)
    det = aa * bb - ab * ab
    det = np.where(np.abs(det) < 1e-15, np.nan, det)
    lam_p = (-bb * aT + ab * bT) / det
    lam_c = (aa * bT - ab * aT) / det
    return lam_p, lam_c


def _cheirality_fraction(state: RSState, corr: Correspondences, mask: np.ndarray) -> float:
    """Fraction of ``mask``'s points whose depths agree in sign in both frames (either sign)."""
    if mask.sum() < 5:
        return 0.0
    lam_p, lam_c = rs_depths(state, corr.subset(mask))
    front = np.count_nonzero((lam_p > 0) & (lam_c > 0))
    behind = np.count_nonzero((lam_p < 0) & (lam_c < 0))
    return max(front, behind) / int(mask.sum())


def _choose_sign(state: RSState, corr: Correspondences, inliers: np.ndarray) -> RSState:
    """Cheirality: ``(t, v_prev, v_curr)`` and their negatives fit equally (``E_i -> -E_i``);
    keep the sign that puts most inlier points in front of both cameras."""
    sub = corr.subset(inliers) if inliers.sum() >= 5 else corr
    lam_p, lam_c = rs_depths(state, sub)
    front = np.count_nonzero((lam_p > 0) & (lam_c > 0))
    behind = np.count_nonzero((lam_p < 0) & (lam_c < 0))
    if behind > front:
        return RSState(state.R, -state.t, state.w_prev, -state.v_prev, state.w_curr,
                       -state.v_curr)
    return state


def _subsample(n: int, count: int, rng: np.random.Generator) -> np.ndarray:
    return np.arange(n) if n <= count else np.sort(rng.choice(n, count, replace=False))


def _solve_rs(corr: Correspondences, inits: list[RSState], mode: str, ransac: RansacOptions,
              lm: LMOptions, rng: np.random.Generator) -> tuple[RSState, int]:
    """The RS model's search; returns the state at the reference row and LM iterations.

    fast: from each initial GS pose, LM on a subsample with only the difference of the two
    frames' velocities free (:func:`difference_basis`), then all 17 DOF; the start whose result
    has consistent depths and the lowest robust cost on all points wins and is refined on all
    points, then on the inliers. Every stage keeps the velocities inside physical bounds, adds
    the weak velocity prior, and stays within ``max_rotation_change_rad`` of its GS start.
    paper: Algorithm 1 (LM on random 20-point samples from the first GS pose, inlier counting),
    then LM on the best hypothesis' inliers; no prior.
    """
    total = 0
    scale = lm.robust_scale_px
    s_max = max(float(np.max(np.abs(np.concatenate([corr.s_prev, corr.s_curr])))), 1e-12)
    bounds = (lm.max_angular_velocity, lm.max_readout_translation / s_max)
    if mode == "paper":
        best, best_count = inits[0], -1
        for _ in range(ransac.rs_iterations):
            idx = rng.choice(len(corr), ransac.rs_sample_size, replace=False)
            cand, _, it = levenberg_marquardt(inits[0], corr.subset(idx), lm.sample_iterations,
                                              lm.lambda_init, bounds=bounds)
            total += it
            e, _ = sampson_residuals(cand, corr)
            count = int(np.count_nonzero(np.abs(e) < ransac.threshold_px))
            if count >= best_count:
                best, best_count = cand, count
        e, _ = sampson_residuals(best, corr)
        inl = np.abs(e) < ransac.threshold_px
        state = best
        if inl.sum() >= NUM_PARAMS + 3:
            state, _, it = levenberg_marquardt(best, corr.subset(inl), lm.max_iterations,
                                               lm.lambda_init, lm.rel_tol, bounds=bounds)
            total += it
        return state, total

    prior = None
    if lm.prior_rotation_rad > 0 and lm.prior_translation > 0:
        prior = np.sqrt(len(corr)) * velocity_prior(corr, lm.prior_rotation_rad,
                                                    lm.prior_translation)

    def run(st, data, anchor, robust=True, basis=None):
        return levenberg_marquardt(
            st, data, lm.max_iterations, lm.lambda_init, lm.rel_tol,
            robust_scale=scale if robust else None, basis=basis, bounds=bounds,
            prior_inv_sigma=prior, max_rotation_change=lm.max_rotation_change_rad,
            anchor_R=anchor.R,
        )  # fmt: skip

    sub = corr.subset(_subsample(len(corr), lm.subsample, rng))
    candidates = []
    for init in inits:
        st, _, it1 = run(init, sub, init, basis=difference_basis())
        st, _, it2 = run(st, sub, init)
        total += it1 + it2
        e, _ = sampson_residuals(st, corr)
        cost = _robust_cost(e, scale)
        if prior is not None:
            cost += float(prior**2 @ _velocities(st) ** 2)
        inconsistent = _cheirality_fraction(st, corr, np.abs(e) < 3.0 * scale) < 0.75
        candidates.append((inconsistent, cost, len(candidates), st, init))
    _, _, _, best, anchor = min(candidates)  # consistent depths first, then the lowest cost
    state, _, it = run(best, corr, anchor)
    total += it
    e, _ = sampson_residuals(state, corr)
    inl = np.abs(e) < ransac.threshold_px
    if inl.sum() >= NUM_PARAMS + 3:
        state, _, it = run(state, corr.subset(inl), anchor, robust=False)
        total += it
    return state, total
