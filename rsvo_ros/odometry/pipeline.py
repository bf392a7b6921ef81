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

import dataclasses
import functools
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from rsvo_ros.core.geometry import pose_inverse, rigid_correction
from rsvo_ros.core.lens import LensModel, as_lens, undistort_points
from rsvo_ros.core.readout import check_readout, sensor_line_count, sensor_rows
from rsvo_ros.odometry.frame import FrameState, Observations
from rsvo_ros.odometry.line_delay import (
    LineDelayCalibrator,
    LineDelayEstimate,
    LineDelayOptions,
    RefinedLineDelay,
    RefineOptions,
    refine_line_delay,
)
from rsvo_ros.odometry.pairwise import (
    BOOTSTRAP_UNCERTAIN_ROTATION_DEG,
    ROTATION_ONLY_PARALLAX_PX,
    UNCERTAIN_PAIR_ROTATION_DEG,
    PairwiseChain,
)
from rsvo_ros.odometry.refine_worker import RefineJob, lower_thread_priority
from rsvo_ros.odometry.relocalize import describe
from rsvo_ros.odometry.tracker import FeatureTracker, TrackerOptions
from rsvo_ros.odometry.twist import Twist, TwistEstimator
from rsvo_ros.odometry.window import (
    WindowOdometry,
    WindowOptions,
    covariance_from_tracking,
)
from rsvo_ros.twoview import LMOptions, RansacOptions, RelativePoseResult
from rsvo_ros.twoview.estimator import warm_up as warm_up_two_view

BACKENDS = ("window", "pairwise")
# a fault of the package (an exception from process()) in this many frames in a row: the node
# and the replay reset the pipeline and start a new trajectory, instead of skipping every
# frame after a fault that the pipeline's state carries on (the first traceback is logged)
FAULT_RESET_AFTER = 3
# close(): how long a line-delay refinement still running is waited for
REFINE_WAIT_S = 300.0
# with TrackerOptions.decimation, a side of the reduced image under this many pixels is a
# skipped frame (nothing to track in it)
MIN_DECIMATED_SIZE_PX = 16


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
    # pairwise chain (the pairwise backend, and the window's frames while its map starts): a
    # pair whose tracks a turning camera explains to within this many px (median, at 1000 px
    # focal) is posed by that rotation (odometry/rotation.py): too short a baseline for the
    # pair estimator, as between a walk's consecutive frames (0: never)
    rotation_only_parallax_px: float = ROTATION_ONLY_PARALLAX_PX
    # RS pairwise chain: a pair estimate whose rotation std is over this many degrees takes a
    # turning camera's rotation at any parallax, its scale the last baseline (0: never; None:
    # the backend's choice, BOOTSTRAP_UNCERTAIN_ROTATION_DEG for the window's bootstrap chain,
    # UNCERTAIN_PAIR_ROTATION_DEG for the pairwise backend)
    uncertain_rotation_deg: float | None = None
    seed: int = 0
    # Time that jumps. Back by more than this many frame intervals (a looped bag, a restarted
    # simulator): the odometry resets and a new trajectory starts at that frame; back by less
    # (a late frame): the frame is skipped.
    reset_back_frames: float = 2.0
    # Ahead by more than this many frame intervals (and at least ahead_min_s): a stamp off the
    # stream's cadence (a corrupt header) is one bad frame, skipped, the clock kept; when the
    # next frame follows the new time at the cadence, the stream did jump: it goes on from there.
    ahead_frames: float = 20.0
    ahead_min_s: float = 1.0
    # line_delay auto (window backend, RS model): estimate the line delay from the video
    # (:mod:`rsvo_ros.odometry.line_delay`) and use it; until the first estimate the given
    # line delay is used, or, when it is 0, a readout of auto_initial_readout frame intervals
    # (at 30 Hz; 0: start as a global shutter)
    line_delay_auto: bool = False
    line_delay_calibration: LineDelayOptions = field(default_factory=LineDelayOptions)
    auto_initial_readout: float = 0.5
    # line_delay auto: when the first estimate comes, the frames of the trajectory so far (at
    # most this many, kept as images) are processed again with it, from a fresh start, before
    # the next frame: the frames run before it with the starting readout leave the map and its
    # scale distorted for the rest of the run (README, "Unknown line delay"). The re-posed
    # frames are in FrameResult.revised; the published pose stays continuous (a rigid offset).
    # 0: keep going with what those frames built (the node's default: processing them again
    # takes a second or two in one frame)
    line_delay_rerun_max_frames: int = 300
    # ... and again with a later estimate that differs from the one the frames last ran with
    # by more than line_delay_rerun_tolerance of it (the windows built with one readout pull
    # the next estimate towards it), at most line_delay_reruns times in all (on the README's
    # 38 line-delay bags 1 and 3 gave the one-pass ATE within 10 % of the true line delay's
    # on 26 and 28 of 33 rolling-shutter bags, on 12 fresh ones 8 and 8 of 10, geometric mean
    # 1.03 and 1.00 of the true line delay's; the estimate within 10 %: 19, 19; 7, 6)
    line_delay_reruns: int = 3
    line_delay_rerun_tolerance: float = 0.1
    # a given line delay (a first estimate) refined: the window removes the map's shear
    # (WindowOptions.shear_from_turns) and refined_line_delay() regresses the tracked frames'
    # turn rates during the readout on the turns between them (line_delay.refine_line_delay;
    # rsvo_calibrate's second pass). RS model, window backend, not with line_delay_auto
    line_delay_refine: bool = False
    line_delay_refinement: RefineOptions = field(default_factory=RefineOptions)
    # line_delay auto: once the trajectory has this many frames (kept as images) and an
    # estimate, a second pipeline runs them again at that estimate with line_delay_refine and
    # its refined value replaces the estimate (status "refined"; the calibrator stops). With
    # async mapping (the node) in a process of its own at the lowest CPU priority
    # (refine_worker.py), taken at a later frame; else inline, in that frame (the replay).
    # Without a non-zero estimate by twice this many frames: not refined. 0: the estimate is
    # the calibrator's (README, "The pipeline refines its own estimate after 150 frames")
    line_delay_auto_refine_frames: int = 150
    # ... only for frames that come at least this fast (their median interval): at 10-15 Hz
    # neither the first estimate nor its refinement was usable (README, "Refining the
    # estimate": the live node at 15 Hz went from -36 % to +133 %)
    line_delay_auto_refine_min_rate_hz: float = 25.0
    # which way the rolling shutter reads the images as they arrive (core/readout.py): "down"
    # (rows top to bottom, CONTRACTS.md), "up" (an image turned by 180 degrees: a camera
    # mounted upside down), "right" / "left" (columns: an image turned by 90 degrees, a phone
    # in portrait); line_delay is then per line read (a column for right / left)
    readout: str = "down"


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
    # (n,) of pts_curr: rejected by the estimate; None: every track that is not an inlier was
    # (window: tracks with no map point are neither)
    outliers: np.ndarray | None = None
    keyframe: bool = False  # window: this frame became a keyframe
    # "initialising" (no motion estimate yet), "tracking" or "lost" (the pose is held)
    tracking: str = "tracking"
    velocity: tuple[np.ndarray, np.ndarray] | None = None  # window: (w, v) in the row-0 frame
    time_reset: bool = False  # time jumped back: this frame starts a new trajectory
    mapping_ms: float = 0.0  # window: the part of time_ms spent in a window BA (keyframes)
    # window, async mapping: a window BA that ran on the mapping thread and was picked up at
    # this frame, its time (not part of time_ms: it ran beside the tracking)
    background_mapping_ms: float = 0.0
    refound: bool = False  # window: this frame re-found a lost map by its landmarks' descriptors
    # (gain, offset): the tracker found the brightness changed (auto exposure), ``image ~ gain x
    # previous image + offset``, and tracked in the previous image's grey levels; None: it did
    # not change (or the frame was not tracked)
    brightness_change: tuple[float, float] | None = None
    # (dx, dy), px at the tracking resolution: KLT alone kept too few tracks (a turn past its
    # reach) and they were found again from the images' shift by phase correlation
    # (TrackerOptions.shift_retry); None: KLT's own (or the frame was not tracked)
    image_shift: tuple[float, float] | None = None
    # line_delay auto: the first estimate came with this frame, and the trajectory's earlier
    # frames were processed again with it (PipelineOptions.line_delay_rerun_max_frames): their
    # new results, in the published odometry frame, oldest first
    revised: list[FrameResult] | None = None
    # the velocity since the last posed frame of the trajectory, in this frame's camera frame
    # (odometry/twist.py: nav_msgs/Odometry's twist); unknown (infinite covariance) where there
    # is none
    twist: Twist = field(default_factory=Twist)

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
        check_readout(self.options.readout)
        o = self.options
        if o.line_delay_auto_refine_frames < 0:
            raise ValueError(f"line_delay_auto_refine_frames must be >= 0 (0: off), got "
                             f"{o.line_delay_auto_refine_frames}")
        if o.line_delay_refine and (o.line_delay_auto or o.model != "rs" or o.backend != "window"):
            raise ValueError("line_delay_refine refines a given line delay: it needs the RS "
                             "model, the window backend and line_delay_auto off")
        self._image_size: tuple[int, int] | None = None  # (width, height) of the last image
        self.set_camera(K, D, line_delay)
        tracker = self.options.tracker
        if tracker.refine_window_px is None and self.options.backend == "pairwise":
            # the pairwise chain uses each track for one pair only, where the drift the
            # refinement removes does not add up; with it, its vehicles were 1.21x worse (README)
            tracker = replace(tracker, refine_window_px=0)
        self.tracker = FeatureTracker(tracker)
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
        if changed and self._refine_job is not None:  # a refinement for the old camera
            self._refine_job[0].cancel()
        self.K, self.D, self.given_line_delay = K, D, float(line_delay)
        if changed or not hasattr(self, "window"):
            # the line delay the pipeline runs with: the given one, or line_delay auto's
            self.line_delay = self.given_line_delay
            self.calibrator: LineDelayCalibrator | None = None
            self.line_delay_estimate = LineDelayEstimate("off")
            self.line_delay_history: list[dict] = []
            # the re-runs of the frames before the first estimate (and of later ones)
            self.line_delay_reruns: list[dict] = []
            # line_delay_refine: every posed frame's (stamp, R, w, line delay), whole run
            self.refine_log: list[tuple[int, np.ndarray, np.ndarray, float]] = []
            self._calibration_thread: threading.Thread | None = None
            self._calibration_result: LineDelayEstimate | None = None
            # line_delay_auto_refine_frames: the trajectory's frames for the refinement (None:
            # not kept), the refinement running in the background, and what it gave (summary)
            self._refine_frames: list[tuple[int, np.ndarray]] | None = None
            self._refine_unprocessed = 0  # of them, frames the caller did not process
            # (RefineJob, the estimate it refines, start time) while it runs
            self._refine_job: tuple | None = None
            # the estimate the running refinement started from: read (once), and when it was
            # put in use (ms after the refinement began; None: not taken before its end)
            self._refine_start_seen, self._refine_start_ms = False, None
            self.line_delay_auto_refinement: dict | None = None
            if self.options.line_delay_auto and self.options.model == "rs":
                self.line_delay_estimate = LineDelayEstimate(
                    "collecting", reason="no keyframe windows yet")
                if self.line_delay <= 0:  # the lines read are about twice the centre's
                    centre = K[0, 2] if self.options.readout in ("right", "left") else K[1, 2]
                    self.line_delay = self.options.auto_initial_readout / 30.0 \
                        / max(2.0 * float(centre), 1.0)
                if self.options.line_delay_auto_refine_frames > 0 \
                        and self.options.backend == "window":
                    self._refine_frames = []
        if changed:
            self.reset()  # the backends hold the camera: a new camera starts a new trajectory

    def refined_line_delay(self) -> RefinedLineDelay:
        """line_delay_refine: the line delay from the frames tracked so far
        (:func:`~rsvo_ros.odometry.line_delay.refine_line_delay`)."""
        if not self.options.line_delay_refine:
            return RefinedLineDelay("off", reason="line_delay_refine is off")
        log = list(self.refine_log)
        if not log:
            return RefinedLineDelay("not observable", reason="no frame was tracked by the map")
        stamps, R, w, taus = zip(*log, strict=True)
        return refine_line_delay(np.array(stamps), np.array(R), np.array(w), np.array(taus),
                                 self.options.line_delay_refinement)

    def _same_camera(self, K: np.ndarray, D: LensModel | None, line_delay: float) -> bool:
        return D == self.D and np.array_equal(K, self.K) and line_delay == self.given_line_delay

    def reset(self) -> None:
        """Forget everything: the next frame starts a new trajectory at the identity."""
        o = self.options
        self.tracker.reset()
        self.T_world_cam = np.eye(4)
        self.covariance = np.zeros((6, 6))
        self._last_stamp: int | None = None
        self._intervals: list[int] = []  # the last frame intervals (ns): the stream's cadence
        self._ahead_stamp: int | None = None  # a skipped far-ahead stamp
        # the newest frame the caller dropped unprocessed since the last processed one
        # (note_dropped): where the stream's clock is for the next frame's time checks
        self._dropped_stamp: int | None = None
        self._index = 0
        self._started = False
        tau = self.line_delay if o.model == "rs" else 0.0
        if hasattr(self, "window"):
            self.window.close()  # its mapping thread (async mapping)
        uncertain = o.uncertain_rotation_deg
        if uncertain is None:
            uncertain = (BOOTSTRAP_UNCERTAIN_ROTATION_DEG if o.backend == "window"
                         else UNCERTAIN_PAIR_ROTATION_DEG)  # fmt: skip
        self.chain = PairwiseChain(self.K, self.D, self.line_delay, o.model, o.mode, o.ransac,
                                   o.lm, o.initial_scale, o.motion_prior, o.max_scale_change,
                                   o.seed, o.rotation_only_parallax_px, uncertain)  # fmt: skip
        window_options = o.window
        if self.options.line_delay_refine:
            window_options = dataclasses.replace(o.window, shear_from_turns=True)
        self.window = WindowOdometry(self.K, tau, window_options, o.model, o.ransac, o.lm,
                                     o.initial_scale, o.motion_prior, o.seed)  # fmt: skip
        self.window.calibrator = self.calibrator  # kept across resets: the same camera
        self._window_was_initialising = True
        # T_odom_world: the published odometry is this times the window's estimate; each window
        # BA that moves the current frame updates it, so that the published pose stays
        # continuous while the map (and the keyframe path) take the correction (REP 105's odom)
        self.T_odom_world = np.eye(4)
        # T_odom_world at the last frame posed in a trusted map (WindowOdometry.in_trusted_map):
        # a frame that re-finds the map is posed in that map's world, and is published with it
        self._T_odom_trusted: np.ndarray | None = None
        self.twist = TwistEstimator()
        # line_delay auto before its first estimate: the trajectory's frames, to be processed
        # again with that estimate (None: not kept)
        estimated = any(h["line_delay_s"] is not None for h in self.line_delay_history)
        keep = (o.line_delay_auto and o.model == "rs" and o.backend == "window"
                and o.line_delay_rerun_max_frames > 0 and not estimated)  # fmt: skip
        self._rerun_frames: list[tuple[int, np.ndarray]] | None = [] if keep else None
        self._rerun_line_delay = self.line_delay  # what the kept frames last ran with
        self._rerun_due = False
        self._rerunning = False

    def process(self, stamp_ns: int, gray: np.ndarray) -> FrameResult:
        """One new frame (uint8 gray). Never raises for bad data: returns a skipped result."""
        self._revised = None
        res = self._process(stamp_ns, gray)
        if not self._rerunning:
            self._refine_step(stamp_ns)
        if res.status != "skipped":  # a skipped frame leaves the trajectory as it was
            continuous = (res.status == "posed" and res.tracking == "tracking"
                          and not res.refound and not res.time_reset)  # fmt: skip
            res.twist = self.twist.update(stamp_ns, res.T_world_cam, continuous)
        res.revised, self._revised = self._revised, None
        return res

    @property
    def image_size(self) -> tuple[int, int] | None:
        """(width, height) of the last image processed, None before any."""
        return self._image_size

    @property
    def wants_unprocessed_frames(self) -> bool:
        """True while the line-delay refinement keeps frames (:meth:`keep_unprocessed`)."""
        return self._refine_frames is not None and not self._rerunning

    def keep_unprocessed(self, stamp_ns: int, gray: np.ndarray) -> bool:
        """A frame the caller drops unprocessed to keep up (the node's newest-frame policy),
        given before the next processed frame: kept for the line-delay refinement's second
        pass only, which then sees the camera's frames, as a replay of the recording does.
        Not kept (False) when no refinement keeps frames, or for an image unlike the kept
        ones (not uint8 gray, another size) or a stamp not after the last kept one."""
        frames = self._refine_frames
        if frames is None or self._rerunning or not _is_gray(gray):
            return False
        if frames and (gray.shape != frames[-1][1].shape or stamp_ns <= frames[-1][0]):
            return False
        frames.append((int(stamp_ns), gray.copy()))
        self._refine_unprocessed += 1
        return True

    def note_dropped(self, stamp_ns: int) -> None:
        """A frame the caller received and dropped unprocessed to keep up (the node's
        newest-frame policy), given before the next processed frame: the next frame's stamp
        is checked against it (a stall of 20 frame intervals or a second, with the frames
        dropped meanwhile, made the next frame look far ahead of the stream and skipped it,
        logged as bad input). Ignored before the first frame and for a stamp not after the
        last processed one."""
        last = self._last_stamp
        if last is not None and stamp_ns > last:
            self._dropped_stamp = max(self._dropped_stamp or stamp_ns, int(stamp_ns))

    def _process(self, stamp_ns: int, gray: np.ndarray) -> FrameResult:
        t0 = time.perf_counter()
        idx = self._index
        self._index += 1
        tracked = False

        def result(status, reason="", **kw):
            res = FrameResult(idx, stamp_ns, status, reason,
                              None if status == "skipped" else self.T_world_cam.copy(),
                              self.covariance.copy(), **kw)  # fmt: skip
            res.brightness_change = self.tracker.last_photometric if tracked else None
            res.image_shift = self.tracker.last_shift if tracked else None
            res.tracking = self._tracking_state(status, reason)
            res.time_ms = (time.perf_counter() - t0) * 1e3
            return res

        if not _is_gray(gray):
            return result("skipped", "not a non-empty uint8 gray image")
        factor = self.tracker.options.decimation
        if factor > 1 and min(gray.shape) < MIN_DECIMATED_SIZE_PX * factor:
            return result("skipped", f"a {gray.shape[1]}x{gray.shape[0]} image is too small to "
                                     f"track at decimation {factor} (under "
                                     f"{MIN_DECIMATED_SIZE_PX} px a side)")
        jump = self._time_jump(stamp_ns)
        if jump == "reset":
            back = (self._last_stamp - stamp_ns) * 1e-9
            if self._refine_frames is not None:  # the new trajectory's frames only
                self._refine_frames, self._refine_unprocessed = [], 0
            self.reset()  # as a new pipeline: frame indices (and RANSAC seeds) start over
            res = self._process(stamp_ns, gray)
            res.time_reset = True
            res.reason = f"time jumped back {back:.3f} s: odometry reset, a new trajectory " \
                         f"starts here ({res.reason})"
            return res
        if jump:
            return result("skipped", jump)
        prev_stamp, self._last_stamp = self._last_stamp, stamp_ns
        self._dropped_stamp = None
        if prev_stamp is not None:
            self._intervals = (self._intervals + [stamp_ns - prev_stamp])[-15:]
        height, width = gray.shape
        self._image_size = (width, height)
        self._calibrate(stamp_ns, sensor_line_count(self.options.readout, width, height))
        if self._rerun_due:
            self._revised = self._rerun(idx)
        kept = None  # one copy of the image for the re-runs and the refinement
        if self._rerun_frames is not None and not self._rerunning:
            if len(self._rerun_frames) < self.options.line_delay_rerun_max_frames:
                kept = gray.copy()
                self._rerun_frames.append((stamp_ns, kept))
            else:  # too long without an estimate: go on with what the frames built
                self._rerun_frames = None
        if self._refine_frames is not None and not self._rerunning:
            self._refine_frames.append((stamp_ns, gray.copy() if kept is None else kept))
        pair = self.tracker.track(gray, stamp_ns)
        tracked = True
        if self.options.readout != "down":
            pair.sensor_rows_prev = self._rows(pair.pts_prev)
            pair.sensor_rows_curr = self._rows(pair.pts_curr)
        if self.options.backend == "window":
            interval = None if prev_stamp is None else (stamp_ns - prev_stamp) * 1e-9
            return self._process_window(stamp_ns, gray, pair, interval, idx, result)
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

    # ------------------------------------------------------------------ line delay auto

    def _calibrate(self, stamp_ns: int, height: int) -> None:
        """line_delay auto: feed the calibrator, estimate when it is due (on a thread with
        async mapping, else inline), and go on with a new estimate."""
        o = self.options
        if not o.line_delay_auto or o.model != "rs" or o.backend != "window" \
                or self._rerunning:
            return
        if self.calibrator is None:
            self.calibrator = LineDelayCalibrator(height, o.line_delay_calibration)
            self.window.calibrator = self.calibrator
        cal = self.calibrator
        if self.line_delay_estimate.status in ("converged", "refined"):
            return
        cal.add_frame()
        done, self._calibration_result = self._calibration_result, None
        if done is not None:
            self._take_estimate(done, stamp_ns)
            if self._rerun_due:  # the frames so far run again first, and feed it anew
                return
        running = self._calibration_thread is not None and self._calibration_thread.is_alive()
        if running or not cal.due() or self._refine_job is not None:
            # (while the refinement runs, in its process, the calibrator waits: the
            # refinement estimates over all its windows itself, and its result replaces any
            # estimate the calibrator would make meanwhile; on the node the two took the CPU
            # from the tracking and from each other)
            return
        interval = (self.frame_interval_ns or 0.0) * 1e-9
        if o.window.async_mapping:
            def run():
                # as background work: the tracking and the mapping go first (what it still
                # costs them is the CPU it takes: README, "The calibrator's re-solves,
                # warm-started")
                lower_thread_priority()
                self._calibration_result = cal.estimate(interval)

            self._calibration_thread = threading.Thread(target=run, name="rsvo_line_delay",
                                                        daemon=True)  # fmt: skip
            self._calibration_thread.start()
        else:
            self._take_estimate(cal.estimate(interval), stamp_ns)

    def _take_estimate(self, est: LineDelayEstimate, stamp_ns: int) -> None:
        self.line_delay_estimate = est
        self.line_delay_history.append({"stamp_ns": int(stamp_ns), **est.as_dict()})
        if est.status in ("estimated", "converged", "refined") and est.line_delay_s is not None:
            self._set_line_delay(float(est.line_delay_s))
            if self._rerun_frames is not None:
                # an estimate away from what the frames so far ran with: they run again with it;
                # near it (a fixed point of estimate and re-run): they are kept no longer
                ran, o = self._rerun_line_delay, self.options
                away = abs(self.line_delay - ran) > o.line_delay_rerun_tolerance * max(
                    self.line_delay, ran)
                if away and len(self.line_delay_reruns) < o.line_delay_reruns:
                    self._rerun_due = bool(self._rerun_frames)
                else:
                    self._rerun_frames = None
        elif est.status == "not observable" and not self.line_delay_history[:-1]:
            # nothing measured yet: back to the given value (0: a global shutter) while it
            # goes on collecting
            self._set_line_delay(self.given_line_delay)

    def _refine_step(self, stamp_ns: int) -> None:
        """line_delay_auto_refine_frames: take a finished refinement; start one when the
        trajectory has its frames and an estimate or the windows for one (or give up without
        them)."""
        job = self._refine_job
        if job is not None and job[0].done():
            self._refine_job = None
            start, ref = job[0].result()
            self._take_refined(ref, start or job[1], job[1], job[2], stamp_ns)
        elif job is not None and not self._refine_start_seen:
            # the process has estimated over all the windows and runs the second pass: its
            # start, more windows than the running estimate's, is used meanwhile (the node's
            # second pass takes seconds: README, "The refinement's start in use at once")
            start = job[0].started_from()
            if start is not None:
                self._refine_start_seen = True
                if self._replaces(start, job[1]):
                    self._take_estimate(start, stamp_ns)
                    self._refine_start_ms = (time.perf_counter() - job[2]) * 1e3
        frames, n = self._refine_frames, self.options.line_delay_auto_refine_frames
        if frames is None or len(frames) < n:
            return
        e, cal = self.line_delay_estimate, self.calibrator
        ready = (e.status in ("estimated", "converged") and bool(e.line_delay_s)) or (
            cal is not None and cal.has_data())
        if not ready:
            if len(frames) >= 2 * n:
                self._refine_frames = None
                self._not_refined(len(frames), f"no non-zero estimate after {len(frames)} "
                                               f"frames ({e.status})")  # fmt: skip
            return
        self._refine_frames = None  # once per camera
        rate = 1e9 / max(float(np.median(np.diff([st for st, _ in frames]))), 1.0)
        minimum = self.options.line_delay_auto_refine_min_rate_hz
        if rate < minimum:
            self._not_refined(len(frames), f"the frames came at {rate:.1f} Hz, under the "
                                           f"{minimum:g} Hz the refinement needs")  # fmt: skip
            return
        t0 = time.perf_counter()
        interval = (self.frame_interval_ns or 0.0) * 1e-9
        if self.options.window.async_mapping:
            # the node: in a process of its own at the lowest CPU priority (refine_worker.py),
            # the calibrator's windows so far with it (its own estimates lag on their thread)
            args = (self.K, self.D, self.options, frames,
                    None if cal is None else cal.snapshot(), interval, e)  # fmt: skip
            self._refine_job = (RefineJob(args), e, t0)
            self._refine_start_seen, self._refine_start_ms = False, None
        else:
            start, ref = refine_from_estimate(self.K, self.D, self.options, frames, cal,
                                              interval, e)  # fmt: skip
            self._take_refined(ref, start, e, t0, stamp_ns)

    def _not_refined(self, frames: int, reason: str) -> None:
        self.line_delay_auto_refinement = {"status": "not refined", "frames": frames,
                                           "line_delay_s": None, "reason": reason}

    def _take_refined(self, ref: RefinedLineDelay, start: LineDelayEstimate,
                      running: LineDelayEstimate, t0: float, stamp_ns: int) -> None:
        """A finished refinement of the estimate ``start`` (over the calibrator's windows
        when it began; ``running`` the estimate in use then): a refined line delay replaces
        the estimate (as a new estimate: the kept frames may run again with it); otherwise
        ``start``, if newer than the estimate in use now, replaces it."""
        first = start.line_delay_s
        self.line_delay_auto_refinement = {
            **ref.as_dict(), "first_line_delay_s": first, "first_std_s": start.std_s,
            "first_windows": start.windows,
            "running_line_delay_s": running.line_delay_s,
            "frames_unprocessed": self._refine_unprocessed,
            "first_in_use_after_ms": self._refine_start_ms,
            "time_ms": (time.perf_counter() - t0) * 1e3, "stamp_ns": int(stamp_ns)}
        if ref.status == "refined" and first and ref.line_delay_s \
                and np.isfinite(ref.line_delay_s):  # fmt: skip
            self._take_estimate(replace(
                start.refined(ref.line_delay_s, ref.std_s), frames=ref.frames,
                reason=f"refined in a second pass over {ref.frames} tracked frames "
                       f"({ref.blocks} blocks) from {first * 1e6:.2f} us/row"),
                stamp_ns)  # fmt: skip
            return
        if self._replaces(start, running):
            self._take_estimate(start, stamp_ns)

    def _replaces(self, start: LineDelayEstimate, running: LineDelayEstimate) -> bool:
        """Whether a refinement's ``start`` (the calibrator's estimate over all its windows;
        ``running`` the estimate in use when the refinement began) is to replace the
        estimate in use now: a new estimate of at least as many windows, unless that one is
        converged or refined (taken once: not again when the refinement ends unrefined)."""
        now = self.line_delay_estimate
        return start != running and start != now \
            and start.status in ("estimated", "converged") \
            and now.status not in ("converged", "refined") and start.windows >= now.windows

    def _set_line_delay(self, line_delay: float) -> None:
        if line_delay != self.line_delay:
            self.line_delay = line_delay
            self.window.set_line_delay(line_delay)
            self.chain.line_delay = line_delay

    def _rerun(self, index: int) -> list[FrameResult]:
        """line_delay auto's first estimate (or a later one away from it, see
        ``PipelineOptions.line_delay_reruns``): the trajectory's frames so far processed again
        from a fresh start with it (tracking, map, window BA; the calibrator's windows and
        poses replaced by the new run's), before the frame ``index``. The last re-run pose is
        put where the last published one was (a rigid offset for all of them): the published
        odometry goes on without a jump. Returns the frames' new results."""
        frames, self._rerun_due = self._rerun_frames, False
        t0 = time.perf_counter()
        clock = (self._last_stamp, list(self._intervals), self._ahead_stamp)
        published = self.T_world_cam.copy()
        if self.calibrator is not None:
            self.calibrator.restart()
        self.reset()  # keeps the line delay, its estimate and the calibrator
        self._rerunning = True
        try:
            results = [self.process(stamp, gray) for stamp, gray in frames]
        finally:
            self._rerunning = False
        more = len(self.line_delay_reruns) + 1 < self.options.line_delay_reruns
        self._rerun_frames = frames if more else None  # for the next re-run, if any
        self._rerun_line_delay = self.line_delay
        D = rigid_correction(self.T_world_cam, published)
        if np.isfinite(D).all() and np.isfinite(self.T_world_cam).all():
            self.T_odom_world = D @ self.T_odom_world
            if self._T_odom_trusted is not None:
                self._T_odom_trusted = D @ self._T_odom_trusted
            self.T_world_cam = D @ self.T_world_cam
            J = np.kron(np.eye(2), D[:3, :3])
            self.covariance = J @ self.covariance @ J.T
            for r in results:
                if r.T_world_cam is not None:
                    r.T_world_cam = D @ r.T_world_cam
        self._last_stamp, self._intervals, self._ahead_stamp = clock
        self._index = index + 1
        self.line_delay_reruns.append({"frames": len(frames), "stamp_ns": int(clock[0] or 0),
                                       "time_ms": (time.perf_counter() - t0) * 1e3,
                                       "line_delay_s": self.line_delay})  # fmt: skip
        return results

    def close(self, refine_wait_s: float = REFINE_WAIT_S) -> None:
        """Stop the background threads (async mapping, line-delay estimation); a line-delay
        refinement still running is waited for up to ``refine_wait_s`` and taken, or stopped
        (status "failed": it did not finish; the node waits briefly, a replay to the end)."""
        self.window.close()
        if self._calibration_thread is not None:
            self._calibration_thread.join(timeout=60.0)
        done, self._calibration_result = self._calibration_result, None
        if done is not None and self.line_delay_estimate.status not in ("converged", "refined"):
            # an estimate that finished after the last frame (async mapping: it runs on a
            # thread, 1-2 s): taken, not lost (the node saves the last one at shutdown)
            self._take_estimate(done, self._last_stamp or 0)
        job, self._refine_job = self._refine_job, None
        if job is not None:  # running after the last frame
            job[0].wait(refine_wait_s)
            start, ref = job[0].result()
            self._take_refined(ref, start or job[1], job[1], job[2], self._last_stamp or 0)

    @property
    def frame_interval_ns(self) -> float | None:
        """The stream's cadence (median of the last intervals), None before two frames."""
        return float(np.median(self._intervals)) if self._intervals else None

    def _time_jump(self, stamp_ns: int) -> str | None:
        """None: an ordinary next stamp; "reset": time went back a lot; else why the frame is
        skipped (a duplicate, a late frame, a stamp far ahead of the cadence)."""
        last = self._last_stamp
        if last is None:
            return None
        o = self.options
        interval = self.frame_interval_ns
        if stamp_ns == last:
            return f"duplicate stamp ({stamp_ns} ns)"
        if stamp_ns < last:
            if interval is None or last - stamp_ns > o.reset_back_frames * interval:
                return "reset"
            return f"backwards stamp ({stamp_ns} after {last} ns)"
        ahead = max(o.ahead_frames * (interval or 0.0), o.ahead_min_s * 1e9)
        # after the frames the caller dropped (note_dropped), from the newest of them
        if stamp_ns - max(last, self._dropped_stamp or last) <= ahead:
            self._ahead_stamp = None
            return None
        pending, self._ahead_stamp = self._ahead_stamp, stamp_ns
        if pending is not None and 0 < stamp_ns - pending <= max(3 * (interval or 0), 0.5e9):
            self._ahead_stamp = None  # two frames agree: the stream jumped (or paused)
            return None
        return (f"stamp far ahead of the stream ({(stamp_ns - last) * 1e-9:.3f} s after the "
                f"last frame; the clock is kept)")

    def _tracking_state(self, status: str, reason: str) -> str:
        if status == "first" or reason.startswith("initialising"):
            return "initialising"
        return "lost" if status == "held" else "tracking"

    def map_points(self) -> np.ndarray:
        """(M, 3) points of the local map in the odometry frame (window backend; the pairwise
        chain keeps no map: empty)."""
        if self.options.backend != "window":
            return np.zeros((0, 3))
        X = self.window.map_points()
        return X @ self.T_odom_world[:3, :3].T + self.T_odom_world[:3, 3]

    def keyframe_poses(self, last: int | None = None) -> list[tuple[int, np.ndarray]]:
        """``(stamp_ns, T_odom_camera)`` of the keyframes (all, or the ``last`` ones) as the
        window last refined them, in the odometry frame (window backend; pairwise: empty)."""
        if self.options.backend != "window":
            return []
        return [(stamp, self.T_odom_world @ T) for stamp, T in self.window.keyframe_poses(last)]

    def _rows(self, raw: np.ndarray) -> np.ndarray:
        """(N,) the RS timing rows of raw pixels ``raw`` (N, 2) of the last image."""
        if self.options.readout == "down" or self._image_size is None:
            return np.asarray(raw, float)[:, 1]
        return sensor_rows(raw, self.options.readout, *self._image_size)

    def observations(self, gray: np.ndarray | None = None) -> Observations:
        """Every feature of the last image as the window backend takes them (with ``gray``,
        the image, their ORB descriptors on demand: ``Observations.describe``)."""
        ids, raw = self.tracker.current()
        px = undistort_points(raw, self.K, self.D)
        x = (px - self.K[:2, 2]) / np.array([self.K[0, 0], self.K[1, 1]])
        rows = self._rows(raw)
        obs = Observations(ids, x, self.window.row_time(rows), px, rows)
        if gray is not None:
            obs.describe = functools.cache(functools.partial(describe, gray, raw))
        return obs

    def _process_window(self, stamp_ns: int, gray: np.ndarray, pair, interval: float | None,
                        idx: int, result) -> FrameResult:  # fmt: skip
        """The window backend; while its map initialises, the pairwise chain poses the frames
        and the map starts in the chain's world and scale."""
        obs = self.observations(gray)
        step = None
        bootstrap = self.options.window.pairwise_bootstrap and self.window.initialising
        if bootstrap and interval is not None and len(pair.ids) >= self.options.min_tracks:
            step = self.chain.step(pair, interval, idx)
        hint = self.chain.T_world_cam.copy() if bootstrap else None
        # the chain's world (the odometry frame) in the lost map's, whose landmarks the memory
        # holds: a new map's frames try to re-find it
        memory_from_hint = None
        if bootstrap and self._T_odom_trusted is not None:
            memory_from_hint = pose_inverse(self._T_odom_trusted)
        out = self.window.track(stamp_ns, obs, hint, memory_from_hint)
        state: FrameState | None = out.state
        if self.options.line_delay_refine and out.status == "posed" and state is not None:
            self.refine_log.append((stamp_ns, state.R.copy(), state.w.copy(), self.line_delay))
        if out.status != "posed" and step is not None and step.status == "posed":
            self.T_world_cam, self.covariance = self.chain.T_world_cam, self.chain.covariance
            return result("posed", f"pairwise while the map initialises ({out.reason})",
                          num_tracks=len(obs), num_inliers=step.num_inliers,
                          inlier_ratio=step.inlier_ratio, relative=step.relative,
                          pts_prev=pair.pts_prev, pts_curr=pair.pts_curr,
                          inliers=step.relative.inliers)  # fmt: skip
        started = bootstrap and not self.window.initialising and state is not None
        if started:
            # the new map starts where the chain has this frame: the published odometry goes on
            # without a jump (the map's pose of it differs by the chain's drift since the map's
            # first keyframe: 4-14 deg on walks, one frame's jump)
            T_odom_world = rigid_correction(self.window.row0_pose(state), self.chain.T_world_cam)
            self.T_odom_world = T_odom_world if np.isfinite(T_odom_world).all() else np.eye(4)
        if out.refound and self._T_odom_trusted is not None:
            # back in the world of the map that was lost: its odometry frame, not the one the
            # rebuilt map's (or the chain's) continuity gave
            self.T_odom_world = self._T_odom_trusted.copy()
        if state is not None and out.status == "posed":
            for before, after in [] if started else out.ba_moved:
                # a BA moved a frame: keep odometry continuous
                D = rigid_correction(self.window.row0_pose(after), self.window.row0_pose(before))
                if np.isfinite(D).all():  # never a NaN pose
                    self.T_odom_world = self.T_odom_world @ D
            # held frames keep the last pose
            self.T_world_cam = self.T_odom_world @ self.window.row0_pose(state)
            if self.window.in_trusted_map(stamp_ns):
                self._T_odom_trusted = self.T_odom_world.copy()
        if out.status == "posed":
            R = self.T_odom_world[:3, :3]
            J = np.kron(np.eye(2), R)
            self.covariance = J @ covariance_from_tracking(out) @ J.T
        else:
            self.covariance = self.covariance + np.diag([1e-2] * 3 + [1e-3] * 3)
        if self.window.initialising and not self._window_was_initialising:
            # the map was lost and starts over: the chain goes on from here
            speed = 0.0 if state is None else float(np.linalg.norm(state.v))
            if out.stall_restart and state is not None:
                # after a stall: from the predicted pose, with a usual frame interval's step
                T = self.T_odom_world @ self.window.row0_pose(state)
                if np.isfinite(T).all():
                    self.T_world_cam = T
                cadence = (self.frame_interval_ns or 0.0) * 1e-9
                interval = min(interval or 0.0, cadence) if cadence > 0 else interval
            self.chain.restart(self.T_world_cam, speed * (interval or 0.0))
        self._window_was_initialising = self.window.initialising
        velocity = None
        if state is not None and out.status == "posed":
            velocity = state.row0_velocities(self.window.row0_time())
        n = len(obs)
        reason = out.reason
        if out.status == "held" and interval is not None and len(pair.ids) \
                < self.options.min_tracks:
            reason = f"lost tracking ({len(pair.ids)} tracks): {reason}"
        ba_ms = out.ba.time_ms if out.ba is not None else 0.0
        drawn = {}
        if out.inlier_ids is not None and out.status == "posed":
            drawn = {"inliers": np.isin(pair.ids, out.inlier_ids),
                     "outliers": np.isin(pair.ids, out.outlier_ids)}
        return result(out.status, reason, num_tracks=n, num_inliers=out.inliers,
                      inlier_ratio=out.inliers / max(out.tracked, 1),
                      pts_prev=pair.pts_prev, pts_curr=pair.pts_curr, **drawn,
                      keyframe=out.keyframe, velocity=velocity,
                      mapping_ms=ba_ms if not out.ba_background else 0.0,
                      background_mapping_ms=ba_ms if out.ba_background else 0.0,
                      refound=out.refound)  # fmt: skip


def _is_gray(gray: np.ndarray | None) -> bool:
    """A frame the pipeline takes: a non-empty 2-D uint8 image."""
    return gray is not None and gray.ndim == 2 and gray.dtype == np.uint8 and gray.size > 0


def refine_pass(K: np.ndarray, D: LensModel | None, line_delay: float,
                options: PipelineOptions,
                frames: list[tuple[int, np.ndarray]]) -> RefinedLineDelay:  # fmt: skip
    """``frames`` processed by a new pipeline at ``line_delay`` with the map's shear removed
    (``line_delay_refine``; the options otherwise those of the pipeline that kept them), and
    its refined line delay (rsvo_calibrate's second pass). Never raises: a failure is
    reported as status "failed"."""
    options = replace(options, line_delay_auto=False, line_delay_refine=True,
                      line_delay_rerun_max_frames=0, line_delay_auto_refine_frames=0,
                      window=replace(options.window, async_mapping=False))  # fmt: skip
    try:
        second = OdometryPipeline(K, D, line_delay, options)
        for stamp, gray in frames:
            second.process(stamp, gray)
        second.close()
        return second.refined_line_delay()
    except Exception as exc:  # noqa: BLE001 - the estimate it refines is kept
        return RefinedLineDelay("failed", reason=f"the second pass failed: {exc!r}")


def refine_from_estimate(K: np.ndarray, D: LensModel | None, options: PipelineOptions,
                         frames: list[tuple[int, np.ndarray]],
                         calibrator: LineDelayCalibrator | None, frame_interval_s: float,
                         running: LineDelayEstimate,
                         on_start: Callable[[LineDelayEstimate], None] | None = None,
                         ) -> tuple[LineDelayEstimate, RefinedLineDelay]:  # fmt: skip
    """line_delay auto's refinement after its first ``frames``: the ``calibrator``'s estimate
    over all its windows so far (``running``, the estimate in use, where that gives none),
    refined by :func:`refine_pass` over the frames. Returns the estimate it started from and
    the refinement ("not refined" for a zero or no estimate: nothing to refine);
    ``on_start(start)`` is called before the second pass (the node's worker hands the estimate
    over then, to be used while the pass runs). The
    calibrator's own estimates come every few windows and, with async mapping, on a thread
    that falls behind: by the node's 150th frame they covered 5 of the 9-52 windows, or none,
    on the line-delay table's sequences (README, "The node's refinement: all the windows, all
    the frames")."""
    start = running
    if calibrator is not None:
        try:
            full = calibrator.estimate(frame_interval_s)
        except Exception as exc:  # noqa: BLE001 - the running estimate is refined instead
            full = LineDelayEstimate("failed", reason=f"the estimate failed: {exc!r}")
        if full.status in ("estimated", "converged") and full.line_delay_s is not None:
            start = full
    if start.status not in ("estimated", "converged") or not start.line_delay_s:
        why = (f"the estimate over {start.windows} windows is 0 (a global shutter)"
               if start.line_delay_s == 0.0 else f"no estimate ({start.status}: "
               f"{start.reason})")  # fmt: skip
        return start, RefinedLineDelay("not refined", frames=len(frames),
                                       reason=f"{why}: nothing to refine")  # fmt: skip
    if on_start is not None:
        on_start(start)
    return start, refine_pass(K, D, float(start.line_delay_s), options, frames)


def warm_up() -> float:
    """Compile (first run after an install) or load from numba's cache every kernel the
    pipeline runs: the two-view estimator's, then the window backend's (tracking, window BA,
    landmarks), by running the window odometry over a small synthetic scene. Returns seconds.
    A live node calls it before subscribing, so that no frame waits for a compiler."""
    t0 = time.perf_counter()
    warm_up_two_view()
    rng = np.random.default_rng(0)
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    X = np.column_stack([rng.uniform(-4, 4, (150, 2)), rng.uniform(4, 12, 150)])
    ids = np.arange(len(X))
    odometry = WindowOdometry(K, 2e-5, WindowOptions(pairwise_bootstrap=False))
    for k in range(16):  # 0.1 m per frame to the side: the map starts, frames are tracked
        x = X - np.array([0.1 * k, 0.0, 0.0])
        xn = x[:, :2] / x[:, 2:]
        px = xn * 500.0 + K[:2, 2]
        odometry.track(int(k * 33_333_333), Observations(ids, xn, odometry.row_time(px[:, 1]),
                                                         px, px[:, 1]))  # fmt: skip
    return time.perf_counter() - t0
