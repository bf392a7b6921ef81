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

from rsvo_ros.geometry import pose_from_row
from rsvo_ros.rs_model import (
    Correspondences,
    RSBatch,
    make_correspondences,
)
from rsvo_ros.rs_solver import (
    LMOptions,
    depths,
    fix_sign,
    pose_covariance,
    residuals,
    search_fast,
    search_paper,
)

__all__ = ["LMOptions", "RansacOptions", "RelativePoseResult", "estimate_relative_pose",
           "warm_up"]

MODELS = ("rs", "gs", "mvo")
RS_MODES = ("fast", "paper")
MIN_POINTS = {"gs": 5, "mvo": 8, "rs": 20}  # 5-point, 8-point, the paper's 20-point samples
PAPER_RANSAC_ITERATIONS = 500  # Algorithm 1
PARALLAX_TO_NOISE = 3.0  # parallax below this many times the GS fit's noise: no translation
PAPER_SAMPLE_SIZE = 20  # Sec. 6: "20 feature point correspondences as the input of RANSAC"
# GS starts of the RS model: OpenCV's USAC with local optimisation finds a good GS fit of RS
# data (inlier ratio ~35-75 %) in 1-2 ms where plain RANSAC takes 7-35 ms.
INIT_METHOD = cv2.USAC_FAST
CHEIRALITY_VOTERS = 100  # inliers that choose among the four decompositions of E


@dataclass
class RansacOptions:
    """Robust-estimation settings, kept apart from the optimizer's (PoseLib style)."""

    threshold_px: float = 1.0  # Sampson distance of an inlier, pixels
    max_iterations: int = 1000  # hypotheses of the GS baselines (OpenCV, MVO)
    confidence: float = 0.999
    rs_iterations: int = PAPER_RANSAC_ITERATIONS  # paper mode: LM runs on random 20-point samples
    rs_sample_size: int = PAPER_SAMPLE_SIZE
    init_threshold_px: float = 3.0  # GS initialisation of the RS model tolerates RS distortion
    init_max_iterations: int = 50  # USAC stops early by its confidence; this caps the worst case


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
    """The decomposition of ``E = [t]x R`` (Hartley & Zisserman, Result 9.19: two rotations
    times the two signs of ``t``) that puts most of the ``mask``'s points in front of both
    cameras (what OpenCV's recoverPose does, in a quarter of its time). Returns R, t (unit)
    and the number of points in front, or identity, zero and 0."""
    if mask.sum() < MIN_POINTS["gs"]:
        return np.eye(3), np.zeros(3), 0
    U, _, Vt = np.linalg.svd(E)
    U = U * np.sign(np.linalg.det(U))  # proper rotations; E only matters up to sign
    Vt = Vt * np.sign(np.linalg.det(Vt))
    W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    Rs = np.stack([U @ W @ Vt, U @ W.T @ Vt] * 2)
    ts = np.stack([U[:, 2], U[:, 2], -U[:, 2], -U[:, 2]])
    # depths of the four candidates (4, n); at most CHEIRALITY_VOTERS evenly spread inliers vote
    voters = np.flatnonzero(mask)
    count = min(len(voters), CHEIRALITY_VOTERS)
    voters = voters[np.linspace(0, len(voters) - 1, count).astype(int)]
    zeros = np.zeros(len(voters))
    lam_p, lam_c = depths(RSBatch.from_pose(Rs, ts),
                          Correspondences(x_prev[voters], x_curr[voters], zeros, zeros, 1.0))
    front = np.count_nonzero((lam_p > 0) & (lam_c > 0), axis=1)
    k = int(np.argmax(front))
    if front[k] == 0:
        return np.eye(3), np.zeros(3), 0
    return Rs[k], ts[k], int(front[k])


def _estimate_gs_opencv(corr: Correspondences, threshold_px: float, confidence: float,
                        max_iterations: int, seed: int, method: int = cv2.RANSAC,
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:  # fmt: skip
    """OpenCV's 5-point RANSAC (``method``: ``cv2.RANSAC``, or a USAC variant, whose own
    generator is seeded by OpenCV) on normalized points, then recoverPose.
    Returns R, t, mask, n and OpenCV's E (USAC's is not always on the essential manifold)."""
    cv2.setRNGSeed(int(seed))
    p = np.ascontiguousarray(corr.x_prev[:, :2])
    c = np.ascontiguousarray(corr.x_curr[:, :2])
    E, mask = cv2.findEssentialMat(
        p, c, np.eye(3), method=method, prob=confidence,
        threshold=threshold_px / corr.focal, maxIters=max_iterations,
    )  # fmt: skip
    if E is None or E.shape[0] < 3:
        return np.eye(3), np.zeros(3), np.zeros(len(corr), bool), 0, np.zeros((3, 3))
    E = E[:3]
    mask = mask.ravel().astype(bool)
    R, t, _ = _pose_from_essential(E, corr.x_prev, corr.x_curr, mask)
    return R, t, mask, max_iterations, E


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
    E = np.swapaxes(Tc, -1, -2) @ E @ Tp  # back to normalized camera coordinates
    U, _, Vt = np.linalg.svd(E)
    return U @ (np.array([1.0, 1.0, 0.0])[:, None] * Vt)  # closest essential matrix


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
    rows_prev: np.ndarray | None = None,
    rows_curr: np.ndarray | None = None,
    frame_interval: float | None = None,
    predicted: tuple[np.ndarray, np.ndarray] | None = None,
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
        mode: RS only. ``"fast"`` (default): multi-start search from several GS fits
            (:func:`rsvo_ros.rs_solver.search_fast`). ``"paper"``: Algorithm 1,
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

    if model == "mvo":
        R, t, mask, iters = _estimate_mvo(corr, ransac.threshold_px, ransac.confidence,
                                          ransac.max_iterations, rng)
        E = _essential(R, t)
    else:
        thr = ransac.threshold_px if model == "gs" else ransac.init_threshold_px
        max_it = ransac.max_iterations if model == "gs" else ransac.init_max_iterations
        method = cv2.RANSAC if model == "gs" else INIT_METHOD
        R, t, mask, iters, E = _estimate_gs_opencv(corr, thr, ransac.confidence, max_it, seed,
                                                   method)
    if mask.sum() < min_inliers:
        return failed(f"too few inliers for a GS essential matrix ({int(mask.sum())})", mask,
                      iters)
    parallax, R_rot = _rotation_only_residual_px(corr, rng)
    has_pose = np.linalg.norm(t) > 0
    # the noise of the model RANSAC fitted (an upper bound: RS distortion adds to it)
    e_fit = _sampson_gs_px(E, corr.x_prev, corr.x_curr, corr.focal)
    noise_px = float(np.median(e_fit[mask])) if has_pose else 0.0
    if parallax < max(min_parallax_px, PARALLAX_TO_NOISE * noise_px):
        return failed(f"insufficient parallax ({parallax:.2f} px after the best rotation, "
                      f"noise {noise_px:.2f} px): pure rotation or no motion", mask, iters)
    if not has_pose:
        return failed("no decomposition of the essential matrix puts the points in front of "
                      "both cameras", mask, iters)

    if model in ("gs", "mvo"):
        gs_state = RSBatch.from_pose(R, t)
        e_gs = _sampson_gs_px(_essential(R, t), corr.x_prev, corr.x_curr, corr.focal)
        depths_p, depths_c = depths(gs_state, corr)
        return finish(RelativePoseResult(
            True, model, R, t, mask, iterations=iters, cost=float(np.mean(e_gs[mask] ** 2)),
            depths_prev=depths_p[0], depths_curr=depths_c[0],
            covariance=pose_covariance(gs_state, corr.subset(mask), gs_only=True),
        ))  # fmt: skip

    start = RSBatch.from_pose(R, t)
    if mode == "paper":
        found = search_paper(corr, start, ransac.rs_iterations, ransac.rs_sample_size,
                             ransac.threshold_px, lm, rng)
    else:
        starts = [start] + _gs_starts(corr, pts_prev[:, 1] - row_ref, ransac, lm, seed,
                                      min_inliers) + [_rotation_start(corr, R_rot)]
        if predicted is not None:
            starts.append(RSBatch.from_pose(*predicted))
        batch = RSBatch(*(np.concatenate([getattr(s, f) for s in starts])
                          for f in ("R", "t", "vel")))  # fmt: skip
        found = search_fast(corr, batch, ransac.threshold_px, lm, rng, frame_interval)
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


def _gs_starts(corr: Correspondences, rows_from_ref: np.ndarray, ransac: RansacOptions,
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
        if mask.sum() < max(min_inliers, 2 * MIN_POINTS["gs"]):
            continue
        R, t, inl, _, _ = _estimate_gs_opencv(corr.subset(mask), thr, ransac.confidence,
                                              ransac.init_max_iterations, seed, INIT_METHOD)
        if inl.sum() >= min_inliers and np.linalg.norm(t) > 0:
            starts.append(RSBatch.from_pose(R, t))
    return starts


def _rotation_start(corr: Correspondences, R: np.ndarray) -> RSBatch:
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


def _essential(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return tx @ R


def _kabsch(b_prev: np.ndarray, b_curr: np.ndarray) -> np.ndarray:
    """Rotations (…, 3, 3) best mapping unit bearings ``b_curr ~ R b_prev`` (…, n, 3)."""
    H = np.swapaxes(b_curr, -1, -2) @ b_prev
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.zeros(H.shape)
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = d
    return U @ D @ Vt


def _rotation_only_residual_px(corr: Correspondences, rng: np.random.Generator,
                               hypotheses: int = 16) -> tuple[float, np.ndarray]:
    """Median image distance (px) left by the best rotation-only motion (2-point RANSAC +
    refit): what a camera that only rotates cannot explain, i.e. the translation parallax.
    Returns it and that rotation."""
    b_p = corr.x_prev / np.linalg.norm(corr.x_prev, axis=1, keepdims=True)
    b_c = corr.x_curr / np.linalg.norm(corr.x_curr, axis=1, keepdims=True)
    idx = np.argsort(rng.random((hypotheses, len(corr))), axis=1)[:, :2]
    Rs = _kabsch(b_p[idx], b_c[idx])

    def residuals(R):
        rp = b_p @ np.swapaxes(R, -1, -2)
        z = np.where(np.abs(rp[..., 2:3]) > 1e-12, rp[..., 2:3], 1e-12)
        return np.linalg.norm(rp[..., :2] / z - corr.x_curr[:, :2], axis=-1) * corr.focal

    med = np.median(residuals(Rs), axis=1)
    R = Rs[int(np.argmin(med))]
    for _ in range(2):
        r = residuals(R)
        keep = r <= np.median(r)
        R = _kabsch(b_p[keep], b_c[keep])
    return float(np.median(residuals(R))), R
