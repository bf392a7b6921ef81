"""The odometry pipeline: track, estimate each frame pair, chain poses with a consistent scale.

Pure Python/numpy (no rclpy): the same object serves ``rsvo_replay`` and the live node; they
differ only in where frames come from and where results go.

Chaining as in the paper: ``T_{k+1} = T_k [R t; 0 1]^-1`` with ``X_curr = R X_prev + t``, i.e.
``T_world_curr = T_world_prev @ inv(T_curr_prev)``, applied to the cameras of the frames'
middle rows (the reference row of the RS solver): their relative motion needs no velocity to be
right, while the row-0 one inherits the velocities' errors (which from two views stay large
under noise). Each frame's row-0 pose, what the pipeline reports (CONTRACTS.md), is where the
chain of middle-row cameras was at the row-0 time: ``row_mid * tau`` before the frame's middle
row, interpolated between consecutive middle-row poses. With a global shutter (``tau = 0``, or
the GS models, whose reference row is row 0) this is the plain chain.

Motion prior (RS, ``PipelineOptions.motion_prior``): the frames are one continuous motion, so
each pair's velocity prior is centred on the constant velocity of that pair's own motion over
its stamps' interval, with a much tighter translation part than the paper's experiment allows
(from two views the velocities' common part, above all the linear velocity under forward
motion, is barely observed: on the synthetic vehicle it came out 100-1000 % off, and warped
the depths that carry the scale), and the previous pair's middle-row motion is one more start
of the search. Measured over 16 vehicle sequences, the tighter prior and the extra start give
the gain; where the prior is centred (constant velocity or zero) changes the ATE little, but
only the constant velocity leaves the velocities unbiased.

Scale: the first pair's baseline is ``initial_scale``; each later pair's ``|t|`` makes the
depths of the points it shares with the previous pair agree (a line fitted to their inverse
depths, which the estimator gives in each point's own row camera); without enough shared points
it keeps the previous baseline.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from rsvo_ros.core.geometry import pose_at_row, so3_exp, so3_log
from rsvo_ros.odometry.tracker import FeatureTracker, TrackerOptions, undistort_points
from rsvo_ros.twoview import (
    LMOptions,
    RansacOptions,
    RelativePoseResult,
    estimate_relative_pose,
)

MIN_SHARED_FOR_SCALE = 8  # shared triangulated points needed to measure the relative scale
MAX_DEPTH_IN_BASELINES = 40.0  # farther points do not vote on the scale
MAX_SCALE_STEP = 1.25  # largest change of the baseline from one pair to the next
HOLD_COVARIANCE_GROWTH = 4.0  # covariance multiplier of a held (not estimated) pose
DEFAULT_POSITION_VARIANCE = 1e-2  # m^2 per pair when a fit gives no usable covariance


@dataclass
class PipelineOptions:
    """How the pipeline estimates; ``model``: "rs" | "gs" | "mvo"."""

    model: str = "rs"
    mode: str = "fast"
    tracker: TrackerOptions = field(default_factory=TrackerOptions)
    ransac: RansacOptions = field(default_factory=RansacOptions)
    lm: LMOptions = field(default_factory=LMOptions)
    min_tracks: int = 25  # fewer tracked correspondences: re-initialise
    initial_scale: float = 1.0  # metres of the first pair's baseline (1 = up to scale)
    # RS: use that frames come from one continuous motion: the velocity prior is centred on the
    # constant velocity of each pair's motion over its stamps' interval, and the previous
    # pair's motion is one more start of the search (off: each pair on its own, as the paper)
    motion_prior: bool = True
    max_scale_change: float = 5.0  # relative scale outside [1/x, x] is not trusted
    seed: int = 0


@dataclass
class FrameResult:
    """What the pipeline says about one input frame."""

    index: int
    stamp_ns: int
    status: str  # "posed" (estimated), "first", "held" (pose kept), "skipped"
    reason: str
    T_world_cam: np.ndarray | None  # (4, 4), None when skipped
    covariance: np.ndarray  # (6, 6) of [position, rotation vector] in the world frame
    num_tracks: int = 0
    num_inliers: int = 0
    inlier_ratio: float = 0.0
    scale: float = 0.0  # metres of this pair's baseline
    time_ms: float = 0.0
    relative: RelativePoseResult | None = None
    pts_prev: np.ndarray | None = None  # raw pixels of the pair (for drawing)
    pts_curr: np.ndarray | None = None

    @property
    def has_pose(self) -> bool:
        return self.T_world_cam is not None


def _scale_from_inverse_depths(pairs: np.ndarray) -> float:
    """``s`` with ``d_old = s d_new`` from (n, 2) depth pairs of the same points: a line through
    the origin fitted to the inverse depths (``1/d_new = s / d_old``), which weights near points
    (large parallax, small depth error) most, with one round of outlier trimming."""
    rho_old, rho_new = 1.0 / pairs[:, 0], 1.0 / pairs[:, 1]
    keep = np.ones(len(pairs), bool)
    for _ in range(2):
        s = float(rho_old[keep] @ rho_new[keep] / max(rho_old[keep] @ rho_old[keep], 1e-300))
        r = rho_new - s * rho_old
        mad = 1.4826 * float(np.median(np.abs(r[keep]))) + 1e-12
        keep = np.abs(r) < 3.0 * mad
        if keep.sum() < MIN_SHARED_FOR_SCALE:
            break
    return s


def _interpolate(T: np.ndarray, a: float) -> np.ndarray:
    """The fraction ``a`` of the motion ``T`` (4, 4): rotation ``Exp(a Log R)``, translation
    ``a p`` (constant velocity between two poses; ``a`` outside [0, 1] extrapolates)."""
    out = np.eye(4)
    out[:3, :3] = so3_exp(a * so3_log(T[:3, :3]))
    out[:3, 3] = a * T[:3, 3]
    return out


def _inverse(T: np.ndarray) -> np.ndarray:
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


class OdometryPipeline:
    """Feed frames with :meth:`process`; poses are ``T_world_camera`` at row-0 times."""

    def __init__(self, K: np.ndarray, D: np.ndarray | None, line_delay: float,
                 options: PipelineOptions | None = None):  # fmt: skip
        self.options = options or PipelineOptions()
        self.set_camera(K, D, line_delay)
        self.tracker = FeatureTracker(self.options.tracker)
        self.reset()

    def set_camera(self, K: np.ndarray, D: np.ndarray | None, line_delay: float) -> None:
        K = np.asarray(K, float)
        if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"camera matrix K must be a finite 3x3 with positive focal "
                             f"lengths, got {K.tolist()}")  # fmt: skip
        if not np.isfinite(line_delay) or line_delay < 0:
            raise ValueError(f"line_delay must be finite and >= 0, got {line_delay}")
        self.K = K
        self.D = None if D is None or len(D) == 0 else np.asarray(D, float)
        self.line_delay = float(line_delay)

    def reset(self) -> None:
        """Forget everything: the next frame starts a new trajectory at the identity."""
        self.tracker.reset()
        self.T_world_cam = np.eye(4)
        self._T_world_mid: np.ndarray | None = None  # the last posed frame's middle-row camera
        self.covariance = np.zeros((6, 6))
        self._last_stamp: int | None = None
        self._index = 0
        self._prev_depths: dict[int, float] = {}  # track id -> metric depth in the last frame
        self._last_baseline = self.options.initial_scale  # metres between middle-row cameras
        self._started = False
        # the last estimated motion between middle-row cameras: (R, unit t, seconds)
        self._last_motion: tuple[np.ndarray, np.ndarray, float] | None = None

    def process(self, stamp_ns: int, gray: np.ndarray) -> FrameResult:
        """One new frame (uint8 gray). Never raises for bad data: returns a skipped result."""
        t0 = time.perf_counter()
        idx = self._index
        self._index += 1

        def result(status, reason="", **kw):
            res = FrameResult(idx, stamp_ns, status, reason,
                              None if status == "skipped" else self.T_world_cam.copy(),
                              self.covariance.copy(), **kw)  # fmt: skip
            res.time_ms = (time.perf_counter() - t0) * 1e3
            return res

        if gray is None or gray.ndim != 2 or gray.dtype != np.uint8 or gray.size == 0:
            return result("skipped", "not a non-empty uint8 gray image")
        if self._last_stamp is not None and stamp_ns <= self._last_stamp:
            kind = "duplicate" if stamp_ns == self._last_stamp else "backwards"
            return result("skipped", f"{kind} stamp ({stamp_ns} after {self._last_stamp} ns)")
        prev_stamp, self._last_stamp = self._last_stamp, stamp_ns
        pair = self.tracker.track(gray)
        if not self._started:
            self._started = True
            return result("first", "first frame: trajectory origin",
                          num_tracks=self.tracker.num_tracks)
        n = len(pair.ids)
        if n < self.options.min_tracks:
            self._hold()  # the tracker has already re-detected corners on this frame
            return result("held", f"lost tracking ({n} tracks): re-initialised",
                          num_tracks=self.tracker.num_tracks)
        pts_prev = undistort_points(pair.pts_prev, self.K, self.D)
        pts_curr = undistort_points(pair.pts_curr, self.K, self.D)
        interval = (stamp_ns - prev_stamp) * 1e-9
        moving = self.options.motion_prior and self.options.model == "rs"
        try:
            rel = estimate_relative_pose(
                pts_prev, pts_curr, self.K, self.line_delay, model=self.options.model,
                seed=self.options.seed + idx, mode=self.options.mode,
                ransac=self.options.ransac, lm=self.options.lm,
                rows_prev=pair.pts_prev[:, 1], rows_curr=pair.pts_curr[:, 1],
                frame_interval=interval if moving else None,
                predicted=self._predicted_motion(interval) if moving else None,
            )  # fmt: skip
        except ValueError as exc:  # e.g. all tracks collapsed onto one point
            self._hold()
            return result("held", f"estimation refused the pair: {exc}", num_tracks=n)
        if not rel.ok:
            self._hold()
            return result("held", f"no pose for this pair: {rel.reason}", num_tracks=n,
                          num_inliers=rel.num_inliers, inlier_ratio=rel.inlier_ratio,
                          relative=rel, pts_prev=pair.pts_prev, pts_curr=pair.pts_curr)
        row_mid, tau = float(rel.row_ref), self.line_delay  # 0 for the GS models
        R_m, t_m, _ = pose_at_row(rel.R, rel.t, rel.w_prev, rel.v_prev, rel.w_curr,
                                  rel.v_curr, row_mid, tau)  # in units of |t| (row 0)
        unit = float(np.linalg.norm(t_m))
        if not np.isfinite(unit) or unit < 1e-9:
            self._hold()
            return result("held", "no translation between the middle rows", num_tracks=n,
                          relative=rel)
        d_prev, d_curr = rel.depths_prev, rel.depths_curr  # in each point's own row camera
        scale, scale_note = self._relative_scale(pair.ids, rel, d_prev, unit)
        T_curr_prev = np.eye(4)
        T_curr_prev[:3, :3], T_curr_prev[:3, 3] = R_m, t_m * scale
        M = _inverse(T_curr_prev)  # the current middle-row camera in the previous one
        # row 0 is exposed row_mid * tau before the middle row: where the frames' middle-row
        # cameras were at those times, interpolated along the motion between them
        lead = row_mid * tau / max(interval, 1e-9)
        T_world_mid = self._T_world_mid
        if T_world_mid is None:  # the first pair: place the previous frame's middle row
            T_world_mid = self.T_world_cam @ _inverse(_interpolate(M, -lead))
        T_mid_new = T_world_mid @ M
        T_new = T_world_mid @ _interpolate(M, 1.0 - lead)
        if not (np.isfinite(T_new).all() and np.isfinite(T_mid_new).all()):
            self._hold()
            return result("held", "non-finite chained pose", num_tracks=n, relative=rel)
        self.T_world_cam = T_new
        self._T_world_mid = T_mid_new
        self._accumulate_covariance(rel, scale)
        depth = d_curr * scale
        good = rel.inliers & np.isfinite(depth) & (depth > 0)
        self._prev_depths = dict(zip(pair.ids[good].tolist(), depth[good].tolist(), strict=True))
        self._last_baseline = scale * unit
        self._last_motion = (R_m, t_m / unit, interval)
        return result("posed", scale_note, num_tracks=n, num_inliers=rel.num_inliers,
                      inlier_ratio=rel.inlier_ratio, scale=scale, relative=rel,
                      pts_prev=pair.pts_prev, pts_curr=pair.pts_curr)

    # ------------------------------------------------------------------ internals

    def _predicted_motion(self, interval: float) -> tuple[np.ndarray, np.ndarray] | None:
        """The last estimated middle-row motion, its rotation scaled to ``interval`` (constant
        velocity), as a start for this pair's search."""
        if self._last_motion is None:
            return None
        R, t, last_interval = self._last_motion
        return so3_exp(so3_log(R) * (interval / max(last_interval, 1e-9))), t

    def _relative_scale(self, ids: np.ndarray, rel: RelativePoseResult, depths_prev: np.ndarray,
                        unit: float) -> tuple[float, str]:
        """Metres per unit of ``rel.t`` from the depths this pair shares with the previous one.

        ``depths_prev`` (N,): this pair's depths in the previous frame, in units of ``rel.t``;
        the previous pair stored the same points' metric depths. Only points within
        ``MAX_DEPTH_IN_BASELINES`` vote; the fit is on inverse depths, which weights near
        points (small depth error) most. The result is used as measured, not blended with the
        previous baseline: each pair's scale is measured against depths the previous scale
        produced, so a pair's error is undone by the next one instead of adding up, while any
        blending would keep a part of every real change of speed out for good (a steadily
        accelerating vehicle then drifts in scale). A change of the baseline between middle
        rows (``unit`` of them per unit of ``rel.t``) beyond ``MAX_SCALE_STEP`` is clipped.
        """
        pairs = []
        for i, d_new, inl in zip(ids.tolist(), depths_prev, rel.inliers, strict=True):
            d_old = self._prev_depths.get(i)
            if (inl and d_old is not None and np.isfinite(d_new)
                    and 0 < d_new < MAX_DEPTH_IN_BASELINES):  # fmt: skip
                pairs.append((d_old, d_new))
        last = self._last_baseline
        if len(pairs) < MIN_SHARED_FOR_SCALE:
            why = "no shared depths" if not self._prev_depths else f"{len(pairs)} shared"
            return last / unit, f"scale from the previous baseline ({why})"
        measured = _scale_from_inverse_depths(np.array(pairs)) * unit
        lim = self.options.max_scale_change
        if not (np.isfinite(measured) and last / lim <= measured <= last * lim):
            return last / unit, f"baseline {measured:.3g} rejected: kept the previous one"
        return float(np.clip(measured, last / MAX_SCALE_STEP, last * MAX_SCALE_STEP)) / unit, ""

    def _accumulate_covariance(self, rel: RelativePoseResult, scale: float) -> None:
        """Random-walk growth: the pair's covariance, rotated into the world frame."""
        R_wc = self.T_world_cam[:3, :3]
        rel_cov = np.asarray(rel.covariance, float)
        if not np.isfinite(rel_cov).all():
            rel_cov = np.diag([1e-4, 1e-4, 1e-4, 1.0, 1.0, 1.0])
        step = np.zeros((6, 6))
        step[:3, :3] = R_wc @ rel_cov[3:, 3:] @ R_wc.T * scale**2 + np.eye(3) * 1e-9
        step[3:, 3:] = R_wc @ rel_cov[:3, :3] @ R_wc.T + np.eye(3) * 1e-12
        # a poor fit counts more: inflate by the share of outliers
        step *= 1.0 / max(rel.inlier_ratio, 0.05) ** 2
        self.covariance = self.covariance + step

    def _hold(self) -> None:
        """Keep the pose; the uncertainty grows; depths of the skipped pair are unknown."""
        grow = np.diag([DEFAULT_POSITION_VARIANCE] * 3 + [1e-3] * 3) * HOLD_COVARIANCE_GROWTH
        self.covariance = self.covariance + grow * max(self._last_baseline, 1e-3) ** 2
        self._prev_depths = {}

