"""The odometry pipeline: track features, estimate motion, report poses with a consistent scale.

Pure numpy/OpenCV (no rclpy): the same object serves ``rsvo_replay`` and the live node; they
differ only in where frames come from and where results go. Two backends
(``PipelineOptions.backend``):

- ``"window"`` (default): keyframes, a local map of anchored inverse-depth landmarks and a
  sliding-window rolling-shutter bundle adjustment (:mod:`rsvo_ros.odometry.window`); every
  frame is posed by a motion-only RS optimisation against the map.
- ``"pairwise"``: the paper's method, each frame pair estimated and chained
  (:mod:`rsvo_ros.odometry.pairwise`).

Poses are ``T_world_camera`` of each frame's row-0 camera (CONTRACTS.md).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from rsvo_ros.core.lens import LensModel, as_lens, undistort_points
from rsvo_ros.odometry.frame import FrameState, Observations
from rsvo_ros.odometry.pairwise import PairwiseChain
from rsvo_ros.odometry.tracker import FeatureTracker, TrackerOptions
from rsvo_ros.odometry.window import (
    WindowOdometry,
    WindowOptions,
    covariance_from_tracking,
)
from rsvo_ros.twoview import LMOptions, RansacOptions, RelativePoseResult

BACKENDS = ("window", "pairwise")


@dataclass
class PipelineOptions:
    """How the pipeline estimates; ``model``: "rs" | "gs" | "mvo"; ``backend``: "window" |
    "pairwise"."""

    model: str = "rs"
    backend: str = "window"
    mode: str = "fast"
    tracker: TrackerOptions = field(default_factory=TrackerOptions)
    ransac: RansacOptions = field(default_factory=RansacOptions)
    lm: LMOptions = field(default_factory=LMOptions)
    window: WindowOptions = field(default_factory=WindowOptions)
    min_tracks: int = 25  # pairwise: fewer tracked correspondences: re-initialise
    initial_scale: float = 1.0  # metres of the first pair's baseline (1 = up to scale)
    # RS: use that frames come from one continuous motion: the velocity prior is centred on the
    # constant velocity of each pair's motion over its stamps' interval, and the previous
    # pair's motion is one more start of the search (off: each pair on its own, as the paper)
    motion_prior: bool = True
    max_scale_change: float = 5.0  # pairwise: relative scale outside [1/x, x] is not trusted
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
    scale: float = 0.0  # pairwise: metres of this pair's baseline
    time_ms: float = 0.0
    relative: RelativePoseResult | None = None
    pts_prev: np.ndarray | None = None  # raw pixels of the pair (for drawing)
    pts_curr: np.ndarray | None = None
    inliers: np.ndarray | None = None  # (n,) of pts_curr: used by the estimate (for drawing)
    keyframe: bool = False  # window: this frame became a keyframe
    velocity: tuple[np.ndarray, np.ndarray] | None = None  # window: (w, v) in the row-0 frame

    @property
    def has_pose(self) -> bool:
        return self.T_world_cam is not None


class OdometryPipeline:
    """Feed frames with :meth:`process`; poses are ``T_world_camera`` at row-0 times."""

    def __init__(self, K: np.ndarray, D: LensModel | np.ndarray | None, line_delay: float,
                 options: PipelineOptions | None = None):  # fmt: skip
        """``D``: the lens (:class:`LensModel`, bare plumb_bob / rational_polynomial
        coefficients, or None for an undistorted image)."""
        self.options = options or PipelineOptions()
        if self.options.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {self.options.backend!r}")
        self.set_camera(K, D, line_delay)
        self.tracker = FeatureTracker(self.options.tracker)
        self.reset()

    def set_camera(self, K: np.ndarray, D: LensModel | np.ndarray | None,
                   line_delay: float) -> None:  # fmt: skip
        K = np.asarray(K, float)
        if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"camera matrix K must be a finite 3x3 with positive focal "
                             f"lengths, got {K.tolist()}")  # fmt: skip
        if not np.isfinite(line_delay) or line_delay < 0:
            raise ValueError(f"line_delay must be finite and >= 0, got {line_delay}")
        D = as_lens(D)
        changed = hasattr(self, "window") and not self._same_camera(K, D, float(line_delay))
        self.K, self.D, self.line_delay = K, D, float(line_delay)
        if changed:
            self.reset()  # the backends hold the camera: a new camera starts a new trajectory

    def _same_camera(self, K: np.ndarray, D: LensModel | None, line_delay: float) -> bool:
        return D == self.D and np.array_equal(K, self.K) and line_delay == self.line_delay

    def reset(self) -> None:
        """Forget everything: the next frame starts a new trajectory at the identity."""
        o = self.options
        self.tracker.reset()
        self.T_world_cam = np.eye(4)
        self.covariance = np.zeros((6, 6))
        self._last_stamp: int | None = None
        self._index = 0
        self._started = False
        tau = self.line_delay if o.model == "rs" else 0.0
        self.chain = PairwiseChain(self.K, self.D, self.line_delay, o.model, o.mode, o.ransac,
                                   o.lm, o.initial_scale, o.motion_prior, o.max_scale_change,
                                   o.seed)  # fmt: skip
        self.window = WindowOdometry(self.K, tau, o.window, o.model, o.ransac, o.lm,
                                     o.initial_scale, o.motion_prior, o.seed)  # fmt: skip
        self._window_was_initialising = True

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
        if self.options.backend == "window":
            interval = None if prev_stamp is None else (stamp_ns - prev_stamp) * 1e-9
            return self._process_window(stamp_ns, pair, interval, idx, result)
        if not self._started:
            self._started = True
            return result("first", "first frame: trajectory origin",
                          num_tracks=self.tracker.num_tracks)
        n = len(pair.ids)
        if n < self.options.min_tracks:
            self.chain.hold()  # the tracker has already re-detected corners on this frame
            self.covariance = self.chain.covariance
            return result("held", f"lost tracking ({n} tracks): re-initialised",
                          num_tracks=self.tracker.num_tracks)
        step = self.chain.step(pair, (stamp_ns - prev_stamp) * 1e-9, idx)
        self.T_world_cam, self.covariance = self.chain.T_world_cam, self.chain.covariance
        rel = step.relative
        return result(step.status, step.reason, num_tracks=n, num_inliers=step.num_inliers,
                      inlier_ratio=step.inlier_ratio, scale=step.scale, relative=rel,
                      pts_prev=pair.pts_prev, pts_curr=pair.pts_curr,
                      inliers=None if rel is None else rel.inliers)  # fmt: skip

    def observations(self) -> Observations:
        """Every feature of the last image as the window backend takes them."""
        ids, raw = self.tracker.current()
        px = undistort_points(raw, self.K, self.D)
        x = (px - self.K[:2, 2]) / np.array([self.K[0, 0], self.K[1, 1]])
        return Observations(ids, x, self.window.row_time(raw[:, 1]), px, raw[:, 1])

    def _process_window(self, stamp_ns: int, pair, interval: float | None, idx: int,
                        result) -> FrameResult:  # fmt: skip
        """The window backend; while its map initialises, the pairwise chain poses the frames
        and the map starts in the chain's world and scale."""
        obs = self.observations()
        step = None
        bootstrap = self.options.window.pairwise_bootstrap and self.window.initialising
        if bootstrap and interval is not None and len(pair.ids) >= self.options.min_tracks:
            step = self.chain.step(pair, interval, idx)
        hint = self.chain.T_world_cam.copy() if bootstrap else None
        out = self.window.track(stamp_ns, obs, hint)
        state: FrameState | None = out.state
        if out.status != "posed" and step is not None and step.status == "posed":
            self.T_world_cam, self.covariance = self.chain.T_world_cam, self.chain.covariance
            return result("posed", f"pairwise while the map initialises ({out.reason})",
                          num_tracks=len(obs), num_inliers=step.num_inliers,
                          inlier_ratio=step.inlier_ratio, relative=step.relative,
                          pts_prev=pair.pts_prev, pts_curr=pair.pts_curr,
                          inliers=step.relative.inliers)  # fmt: skip
        if state is not None and out.status == "posed":
            self.T_world_cam = self.window.row0_pose(state)  # held frames keep the last pose
        if out.status == "posed":
            self.covariance = covariance_from_tracking(out)
        else:
            self.covariance = self.covariance + np.diag([1e-2] * 3 + [1e-3] * 3)
        if self.window.initialising and not self._window_was_initialising:
            # the map was lost and starts over: the chain goes on from here
            speed = 0.0 if state is None else float(np.linalg.norm(state.v))
            self.chain.restart(self.T_world_cam, speed * (interval or 0.0))
        self._window_was_initialising = self.window.initialising
        velocity = None
        if state is not None and out.status == "posed":
            velocity = state.row0_velocities(-self.window.row_ref * self.window.line_delay)
        n = len(obs)
        reason = out.reason
        if out.status == "held" and interval is not None and len(pair.ids) \
                < self.options.min_tracks:
            reason = f"lost tracking ({len(pair.ids)} tracks): {reason}"
        return result(out.status, reason, num_tracks=n, num_inliers=out.inliers,
                      inlier_ratio=out.inliers / max(out.tracked, 1),
                      pts_prev=pair.pts_prev, pts_curr=pair.pts_curr,
                      keyframe=out.keyframe, velocity=velocity)  # fmt: skip
