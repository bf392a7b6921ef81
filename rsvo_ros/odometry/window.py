"""The window backend: keyframes, a local map and the rolling-shutter window bundle adjustment.

Two jobs (ORB-SLAM's split):

- tracking (:meth:`WindowOdometry.track`, every frame): the frame's pose and ``(w, v)`` from a
  motion-only RS optimisation against the map's points, each observation at its own row time,
  started from the constant-velocity prediction, with a Cauchy loss, a loose prior tying the
  velocities to the motion since the last frame and one tying the position to the prediction
  (a std of one predicted step); the keyframe decision (parallax after removing
  the rotation, the share of map points still tracked, a time limit);
- mapping (:meth:`WindowOdometry.map_keyframe`): the keyframe into the local map, new
  landmarks, the window BA, the new points for tracking. The node can run it on another thread
  (:class:`Mapper`); the replay runs it inline.

Initialisation and recovery use the paper's pair estimator: the first keyframe and the frame
where the parallax is large enough give the first two keyframes (scale: ``initial_scale`` for
their baseline); when too few map points are seen, the pair estimator between the last keyframe
and the frame, with the scale from the landmarks they share, poses the frame and makes it a
keyframe. Pure numpy + the compiled kernels, no ROS.
"""

from __future__ import annotations

import dataclasses
import threading
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from rsvo_ros.core.geometry import pose_at_row, rigid_correction, so3_exp, so3_log
from rsvo_ros.odometry import rs_projection
from rsvo_ros.odometry.frame import (
    FrameState,
    KeyFrame,
    Observations,
    extrapolate,
    interval_velocity,
)
from rsvo_ros.odometry.line_delay import MIN_SHEAR_FRAMES, map_rate_shear
from rsvo_ros.odometry.local_map import BAReport, Landmark, LocalMap, MapOptions, acc_prior_p2
from rsvo_ros.odometry.relocalize import LandmarkMemory, guided_matches, match_memory
from rsvo_ros.twoview import LMOptions, RansacOptions, estimate_relative_pose
from rsvo_ros.twoview.essential import rotation_only_residual_px
from rsvo_ros.twoview.state import Correspondences

FOCAL_REF_PX = 1000.0  # pixel thresholds below are given at this focal length and scale with it


# a new map after a loss starts at 1 / REINIT_PARALLAX_FACTOR of init_parallax_px, measured as
# translation parallax (the first map's parallax is not rotation-compensated: a walk's head bob
# reaches 80 px of it in about 20 frames, translation alone in 100 or more)
REINIT_PARALLAX_FACTOR = 2.0
SHEAR_FRAMES_KEPT = 900  # tracked frames kept for the map's shear (30 s at 30 Hz)
# tracked frames whose median speed scales a pair recovery in a turn on the spot
RECENT_SPEED_FRAMES = 5
REFOUND_REASON = "re-found the map"  # a frame's reason where descriptors found the map again
# a frame's reason where the last keyframe shared too few tracks for a pair and the frame was
# recovered from the last tracked frame, made a keyframe late
LATE_RECOVERY_REASON = "recovered with the pair estimator from the last tracked frame"
MAX_MAPPING_LAG_S = 2.0  # WindowOptions.mapping_lag_s: longer holds the map back for nothing
# the live node's mapping lag (its parameter mapping_lag_s; the in-process emulations of the
# node take it too): on 52 walks at 15 and 30 Hz 1.02x the inline replay's ATE in geometric
# mean, and the pick-up waited for the mapping thread at 2-3 keyframes of 300 frames (5-10 ms;
# README, "A fixed mapping lag")
NODE_MAPPING_LAG_S = 0.05
STALL_INTERVALS = 4.0  # WindowOptions.stall_intervals' default (the tracker's prediction's limit)


@dataclass
class WindowOptions:
    map: MapOptions = field(default_factory=MapOptions)
    # median image motion of the tracks since the reference frame (rotation included) to
    # initialise the first map: a long first baseline (on 6 vehicle sequences 30 px left 4 of
    # them 0.6-2.4 m off, 80 px one; on 5 walks 60-100 px alike). With the chain's rotation
    # removed, a severity-2 walk (seed 101) stayed under it for 48 frames instead of 35 and
    # its ATE went from 0.082 to 0.156 m (2026-11-26): the translation checks below gate it
    # (a map after a loss: the translation parallax alone, REINIT_PARALLAX_FACTOR)
    init_parallax_px: float = 80.0
    # ... and at least this much of it left by the best rotation (translation parallax): a
    # vehicle turning along its road reached 80 px mostly by turning in 2-3 frames, and the
    # map started from that short baseline was off by degrees per frame (10 of 20 vehicle
    # table sequences 0.9-2.5 m off with 0, 2 with 20; walks alike; README) (0: no check)
    init_translation_parallax_px: float = 20.0
    # ... and a pair whose rotation the images pin down: its standard deviation (the pair
    # estimator's covariance, velocities marginalised) at most this, until the translation
    # parallax is twice the above (then any pair). The two failing vehicle table sequences
    # started their maps from pairs of 1.6 and 3.3 deg and stayed off for 20 frames; good
    # starts had 0.1-0.6 deg (README) (0: no check)
    init_max_rotation_std_deg: float = 1.0
    # ... and, where the pairwise chain posed the frames meanwhile (the map's first start), a
    # pair whose rotation is within this of the chain's between the same two frames: people
    # walking in front of the camera let the pair estimator settle on a motion several
    # degrees off that its own covariance does not flag (README, "People walking in front of
    # the camera"; the RS model with a line delay only) (0: no check)
    init_max_chain_rotation_deg: float = 3.0
    keyframe_parallax_px: float = 25.0  # ... since the last keyframe that makes a keyframe
    keyframe_track_ratio: float = 0.7  # map points tracked vs at the last keyframe
    keyframe_max_interval_s: float = 0.4
    min_landmarks: int = 20  # map points seen to track against the map
    min_inliers: int = 15
    # a tracking result with fewer inliers than this share of the map points it saw is not
    # taken (the pair estimator recovers the frame): in a fast turn a pose that explains a
    # quarter of its points had diverged and, made a keyframe, emptied the map
    min_inlier_ratio: float = 0.5
    track_robust_px: float = 1.5  # Cauchy scale of tracking
    track_inlier_px: float = 3.0
    # > 0: the inlier threshold is at least this many times the image noise the last tracked
    # frames showed (their median reprojection error as a Gaussian's sigma): for blurred
    # video, whose tracks are noisier than track_inlier_px. Off by default: on blurred
    # synthetic walks mixed (README, "Motion blur and sensor noise"), on sharp ones no change
    track_inlier_sigmas: float = 0.0
    track_iterations: int = 10
    # tracking's velocity prior, centred on the motion over the last interval
    prior_w_rad_s: float = 0.3
    prior_v_rel: float = 0.3
    prior_v_floor: float = 0.05
    # ... and on its position, centred on the constant-velocity prediction with a std of this
    # many times the predicted step (0: none). One frame's points fix its position along the
    # view poorly: without it, tracked frames of strong-shake walks jumped 10-40 cm back and
    # forth around a 3 cm step (docs/notebook.md, "Tracking's position prior")
    prior_p_step: float = 1.0
    lost_frames_to_reset: int = 5  # held frames in a row before the map starts over
    # A stall: more than this many of the last frame intervals without a frame (a camera or
    # a node that stalled; 0: no such check). A car's image moves past KLT's reach in it, and
    # on a repeated pattern the tracks lock onto a copy: consistent, wrong by its period (a
    # 0.3-0.55 s stall in a synthetic car: a step 40-55 % short, 25-50 deg off, the whole
    # trajectory's ATE 4-20x worse). After a stall a pose tracked against the map more than
    # reloc_max_rotation_deg off the constant-velocity prediction with fewer than
    # stall_min_inlier_share of the usual inliers is not taken (the aliased ones had 0.25-0.36,
    # walks' true ones 0.56-1.0), nor a pair recovery (its tracks cross the stall) more than
    # reloc_max_rotation_deg off it; without either the map starts over at once at the
    # prediction, with the speed from before, and re-finds the lost map only within
    # reloc_max_jump_steps usual steps of where it starts (README, "A stalled camera")
    stall_intervals: float = STALL_INTERVALS
    stall_min_inlier_share: float = 0.5
    # ... and a stall of at most this long (s): over a longer one the constant-velocity
    # prediction says little (1-3 s: walks 1.9x worse from it, cars 0.56x), and the frame is
    # recovered as any other
    stall_max_s: float = 1.0
    pair_prior_rotation_rad: float = 0.02  # the pair estimator's rotation prior (see __init__)
    pair_model: str = "rs"  # RS model: how pairs start the map ("rs" or "gs_cv", see _pair)
    # while the map initialises, pose the frames with the pairwise chain and start the map in
    # its world and scale (False: hold them at the first frame's pose)
    pairwise_bootstrap: bool = True
    min_shared_for_scale: int = 8
    # a pair recovery whose scale moves the camera more than this many usual steps (the median
    # speed of the last tracked frames times the time since the keyframe) is not believed: the
    # last speed scales it (the shared landmarks' depths from a pair of a walker who stopped,
    # a few millimetres apart, gave 31 usual steps; a walker setting off after a look-around
    # took a right 4.9, which 3 rejected)
    recovery_max_steps: float = 10.0
    # ... and one with less translation parallax than this (px at 1000 px focal; 3 is the
    # chain's rotation_only_parallax_px) is a turn on the spot: the depths it shares with the
    # map do not fix its scale, and its step is the median speed of the last
    # RECENT_SPEED_FRAMES tracked frames (a walker who stopped to look around, 15 Hz: the
    # depths gave 5x the true step). 0: off. Alone it made async 15 Hz walks 1.2x worse (one
    # 7x: the frames after it no longer re-found the map); with reloc_frames_after_recovery
    # 15 Hz walks come out 0.80x inline, 0.94x async, 30 Hz walk tables 0.93x (README, "The
    # frames after a pair recovery re-find the map")
    recovery_turn_parallax_px: float = 3.0
    # mapping (keyframe insertion and the window BA) on a background thread: tracking goes on
    # against the map it has and picks up the refined map at its next frame; while mapping is
    # busy no new keyframe is made (ORB-SLAM's rule). False: inline (deterministic; the replay)
    async_mapping: bool = False
    # > 0: a keyframe's window BA is picked up at the first frame stamped at least this many
    # seconds after the keyframe (at the start of that frame, waiting for the mapper if it has
    # not finished), so the map tracking sees, and every result, does not depend on how fast
    # the machine is: a live node that processes every frame gives what the replay with the
    # same setting gives. With async_mapping False the BA runs inline when the keyframe is made
    # and is picked up as late (the replay's way to reproduce the node). 0: async mapping is
    # picked up at the first frame after it finishes (timing-dependent), inline mapping at once
    mapping_lag_s: float = 0.0
    # async mapping goes synchronous (waits for the mapper, maps keyframes inline) while
    # tracking is weak: inliers below this share of the median of the last frames (a fast turn
    # leaving the map; tracking against a map one keyframe behind lost it there)
    sync_below_inlier_share: float = 0.5
    # refined keyframe states kept for the keyframe path (None: all, as the replay's
    # keyframes.tum needs; a live node keeps its path length, so memory stays flat)
    keyframe_log_max: int | None = None
    # each window BA's keyframe turn-rate priors centred on the keyframes' own rates minus the
    # map's shear (line_delay.map_rate_shear over the tracked frames of the window's span)
    # instead of on the neighbours' central difference: the window's common turn rate, which
    # the images do not fix, held to the turns between the frames. For refining a line delay
    # (PipelineOptions.line_delay_refine); off otherwise (ATE unchanged, and with the line
    # delay still unknown it pulls the estimate to the one the odometry runs with)
    shear_from_turns: bool = False
    # Re-finding the map (odometry/relocalize.py): the landmarks the window placed are
    # remembered (world point, ORB descriptor; the newest reloc_memory); a frame that cannot
    # be tracked, and the keyframes of a map rebuilt after a loss for reloc_window_s, match
    # their tracks against that memory, and with at least reloc_min_inliers inliers of a PnP
    # (reloc_ransac_px at 1000 px focal) the map starts over from that frame in the old map's
    # world and scale (0: off). A pose more than reloc_max_rotation_deg off the predicted
    # rotation is not taken (a false match; a frame's rotation is known well even where its
    # scale is not)
    reloc_min_inliers: int = 30
    reloc_window_s: float = 3.0
    reloc_memory: int = 5000
    reloc_ratio: float = 0.8
    reloc_max_hamming: int = 64
    reloc_ransac_px: float = 4.0
    reloc_max_rotation_deg: float = 15.0
    reloc_guided_px: float = 8.0  # then every remembered point projected this near a track
    # ... and, re-finding the map it is in (not one rebuilt after a loss), a position within
    # this many of the usual steps of the prediction
    reloc_max_jump_steps: float = 3.0
    # after a pair recovery, this many frames (tracked in the recovered map, within
    # reloc_window_s) each try to re-find the remembered map, not only the keyframes (a pair
    # recovery in a turn on the spot can take a wrong scale, and the remembered landmarks may
    # be in view only for the next few frames: a 15 Hz walk's turn, 1.24 -> 0.13 m). 0:
    # keyframes only
    reloc_frames_after_recovery: int = 5


def check_stall(intervals: float, min_inlier_share: float = 0.5, max_s: float = 1.0,
                name: str = "WindowOptions.stall_intervals") -> None:
    """``ValueError`` unless ``intervals`` is a :attr:`WindowOptions.stall_intervals` (0: off,
    else more than one frame interval, finite), ``min_inlier_share`` in [0, 1] and ``max_s``
    (``stall_max_s``) positive and finite; the message names the setting ``name``."""
    if not (intervals == 0 or 1 < intervals < np.inf):  # also NaN
        raise ValueError(f"{name} must be 0 (off) or more than 1 frame interval, got "
                         f"{intervals}")
    if not 0 <= min_inlier_share <= 1:
        raise ValueError(f"WindowOptions.stall_min_inlier_share must be in [0, 1], got "
                         f"{min_inlier_share}")
    if not 0 < max_s < np.inf:
        raise ValueError(f"WindowOptions.stall_max_s must be > 0 s and finite, got {max_s}")


def _turn_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """The rotation (deg) from ``R_a`` to ``R_b``."""
    return float(np.degrees(np.linalg.norm(so3_log(R_a.T @ R_b))))


@dataclass
class PairMotion:
    """A pair estimate as the window uses it: the motion of the reference-row cameras
    (``X_b = R X_a + t``, ``|t| = 1``), each frame's ``(w, v)`` (``v`` in units of ``t`` per
    second), and per shared correspondence the inliers and depths in the first frame."""

    R: np.ndarray
    t: np.ndarray
    vel_prev: tuple[np.ndarray, np.ndarray]
    vel_curr: tuple[np.ndarray, np.ndarray]
    inliers: np.ndarray
    depths_prev: np.ndarray
    num_inliers: int
    rotation_std_deg: float = 0.0  # of the pair's rotation (its covariance); inf: unconstrained


@dataclass
class WindowResult:
    status: str  # "first", "posed", "held"
    reason: str
    state: FrameState | None
    inliers: int = 0
    # what ``inliers`` is out of: the map points seen (tracking, re-finding), or the tracks a
    # pair estimate shared with its keyframe (the map's initialisation, a pair recovery)
    tracked: int = 0
    keyframe: bool = False
    hessian: np.ndarray | None = None  # (15, 15) of tracking, px^-2 units
    sigma2: float = 1.0  # residual variance of tracking (px^2)
    ba: BAReport | None = None
    # ``ba`` ran on the mapping thread (async mapping) and was picked up at this frame: its time
    # was not spent in this frame's tracking; False: inline, in this frame (or no BA)
    ba_background: bool = False
    # a window BA moved a frame (this one inline, or a keyframe whose mapping finished since
    # the last frame): its state (before, after); the pipeline keeps its published odometry
    # continuous across that correction
    ba_moved: list[tuple[FrameState, FrameState]] = field(default_factory=list)
    # the frame was posed against the memory of landmarks: its state is in the world of the
    # maps that wrote them (:meth:`WindowOdometry.in_trusted_map`), not the current map's
    refound: bool = False
    stall_restart: bool = False  # a new map started at the prediction after a stall
    # track ids of the map points this frame was posed with, and of those it rejected (for
    # drawing; None when the frame was not posed against the map)
    inlier_ids: np.ndarray | None = None
    outlier_ids: np.ndarray | None = None


class WindowOdometry:
    """Feed :class:`Observations` of each frame to :meth:`track`."""

    def __init__(self, K: np.ndarray, line_delay: float, options: WindowOptions | None = None,
                 model: str = "rs", ransac: RansacOptions | None = None,
                 lm: LMOptions | None = None, initial_scale: float = 1.0,
                 motion_prior: bool = True, seed: int = 0):  # fmt: skip
        self.K = np.asarray(K, float)
        self.focal = 0.5 * (self.K[0, 0] + self.K[1, 1])
        self.row_ref = float(self.K[1, 2])
        self.line_delay = float(line_delay)
        self.options = options or WindowOptions()
        o = self.options
        check_stall(o.stall_intervals, o.stall_min_inlier_share, o.stall_max_s)
        if not self.options.prior_p_step >= 0:  # also NaN
            raise ValueError(f"WindowOptions.prior_p_step must be >= 0 (0: no position prior), "
                             f"got {self.options.prior_p_step}")
        self.model = model
        self.ransac = ransac or RansacOptions()
        # the pair estimator starts and recovers the map: its velocities seed every keyframe's,
        # so their common part (not observed from two views under smooth motion) is held near
        # the motion between the two frames (a departure of this many rad over half the
        # readout) instead of the loose default; the window BA refines them
        self.lm = dataclasses.replace(lm or LMOptions(),
                                      motion_prior_rotation_rad=self.options.pair_prior_rotation_rad)
        self.initial_scale = initial_scale
        self.motion_prior = motion_prior
        self.seed = seed
        self.calibrator = None  # a LineDelayCalibrator: the BA problems feed it (line_delay auto)
        self.reset()

    def reset(self) -> None:
        self.map = self._new_map()
        self._points = (np.zeros(0, np.int64), np.zeros((0, 3)))  # what tracking matches
        self._next_kf = 0
        self._last: FrameState | None = None
        self._before: FrameState | None = None
        self._ref: KeyFrame | None = None  # the first keyframe while initialising
        self._origin: FrameState | None = None  # where the trajectory restarts after a loss
        self._lost = 0
        self._tracked_at_kf = 0
        # speeds of the last tracked frames: a new map after a loss keeps the trajectory's
        # scale through the speed, and the last frames before a loss may be off
        self._speeds: deque = deque(maxlen=30)
        self._inliers: deque = deque(maxlen=30)  # inliers of the last tracked frames
        self._seen: deque = deque(maxlen=16)  # the stamps of the last frames, any status
        self._stalled_map = False  # the map was started after a stall (until it re-finds)
        self._stall: float | None = None  # this frame came after a stall of this many s
        self._err_medians: deque = deque(maxlen=15)  # their median reprojection errors (px)
        self._err_median = np.nan  # the last motion-only refinement's
        self._weak = False  # the last frame's tracking was weak (async: map synchronously)
        # the last frame tracked against the map, if it did not become a keyframe: (its stamp,
        # observations, outlier track ids; valid while it is ``_last``); a pair recovery whose
        # keyframe shares too few tracks with the lost frame makes it a keyframe late
        self._last_tracked: tuple[int, Observations, np.ndarray] | None = None
        # BA corrections reported with frames that were not posed (the pipeline moves the
        # published odometry at posed frames only): handed on with the next posed frame
        self._moved_unposted: list[tuple[FrameState, FrameState]] = []
        self._hints: dict[int, np.ndarray] = {}  # stamp -> the chain's row-0 pose
        # while a new map initialises after a loss: the last two frames' (stamp, chain pose in
        # the memory's world), the prediction for re-finding the lost map
        self._hints_in_memory: deque = deque(maxlen=2)
        # the last tracked frames' (stamp, R, w): the map's shear (shear_from_turns)
        self._rates: deque = deque(maxlen=SHEAR_FRAMES_KEPT)
        if getattr(self, "_mapper", None) is not None:
            self._mapper.close()
        lag = self.options.mapping_lag_s
        if not (isinstance(lag, int | float | np.number) and 0 <= lag <= MAX_MAPPING_LAG_S):
            raise ValueError(f"WindowOptions.mapping_lag_s must be a number of seconds in "
                             f"[0, {MAX_MAPPING_LAG_S:g}], got {lag!r}")
        self._mapper: Mapper | DeferredMapper | None = (
            Mapper(self) if self.options.async_mapping
            else DeferredMapper(self) if lag > 0 else None)
        self._pending_kf: KeyFrame | None = None  # submitted to the mapper, not yet picked up
        # the frame tracked just after the pending keyframe: its ``after`` once picked up (the
        # BA of the keyframe must not see it, as inline mapping's does not)
        self._pending_after: FrameState | None = None
        self._picked: list[tuple[tuple[FrameState, FrameState], BAReport]] = []
        self._lock = threading.Lock()  # one mapping at a time; tracking reads atomic snapshots
        self.keyframe_log: dict[int, FrameState] = {}  # stamp -> refined keyframe state
        self.memory = LandmarkMemory(self.options.reloc_memory)  # landmarks to re-find
        # a map rebuilt after a loss is provisional until this stamp: its keyframes try to
        # re-find the old map, and it does not write into the memory
        self._provisional_until: int | None = None
        self._refind_frames = 0  # frames left to try re-finding after a pair recovery

    # ------------------------------------------------------------------ helpers

    @property
    def _px(self) -> float:
        """Pixels at this focal length per reference pixel."""
        return self.focal / FOCAL_REF_PX

    def row_time(self, rows: np.ndarray) -> np.ndarray:
        return (np.asarray(rows, float) - self.row_ref) * self.line_delay

    def row0_time(self) -> float:
        """Row time (s) of row 0 from the reference row (negative)."""
        return -self.row_ref * self.line_delay

    def _new_keyframe(self, state: FrameState, obs: Observations,
                      prior: tuple[np.ndarray, np.ndarray] | None) -> KeyFrame:  # fmt: skip
        kf = KeyFrame(self._next_kf, state.copy(), obs, prior)
        self._next_kf += 1
        if self.options.reloc_min_inliers > 0 and obs.describe is not None:
            kf.descriptors = obs.describe()
        return kf

    def _pair(self, a: Observations, b: Observations, dt: float,
              seed: int) -> tuple[PairMotion | None, np.ndarray, np.ndarray]:  # fmt: skip
        """The pair estimator between two observation sets (their shared ids) as the motion of
        the reference-row cameras; None if unusable. ``pair_model="rs"`` (default): the RS
        estimator in stream mode; ``"gs_cv"``: OpenCV's USAC_MAGSAC pose, unbiased where both
        frames carry nearly the same distortion, with the constant velocity of that motion
        (measured: walks alike, vehicle sequences worse)."""
        _, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
        if len(ia) < max(20, self.options.min_inliers):
            return None, ia, ib
        gs_cv = self.model == "rs" and self.options.pair_model == "gs_cv"
        model = "gs" if gs_cv else self.model
        try:
            res = estimate_relative_pose(
                a.px[ia], b.px[ib], self.K, self.line_delay if model == "rs" else 0.0,
                model=model, seed=seed, ransac=self.ransac, lm=self.lm, rows_prev=a.rows[ia],
                rows_curr=b.rows[ib],
                frame_interval=dt if (self.motion_prior and model == "rs") else None)
        except ValueError:
            return None, ia, ib
        if not res.ok:
            return None, ia, ib
        if model == "rs":
            R_m, t_m, (w_p, v_p, w_c, v_c) = pose_at_row(res.R, res.t, res.w_prev, res.v_prev,
                                                         res.w_curr, res.v_curr, self.row_ref,
                                                         self.line_delay)  # fmt: skip
        else:
            R_m, t_m = res.R, res.t
            w_p = w_c = so3_log(R_m.T) / dt if gs_cv else np.zeros(3)
            v_c = -t_m / dt if gs_cv else np.zeros(3)
            v_p = R_m.T @ v_c
        rot_var = float(np.trace(res.covariance[:3, :3]))
        rot_std = float(np.degrees(np.sqrt(rot_var))) if np.isfinite(rot_var) else np.inf
        return PairMotion(R_m, t_m, (w_p, v_p), (w_c, v_c), res.inliers, res.depths_prev,
                          res.num_inliers, rot_std), ia, ib

    def _states_from_pair(self, motion: PairMotion, first: FrameState, stamp_ns: int,
                          scale: float) -> tuple[FrameState, tuple, tuple]:  # fmt: skip
        """The second camera of a pair motion (and both frames' velocities, scaled), given
        the first frame's state at the reference row."""
        R_m, t_m = motion.R, motion.t
        (w_p, v_p), (w_c, v_c) = motion.vel_prev, motion.vel_curr
        R_w2 = first.R @ R_m.T
        p_w2 = first.p - first.R @ (R_m.T @ t_m) * scale
        return (FrameState(stamp_ns, R_w2, p_w2, w_c.copy(), v_c * scale),
                (w_p.copy(), v_p * scale), (w_c.copy(), v_c * scale))

    def _parallax_px(self, kf: KeyFrame, obs: Observations, R_world_cam: np.ndarray) -> float:
        """Median image motion of shared tracks since ``kf`` after removing the rotation."""
        _, ia, ib = np.intersect1d(kf.obs.ids, obs.ids, return_indices=True)
        if not len(ia):
            return 0.0
        R_rel = R_world_cam.T @ kf.state.R  # kf camera -> current camera
        b = np.column_stack([kf.obs.x[ia], np.ones(len(ia))]) @ R_rel.T
        with np.errstate(divide="ignore", invalid="ignore"):
            d = np.linalg.norm(b[:, :2] / b[:, 2:] - obs.x[ib], axis=1)
        d = d[np.isfinite(d)]
        return float(np.median(d)) * self.focal if len(d) else 0.0

    def _translation_parallax_px(self, kf: KeyFrame, obs: Observations) -> float:
        """Median image motion of shared tracks since ``kf`` left by the rotation that best
        explains them (the pair estimator's measure of translation parallax)."""
        _, ia, ib = np.intersect1d(kf.obs.ids, obs.ids, return_indices=True)
        if len(ia) < 8:
            return 0.0
        ones, zeros = np.ones((len(ia), 1)), np.zeros(len(ia))
        corr = Correspondences(np.hstack([kf.obs.x[ia], ones]), np.hstack([obs.x[ib], ones]),
                               zeros, zeros, self.focal)  # fmt: skip
        return rotation_only_residual_px(corr, np.random.default_rng(self.seed))[0]

    # ------------------------------------------------------------------ tracking

    @property
    def initialising(self) -> bool:
        """No map yet (the first frames, or after the map was lost)."""
        return self._last is None

    def in_trusted_map(self, stamp_ns: int) -> bool:
        """Whether a frame at ``stamp_ns`` is posed in a map that writes into the memory of
        landmarks (not one rebuilt after a loss, while it is provisional): the world a
        re-found frame is posed in."""
        return not self.initialising and not self._provisional(stamp_ns)

    def track(self, stamp_ns: int, obs: Observations, hint: np.ndarray | None = None,
              memory_from_hint: np.ndarray | None = None) -> WindowResult:  # fmt: skip
        """One frame. ``hint``: while initialising, the frame's row-0 ``T_world_camera`` from
        another estimate (the pairwise chain): the map starts in its world and scale.
        ``memory_from_hint``: the hint's world in the memory's (the lost map's, 4x4), if
        known: after a loss each frame until the new map's first pose tries to re-find the
        lost map there."""
        if self.initialising and hint is not None:
            self._hints[stamp_ns] = hint
            if memory_from_hint is not None:
                T = memory_from_hint @ hint
                if np.isfinite(T).all():
                    self._hints_in_memory.append((stamp_ns, T))
        self._stall = self._stall_s(stamp_ns)
        self._seen.append(stamp_ns)
        if self._last is None and self._ref is None:
            return self._start(stamp_ns, obs)
        if self._ref is not None:
            return self._initialise(stamp_ns, obs)
        self._picked = []
        if self._weak and self._mapper is not None:
            self._mapper.wait_idle()  # track against the newest map (and map inline if weak)
        self._pick_up_mapping(force=self._weak, stamp_ns=stamp_ns)
        result = self._track_map(stamp_ns, obs)
        if result is None:
            result = self._recover(stamp_ns, obs)
        # the refined map from the background came first, then anything inline
        result.ba_moved = [moved for moved, _ in self._picked] + result.ba_moved
        if result.status == "posed":
            result.ba_moved = self._moved_unposted + result.ba_moved
            self._moved_unposted = []
        elif self.initialising:  # a new map starts: the old map's corrections do not apply
            self._moved_unposted = []
        else:
            self._moved_unposted += result.ba_moved
        if result.ba is None and self._picked:
            result.ba, result.ba_background = self._picked[-1][1], True
        if result.status == "posed" and result.state is not None:
            if self.calibrator is not None:
                self.calibrator.add_pose(result.state)
            if self.options.shear_from_turns:
                if self._rates and stamp_ns <= self._rates[-1][0]:
                    self._rates.clear()  # time went back: a new trajectory
                self._rates.append((stamp_ns, result.state.R.copy(), result.state.w.copy()))
        return result

    def _newest_keyframe(self) -> KeyFrame | None:
        """The keyframe the next keyframe decision compares with: the one being mapped in the
        background, else the map's newest."""
        if self._pending_kf is not None:
            return self._pending_kf
        return self.map.keyframes[-1] if self.map.keyframes else None

    def _pick_up_mapping(self, force: bool = True, stamp_ns: int | None = None) -> None:
        """Async mapping: a keyframe whose window BA finished since the last frame (with
        ``mapping_lag_s``, at the first frame ``stamp_ns`` that long after the keyframe,
        waiting for it; ``force``: now, the caller has waited for the mapper). The frames
        tracked meanwhile (in the map as it was) move with the keyframe's correction, so the
        next prediction is in the refined map."""
        if self._mapper is None:
            return
        lag = self.options.mapping_lag_s
        if lag > 0 and self._pending_kf is not None:
            kf_stamp = self._pending_kf.state.stamp_ns
            if not force and stamp_ns is not None and stamp_ns > kf_stamp \
                    and stamp_ns - kf_stamp < round(lag * 1e9):  # fmt: skip
                return
            self._mapper.wait_idle()
        try:
            done = self._mapper.finished()
        except MappingError:
            self._pending_kf = self._pending_after = None  # that keyframe is not mapped
            raise
        if done is None:
            return
        kf, before, report, self._points = done
        self._pending_kf = None
        after = kf.state.copy() if kf in self.map.keyframes else before.copy()
        # world-frame correction of the map around the keyframe (row 0, as the pipeline's)
        D = rigid_correction(self.row0_pose(before), self.row0_pose(after))
        follow = self._pending_after
        self._pending_after = None
        for st in (self._last, self._before, follow):
            if st is not None and np.isfinite(D).all():  # never a NaN pose
                st.R, st.p = D[:3, :3] @ st.R, D[:3, :3] @ st.p + D[:3, 3]
        if follow is not None and kf.after is None:
            kf.after = follow  # for the next window BA, in the refined map as inline
        if self._last is not None and self._last.stamp_ns == after.stamp_ns:
            # the keyframe is still the last tracked frame: the next frame starts from its
            # refined state, turn rate and velocity too, as after inline mapping (with the
            # velocities tracking gave it, async walks at 15 Hz came out 3-5x worse)
            self._last = after.copy()
        self._picked.append(((before, after), report))

    def _start(self, stamp_ns: int, obs: Observations) -> WindowResult:
        origin = self._origin or FrameState(stamp_ns, np.eye(3), np.zeros(3))
        state = origin.copy()
        state.stamp_ns = stamp_ns
        self._ref = self._new_keyframe(state, obs, None)
        first = self._origin is None
        return WindowResult("first" if first else "held",
                            "first frame: trajectory origin" if first else
                            "map lost: starting a new one here", state)  # fmt: skip

    def _initialise(self, stamp_ns: int, obs: Observations) -> WindowResult:
        if self._origin is not None and self._provisional(stamp_ns):
            found = self._refind_while_initialising(stamp_ns, obs)
            if found is not None:
                return found
        ref = self._ref
        shared = len(np.intersect1d(ref.obs.ids, obs.ids))
        if shared < 2 * self.options.min_inliers:
            # the reference's tracks are gone (a turn): this frame is the new reference
            state = ref.state.copy()
            state.stamp_ns = stamp_ns
            self._ref = self._new_keyframe(state, obs, None)
            return WindowResult("held", f"initialising: new reference frame ({shared} tracks "
                                        "left of the last one)", state)  # fmt: skip
        if self._origin is None:
            par = self._parallax_px(ref, obs, ref.state.R)
        else:
            # a new map after a loss, often in a fast turn: the parallax of translation only
            # (a turn alone reached 80 px in two frames, and the map started from a rotation)
            par = self._translation_parallax_px(ref, obs) * REINIT_PARALLAX_FACTOR
        if par < self.options.init_parallax_px * self._px:
            return WindowResult("held", f"initialising: parallax {par:.1f} px", ref.state)
        need = self.options.init_translation_parallax_px * self._px
        par_t = np.inf
        if self._origin is None and need > 0:
            par_t = self._translation_parallax_px(ref, obs)
            if par_t < need:
                return WindowResult("held", f"initialising: translation parallax {par_t:.1f} "
                                            f"px", ref.state)  # fmt: skip
        dt = (stamp_ns - ref.state.stamp_ns) * 1e-9
        res, ia, ib = self._pair(ref.obs, obs, dt, self.seed + self._next_kf)
        if res is None:
            return WindowResult("held", "initialising: no pose from the pair", ref.state)
        max_std = self.options.init_max_rotation_std_deg
        if self._origin is None and res.rotation_std_deg > max_std > 0 and par_t < 2 * need:
            why = f"the pair's rotation is uncertain ({res.rotation_std_deg:.1f} deg std)"
            return WindowResult("held", f"initialising: {why}", ref.state)
        h_ref, h_cur = self._hints.get(ref.state.stamp_ns), self._hints.get(stamp_ns)
        hinted = h_ref is not None and h_cur is not None
        max_off = self.options.init_max_chain_rotation_deg
        # (the RS model with a line delay only: a GS pair and a GS chain of a rolling-shutter
        # camera disagree by its distortion itself; held there, the GS vehicles' first map
        # waited for seconds, and so did the RS model's with a line delay of 0)
        if self.model == "rs" and self.line_delay > 0 and self._origin is None and hinted \
                and max_off > 0:  # fmt: skip
            # the chain's rotation between the two frames' reference-row cameras (its row-0
            # poses turned by the pair's rates), X_cur = R X_ref, as the pair's
            s0 = self.row0_time()
            R_a = h_ref[:3, :3] @ so3_exp(-s0 * res.vel_prev[0])
            R_b = h_cur[:3, :3] @ so3_exp(-s0 * res.vel_curr[0])
            R_chain = R_b.T @ R_a
            off = float(np.degrees(np.linalg.norm(so3_log(R_chain.T @ res.R))))
            if off > max_off:
                return WindowResult("held", f"initialising: the pair's rotation is {off:.1f} deg "
                                            "from the chain's", ref.state)  # fmt: skip
        scale = self.initial_scale
        if self._origin is not None and np.linalg.norm(self._origin.v) > 0:
            scale = float(np.linalg.norm(self._origin.v)) * dt  # keep the speed across a loss
        if hinted:
            baseline = float(np.linalg.norm(h_cur[:3, 3] - h_ref[:3, 3]))
            if baseline > 0:
                scale = baseline
            # the reference keyframe where the chain puts its row 0, at its reference row
            w_p, v_p = res.vel_prev[0], res.vel_prev[1] * scale
            s0 = self.row0_time()
            R_ref = h_ref[:3, :3] @ so3_exp(-s0 * w_p)
            ref.state = FrameState(ref.state.stamp_ns, R_ref, h_ref[:3, 3] - R_ref @ (s0 * v_p))
        state, vel_ref, vel_cur = self._states_from_pair(res, ref.state, stamp_ns, scale)
        ref.state.w, ref.state.v = vel_ref
        ref.velocity_prior = vel_ref
        kf = self._new_keyframe(state, obs, vel_cur)
        before = state.copy()
        if self._mapper is not None:
            self._mapper.wait_idle()
        with self._lock:
            self.map.add_keyframe(ref)
            self.map.add_keyframe(kf)
        report = self.map_keyframe(None, optimize_only=True)
        if len(self.map.landmarks) < self.options.min_inliers:
            self.map = self._new_map()
            self._ref = self._new_keyframe(state, obs, None)
            return WindowResult("held", "initialising: too few landmarks", state)
        if self._origin is None and not hinted:
            self._rebase_to_row0_of(ref)
        self._ref = None
        self._origin = None
        self._hints.clear()
        self._before, self._last = ref.state.copy(), kf.state.copy()
        self._tracked_at_kf = len(self.map.landmarks)
        # (rebased: the world itself moved, and nothing was published in it yet)
        moved = [(before, kf.state.copy())] if hinted else []
        paired = obs.ids[ib]
        mapped = np.isin(paired, np.fromiter(self.map.landmarks, int, len(self.map.landmarks)))
        return WindowResult("posed", "initialised the map", self._last.copy(),
                            inliers=res.num_inliers, tracked=len(ia),
                            keyframe=True, ba=report, ba_moved=moved,
                            inlier_ids=paired[mapped], outlier_ids=paired[~mapped])  # fmt: skip

    def _refind_while_initialising(self, stamp_ns: int,
                                   obs: Observations) -> WindowResult | None:  # fmt: skip
        """A map started over after a loss: the frame re-finds the lost map in the memory
        (:meth:`_relocalize`), predicted by the pairwise chain's pose in the memory's world.
        A rebuilt map's keyframes try this too, but a new map can wait for its translation
        parallax for seconds (28 frames of a 15 Hz walk's turn on the spot), and by then the
        lost map's landmarks were out of view. None without a prediction or a match."""
        if not self._hints_in_memory or self._hints_in_memory[-1][0] != stamp_ns:
            return None
        T = self._hints_in_memory[-1][1]
        predicted = FrameState(stamp_ns, T[:3, :3].copy(), T[:3, 3].copy(),
                               self._origin.w.copy())  # fmt: skip
        if len(self._hints_in_memory) == 2:
            stamp_prev, T_prev = self._hints_in_memory[0]
            if stamp_prev < stamp_ns:
                prev = FrameState(stamp_prev, T_prev[:3, :3], T_prev[:3, 3])
                predicted.w, predicted.v = interval_velocity(prev, predicted)
        return self._relocalize(stamp_ns, obs, predicted)

    def _rebase_to_row0_of(self, kf: KeyFrame) -> None:
        """Move the world so that the first keyframe's row-0 camera is the origin."""
        T0 = kf.state.pose(self.row0_time())
        R0, p0 = T0[:3, :3], T0[:3, 3]
        for k in self.map.keyframes:
            k.state.p = R0.T @ (k.state.p - p0)
            k.state.R = R0.T @ k.state.R
        self._points = self.map.points()

    def _track_map(self, stamp_ns: int, obs: Observations) -> WindowResult | None:
        o = self.options
        ids, X = self._points  # replaced whole: by inline mapping, or at pick-up
        last_kf = self._newest_keyframe()
        _, ia, ib = np.intersect1d(ids, obs.ids, return_indices=True)
        if len(ia) < o.min_landmarks or last_kf is None:
            return None
        pred = extrapolate(self._last, self._before, stamp_ns)
        w_cv, v_cv = interval_velocity(self._last, pred)
        if not np.isfinite(w_cv).all():
            w_cv, v_cv = self._last.w, self._last.v
        sv = max(o.prior_v_rel * float(np.linalg.norm(v_cv)), o.prior_v_floor)
        # the position's prior: the constant-velocity prediction, with a std of
        # prior_p_step x its step (scale-free; no step, no prior)
        step = float(np.linalg.norm(pred.p - self._last.p))
        sp = o.prior_p_step * step
        pp2 = 1.0 / sp**2 if sp > 0 and np.isfinite(sp) else 0.0
        state, inl, H, sigma2 = self._motion_only(
            stamp_ns, pred.R, pred.p, self._last.w, self._last.v, X[ia], obs.x[ib], obs.s[ib],
            np.concatenate([w_cv, v_cv, pred.p]), sv, pp2)  # fmt: skip
        if state is None or inl.sum() < max(o.min_inliers, o.min_inlier_ratio * len(ia)):
            return None
        if self._stall is not None and self._aliased(pred, state, int(inl.sum())):
            return None
        result = WindowResult("posed", "", state, inliers=int(inl.sum()), tracked=len(ia),
                              hessian=H, sigma2=sigma2, inlier_ids=obs.ids[ib][inl],
                              outlier_ids=obs.ids[ib][~inl])  # fmt: skip
        if last_kf.after is None and last_kf.state.stamp_ns < stamp_ns:
            if last_kf is not self._pending_kf:
                last_kf.after = state.copy()  # read by the next window BA
            elif self._pending_after is None:  # its BA is running: set at the pick-up
                self._pending_after = state.copy()
        inliers = int(inl.sum())
        if np.isfinite(self._err_median):
            self._err_medians.append(self._err_median)
        self._weak = bool(self._inliers) and \
            inliers < o.sync_below_inlier_share * float(np.median(self._inliers))
        self._inliers.append(inliers)
        mapping_busy = self._mapper is not None and self._mapper.busy
        tried = self._refind_frames > 0 and self._provisional(stamp_ns)
        if tried:  # one of the frames after a pair recovery
            self._refind_frames -= 1
            found = self._relocalize(stamp_ns, obs, state, exclude=ids)
            if found is not None:
                return found
        if not mapping_busy and self._needs_keyframe(last_kf, obs, state, inliers):
            if self._provisional(stamp_ns) and not tried:
                found = self._relocalize(stamp_ns, obs, state, exclude=ids)
                if found is not None:
                    return found
            kf = self._new_keyframe(state, obs, (state.w.copy(), state.v.copy()))
            kf.before = self._last.copy()
            kf.rejected.update(int(t) for t in obs.ids[ib][~inl])
            result.keyframe = True
            self._tracked_at_kf = inliers
            if self._mapper is not None and not self._weak:
                self._mapper.submit(kf, state.copy())  # (DeferredMapper: the BA runs here)
                self._pending_kf = kf  # once submitted: a BA that raised leaves none pending
            else:
                before = state.copy()
                result.ba = self.map_keyframe(kf)
                refined = kf.state if kf in self.map.keyframes else state
                state = refined.copy()
                result.state = state.copy()
                result.ba_moved = [(before, state.copy())]
        self._lost = 0
        self._speeds.append(float(np.linalg.norm(state.v)))
        self._last_tracked = None if result.keyframe else (stamp_ns, obs, obs.ids[ib][~inl])
        self._before, self._last = self._last, state.copy()
        return result

    def _motion_only(self, stamp_ns: int, R0: np.ndarray, p0: np.ndarray, w0: np.ndarray,
                     v0: np.ndarray, X: np.ndarray, x: np.ndarray, s: np.ndarray,
                     prior_mean: np.ndarray, v_std: float, p_inv_var: float):  # fmt: skip
        """Tracking's motion-only RS refinement of a frame against world points ``X`` seen at
        ``x`` (row times ``s``), from ``(R0, p0, w0, v0)``, with its priors (the rate's
        ``prior_w_rad_s``, the velocity's ``v_std``, the position's inverse variance
        ``p_inv_var``; ``prior_mean`` = ``[w, v, p]``). Returns the state (None if not
        finite), the inliers (reprojection error under ``track_inlier_px``), the Hessian and
        the inliers' residual variance per image coordinate (px^2, at least 1e-6)."""
        o = self.options
        p2 = np.repeat([1.0 / o.prior_w_rad_s**2, 1.0 / v_std**2, p_inv_var], 3)
        R, p, w, v, a, res, cost, H = rs_projection.track_frame(
            R0, p0, w0, v0, np.zeros(3), X, x, s, self.focal, o.track_robust_px * self._px,
            prior_mean, p2, acc_prior_p2(self.map.options.prior_acc_rad_s2),
            o.track_iterations)  # fmt: skip
        err = np.linalg.norm(res, axis=1)
        threshold = o.track_inlier_px * self._px
        self._err_median = float(np.median(err)) if len(err) else np.nan
        if o.track_inlier_sigmas > 0 and np.isfinite(self._err_median):
            # the image noise the last tracked frames showed (not this frame's, but for the
            # first: a diverged pose must not widen its own threshold); the median of a 2-D
            # Gaussian error's length is sqrt(2 ln 2) sigma
            seen = np.median(self._err_medians) if self._err_medians else self._err_median
            sigma = float(seen) / np.sqrt(2.0 * np.log(2.0))
            threshold = max(threshold, o.track_inlier_sigmas * sigma)
        inl = err < threshold
        finite = np.isfinite(R).all() and np.isfinite(p).all()
        sigma2 = max(float(np.mean(err[inl] ** 2)) / 2.0, 1e-6) if inl.any() else np.inf
        return (FrameState(stamp_ns, R, p, w, v, a) if finite else None), inl, H, sigma2

    def _usual_speed(self) -> float | None:
        """Median speed (map units/s) of the last tracked frames, None before any."""
        return float(np.median(self._speeds)) if self._speeds else None

    def _needs_keyframe(self, last_kf: KeyFrame, obs: Observations, state: FrameState,
                        tracked: int) -> bool:  # fmt: skip
        o = self.options
        if (state.stamp_ns - last_kf.state.stamp_ns) * 1e-9 > o.keyframe_max_interval_s:
            return True
        if tracked < o.keyframe_track_ratio * self._tracked_at_kf:
            return True
        return self._parallax_px(last_kf, obs, state.R) > o.keyframe_parallax_px * self._px

    def _recover(self, stamp_ns: int, obs: Observations) -> WindowResult:
        """Too few map points: the pair estimator between the last keyframe and this frame,
        scaled by the landmarks they share; else hold, and after a few held frames start a new
        map where the trajectory stands."""
        if self._mapper is not None:
            self._mapper.wait_idle()  # the pair recovery and a map reset change the map
            self._pick_up_mapping()
        predicted = None
        if self._last is not None:
            predicted = extrapolate(self._last, self._before, stamp_ns)
            found = self._relocalize(stamp_ns, obs, predicted)
            if found is not None:
                return found
        stall = self._stall
        last_kf = self.map.keyframes[-1] if self.map.keyframes else None
        # a map left with fewer points than tracking needs is not recovered into (its keyframes
        # would be placed by the last speed alone, and it never comes back): it starts over
        dead = len(self.map.landmarks) < self.options.min_landmarks
        late_moved: list[tuple[FrameState, FrameState]] = []
        if last_kf is not None and not dead:
            # after a stall the pair's tracks cross it: its rotation is checked
            check = predicted if stall is not None else None
            found = self._pair_recovery(last_kf, stamp_ns, obs, check)
            late = self._late_keyframe(last_kf) if found is None else None
            if late is not None:
                kf, moved = late
                late_moved = [moved]  # that (published) frame moved first
                found = self._pair_recovery(kf, stamp_ns, obs, check)
                if found is not None:
                    found.reason = LATE_RECOVERY_REASON
                    found.ba_moved = late_moved + found.ba_moved
            if found is not None:
                return found
        self._lost += 1
        held = self._last.copy()
        if self._lost >= self.options.lost_frames_to_reset or dead or stall is not None:
            speed, usual = float(np.linalg.norm(held.v)), self._usual_speed()
            if usual is not None and speed > 2.0 * usual:
                held.v = held.v * (usual / speed)  # a diverging last pose must not set it
            if stall is not None:
                held = extrapolate(held, self._before, stamp_ns)
            self._origin = held
            self.map = self._new_map()
            self._make_provisional(stamp_ns)
            self._points = (np.zeros(0, np.int64), np.zeros((0, 3)))
            self._last = self._before = None
            self._lost = 0
            self._hints_in_memory.clear()
            self._refind_frames = 0
            started = self._start(stamp_ns, obs)
            started.reason = "lost: too few map points and no pair pose; a new map starts"
            self._stalled_map = stall is not None
            if stall is not None:
                started.reason = (f"lost after {stall:.2f} s without a frame: a new map starts "
                                  f"at the constant-velocity prediction")
                started.stall_restart = True
            return started
        return WindowResult("held", "lost: too few map points and no pair pose", held,
                            ba_moved=late_moved)  # fmt: skip

    def _stall_s(self, stamp_ns: int) -> float | None:
        """Seconds since the last frame (posed or not) where that is more than
        ``stall_intervals`` of the stream's cadence (the median interval of the last frames)
        and at most ``stall_max_s``: a stalled camera or node, whose tracks across it may have
        locked onto a repeated pattern; else None."""
        cadence = self._cadence_ns()
        if self.options.stall_intervals <= 0 or cadence is None:
            return None
        gap = stamp_ns - self._seen[-1]
        if not (cadence > 0 and self.options.stall_intervals * cadence < gap
                <= self.options.stall_max_s * 1e9):
            return None
        return gap * 1e-9

    def _cadence_ns(self) -> float | None:
        """The stream's frame interval (ns): the median interval of the last frames seen,
        None before two."""
        if len(self._seen) < 2:
            return None
        return float(np.median(np.diff(np.asarray(self._seen, np.int64))))

    def _aliased(self, predicted: FrameState, state: FrameState, inliers: int) -> bool:
        """Whether a pose tracked across a stall is a repeated pattern's: more than
        ``reloc_max_rotation_deg`` off the constant-velocity prediction and supported by
        fewer than ``stall_min_inlier_share`` of the usual inliers."""
        o = self.options
        turn = _turn_deg(predicted.R, state.R)
        usual = float(np.median(self._inliers)) if self._inliers else 0.0
        return bool(turn > o.reloc_max_rotation_deg and inliers < o.stall_min_inlier_share * usual)

    def _pair_recovery(self, kf: KeyFrame, stamp_ns: int, obs: Observations,
                       predicted: FrameState | None = None) -> WindowResult | None:  # fmt: skip
        """The frame posed by the pair estimator from keyframe ``kf``, scaled by the landmarks
        they share, and made a keyframe (mapped inline); None without a pair pose, or with
        one more than ``reloc_max_rotation_deg`` off ``predicted`` (if given)."""
        dt = (stamp_ns - kf.state.stamp_ns) * 1e-9
        res, ia, ib = self._pair(kf.obs, obs, dt, self.seed + self._next_kf)
        if res is None:
            return None
        limit = self.options.recovery_turn_parallax_px * self._px
        turn = limit > 0 and self._translation_parallax_px(kf, obs) < limit
        scale = self._pair_scale(kf, res, ia, dt, turn)
        if scale is None:
            return None
        state, _, vel_cur = self._states_from_pair(res, kf.state, stamp_ns, scale)
        if predicted is not None and \
                not _turn_deg(predicted.R, state.R) <= self.options.reloc_max_rotation_deg:
            return None
        new_kf = self._new_keyframe(state, obs, vel_cur)
        before = state.copy()
        # the scale is a guess: the BA may refine the points the memory has (the tracked
        # map's), but the landmarks triangulated from the guessed baseline stay out of the
        # memory that re-finding trusts (a walk re-found on such points went on at 0.4 of its
        # scale: README, "A pair recovery's landmarks kept out of the memory")
        report = self.map_keyframe(new_kf, remember_new=False)
        state = new_kf.state.copy() if new_kf in self.map.keyframes else state
        self._before, self._last = self._last, state.copy()
        self._lost = 0
        self._tracked_at_kf = len(self.map.landmarks)
        self._make_provisional(stamp_ns)
        self._refind_frames = self.options.reloc_frames_after_recovery
        paired = obs.ids[ib]
        return WindowResult("posed", "recovered with the pair estimator", state,
                            inliers=res.num_inliers, tracked=len(ib), keyframe=True,
                            ba=report, ba_moved=[(before, state.copy())],
                            inlier_ids=paired[res.inliers],
                            outlier_ids=paired[~res.inliers])  # fmt: skip

    def _late_keyframe(self, last_kf: KeyFrame) -> tuple[KeyFrame, tuple] | None:
        """The last frame tracked against the map after ``last_kf`` made a keyframe now and
        mapped inline (a fast turn can leave the last keyframe too few tracks for a pair
        while the frame before the loss still shares most of its tracks), with its state
        before and after that BA; None if there is no such frame."""
        kept, self._last_tracked = self._last_tracked, None
        if kept is None or self._last is None:
            return None
        stamp_ns, obs, rejected = kept
        if stamp_ns != self._last.stamp_ns or stamp_ns <= last_kf.state.stamp_ns:
            return None
        kf = self._new_keyframe(self._last, obs, (self._last.w.copy(), self._last.v.copy()))
        kf.before = self._before.copy() if self._before is not None else None
        kf.rejected.update(int(t) for t in rejected)
        before = self._last.copy()
        self.map_keyframe(kf)
        if kf not in self.map.keyframes:
            return None
        self._last = kf.state.copy()
        return kf, (before, kf.state.copy())

    def _pair_scale(self, kf: KeyFrame, res, ia: np.ndarray, dt: float,
                    turn: bool = False) -> float | None:  # fmt: skip
        """Map units per unit of the pair's ``|t|`` from the depths of the landmarks the pair
        shares with the map (median ratio) unless that moves the camera more than
        ``recovery_max_steps`` usual steps, else from the last speed (at most twice the usual
        speed: the frames just before a loss may be off). ``turn``: a pair without translation
        parallax, scaled by the last tracked frames' median speed."""
        if turn and self._speeds:
            recent = float(np.median(list(self._speeds)[-RECENT_SPEED_FRAMES:]))
            if recent * dt > 0:
                return recent * dt
        usual = self._usual_speed()
        limit = np.inf if usual is None else self.options.recovery_max_steps * usual * dt
        tids = kf.obs.ids[ia]
        ids, X = self._points
        _, i_map, i_pair = np.intersect1d(ids, tids, return_indices=True)
        good = res.inliers[i_pair] & np.isfinite(res.depths_prev[i_pair]) \
            & (res.depths_prev[i_pair] > 0)
        if good.sum() >= self.options.min_shared_for_scale:
            s = kf.obs.s[ia][i_pair][good]
            R_s, p_s = kf.state.row_cameras(s)
            depth_map = np.einsum("nji,nj->ni", R_s, X[i_map][good] - p_s)[:, 2]
            ratio = depth_map / res.depths_prev[i_pair][good]
            ratio = ratio[np.isfinite(ratio) & (ratio > 0)]
            scale = float(np.median(ratio)) if len(ratio) else np.inf
            if len(ratio) >= self.options.min_shared_for_scale and scale <= limit:
                return scale
        speed = float(np.linalg.norm(self._last.v)) if self._last is not None else 0.0
        if usual is not None:
            speed = min(speed, 2.0 * usual)
        return speed * dt if speed * dt > 0 else None

    # ------------------------------------------------------------------ mapping

    def map_keyframe(self, kf: KeyFrame | None, optimize_only: bool = False,
                     remember_new: bool = True) -> BAReport:
        """Insert ``kf`` (None: only optimise), slide the window, run the BA and give tracking
        the new points. ``remember_new`` False: the points go into the memory only where it has
        them already (a pair recovery's BA: its new landmarks rest on a guessed scale)."""
        report, points = self._map(kf, optimize_only, remember_new)
        self._points = points
        return report

    def _map(self, kf: KeyFrame | None, optimize_only: bool = False,
             remember_new: bool = True) -> tuple[BAReport, tuple[np.ndarray, np.ndarray]]:
        """:meth:`map_keyframe` without handing the points to tracking: the mapping thread's
        points go to tracking with the keyframe's correction, at the frame that picks both up
        (points from the refined map with a prediction from the map as it was had put
        tracking off by that correction)."""
        with self._lock:
            if kf is not None and not optimize_only:
                self.map.add_keyframe(kf)
            self.map.slide()
            self.map.rate_shift = self._map_shear() if self.options.shear_from_turns else None
            report = self.map.optimize()
            if self.calibrator is not None and self.map.last_problem is not None:
                self.calibrator.add_window(self.map.last_problem, self.row_ref)
            points = self.map.points()
            newest = self.map.keyframes[-1].state.stamp_ns if self.map.keyframes else None
            if newest is not None and not self._provisional(newest):
                self._remember(points, remember_new)
            log = dict(self.keyframe_log)
            log.update({k.state.stamp_ns: k.state.copy() for k in self.map.keyframes})
            cap = self.options.keyframe_log_max
            if cap is not None and len(log) > cap:
                log = dict(sorted(log.items())[-cap:])
            # replaced whole, never changed in place: the viewers read it without waiting
            self.keyframe_log = log
        return report, points

    def _map_shear(self) -> np.ndarray | None:
        """The map's shear over the window's span (line_delay.map_rate_shear), None without
        enough tracked frames there."""
        if len(self.map.keyframes) < 2:
            return None
        first, last = self.map.keyframes[0].state.stamp_ns, self.map.keyframes[-1].state.stamp_ns
        span = [r for r in list(self._rates) if first <= r[0] <= last]  # tracking appends
        if len(span) < MIN_SHEAR_FRAMES:
            return None
        stamps, R, w = zip(*span, strict=True)
        return map_rate_shear(np.array(stamps), np.array(R), np.array(w))

    # ------------------------------------------------------------------ re-finding the map

    def _make_provisional(self, stamp_ns: int) -> None:
        if self.options.reloc_min_inliers > 0:
            self._provisional_until = stamp_ns + int(self.options.reloc_window_s * 1e9)

    def _provisional(self, stamp_ns: int) -> bool:
        until = self._provisional_until
        return until is not None and stamp_ns < until

    def _remember(self, points: tuple[np.ndarray, np.ndarray], new: bool = True) -> None:
        """Write the map's landmarks (world points) into the memory, each with the descriptor
        of the newest keyframe of the window that has one for it (``new`` False: only those
        the memory has)."""
        ids, X = points
        if self.options.reloc_min_inliers <= 0 or not len(ids):
            return
        if not new:
            keep = self.memory.known(ids)
            ids, X = ids[keep], X[keep]
        kf_ids, kf_desc = [], []
        for kf in self.map.keyframes:  # oldest first: the newest keyframe's descriptor wins
            if kf.descriptors is not None:
                d, valid = kf.descriptors
                kf_ids.append(kf.obs.ids[valid])
                kf_desc.append(d[valid])
        if not kf_ids:
            return
        all_ids, all_desc = np.concatenate(kf_ids)[::-1], np.concatenate(kf_desc)[::-1]
        uniq, first = np.unique(all_ids, return_index=True)  # first of the reversed: newest
        _, i_pts, i_desc = np.intersect1d(ids, uniq, return_indices=True)
        self.memory.update(ids[i_pts], X[i_pts], all_desc[first[i_desc]])

    def _relocalize(self, stamp_ns: int, obs: Observations, predicted: FrameState,
                    exclude: np.ndarray | None = None) -> WindowResult | None:  # fmt: skip
        """Pose the frame against the memory (:func:`~rsvo_ros.odometry.relocalize.
        match_memory`, then tracking's motion-only RS refinement on the inliers); if it holds,
        the map starts over from this frame, a keyframe whose landmarks are the points found,
        in the memory's world and scale. ``exclude``: track ids not to match (the current
        map's). None where nothing is found."""
        o = self.options
        if o.reloc_min_inliers <= 0 or obs.describe is None \
                or len(self.memory) < o.reloc_min_inliers:  # fmt: skip
            return None
        mem = self.memory.snapshot()
        if exclude is not None and len(exclude):
            keep = ~np.isin(mem[0], exclude)
            mem = (mem[0][keep], mem[1][keep], mem[2][keep])
        desc, valid = obs.describe()
        found = match_memory(mem, obs.x, desc, valid, self.focal, o.reloc_ratio,
                             o.reloc_max_hamming, o.reloc_ransac_px * self._px,
                             o.reloc_min_inliers, self.seed + self._next_kf)  # fmt: skip
        if found is None:
            return None
        turn = _turn_deg(predicted.R, found.R)
        if not turn <= o.reloc_max_rotation_deg:
            return None
        usual = self._usual_speed()
        cadence_ns = self._cadence_ns()
        if self._stalled_map and usual and cadence_ns is not None:
            # a map started after a stall: the lost map's memory can alias as the tracks did
            # (a car re-found 19 steps back, where the stall began), so within the usual steps
            # of the prediction too
            cadence = cadence_ns * 1e-9
            if np.linalg.norm(found.p - predicted.p) > o.reloc_max_jump_steps * usual * cadence:
                return None
        if not self._provisional(stamp_ns) and usual and self._last is not None:
            # a trusted map (not one rebuilt after a loss) moves the frame by about a step
            # (checked before the guided matching, which keeps the pose: a rejected re-finding
            # right after a loss cost it 8-16 ms at 1280x720)
            dt = max((stamp_ns - self._last.stamp_ns) * 1e-9, 1e-3)
            if np.linalg.norm(found.p - predicted.p) > o.reloc_max_jump_steps * usual * dt:
                return None
        found = guided_matches(found, mem, obs.x, desc, valid, self.focal,
                               o.reloc_guided_px * self._px, o.reloc_max_hamming)  # fmt: skip
        sv = max(o.prior_v_rel * (usual or 0.0), o.prior_v_floor)
        w0, v0 = predicted.w.copy(), np.zeros(3)
        j = found.obs_idx
        state, inl, H, sigma2 = self._motion_only(
            stamp_ns, found.R, found.p, w0, v0, found.X, obs.x[j], obs.s[j],
            np.concatenate([w0, v0, found.p]), sv, 0.0)  # fmt: skip
        if state is None or inl.sum() < o.reloc_min_inliers:
            return None
        outlier_ids = obs.ids[j[~inl]]
        j, X = j[inl], found.X[inl]
        R_rows, p_rows = state.row_cameras(obs.s[j])
        depth = np.einsum("nji,nj->ni", R_rows, X - p_rows)[:, 2]
        if self._mapper is not None:
            self._mapper.wait_idle()
            self._pick_up_mapping()
        with self._lock:
            self.map = self._new_map()
            kf = self._new_keyframe(state, obs, (state.w.copy(), state.v.copy()))
            self.map.add_keyframe(kf)
            for n, d in zip(j.tolist(), depth.tolist(), strict=True):
                if d > 0:
                    self.map.landmarks[int(obs.ids[n])] = Landmark(
                        kf.id, obs.x[n].copy(), float(obs.s[n]), 1.0 / d)
            self._points = self.map.points()
        self._last, self._before = state.copy(), None
        self._lost = 0
        self._tracked_at_kf = int(inl.sum())
        self._provisional_until = None
        self._refind_frames = 0
        self._ref = self._origin = None
        self._stalled_map = False
        self._hints.clear()
        return WindowResult("posed", f"{REFOUND_REASON} ({int(inl.sum())} points)", state,
                            inliers=int(inl.sum()), tracked=len(found.obs_idx), keyframe=True,
                            hessian=H, sigma2=sigma2, refound=True,
                            inlier_ids=obs.ids[j], outlier_ids=outlier_ids)  # fmt: skip

    def _map_options(self) -> MapOptions:
        """The map's options: the given ones; without a readout (a global shutter, or the GS
        models) the angular accelerations are held, as nothing in the images shows them."""
        if self.line_delay > 0 or self.options.map.prior_acc_rad_s2 <= 0:
            return self.options.map
        return dataclasses.replace(self.options.map, prior_acc_rad_s2=0.0)

    def _new_map(self) -> LocalMap:
        return LocalMap(self.focal, self._map_options())

    def set_line_delay(self, line_delay: float) -> None:
        """Go on with another line delay (line_delay auto): every kept observation's row time
        is recomputed from its row (the landmarks' anchors with them), the map points renewed."""
        if self._mapper is not None:
            self._mapper.wait_idle()
        with self._lock:
            self.line_delay = float(line_delay)
            self.map.options = self._map_options()
            self.map.set_row_times(self.row_time)
            if self._ref is not None:
                self._ref.obs.s = self.row_time(self._ref.obs.rows)
            self._points = self.map.points()
            if self._mapper is not None:
                self._mapper.replace_points(self._points)

    def map_points(self) -> np.ndarray:
        """(M, 3) world points of the local map's landmarks (what tracking matches)."""
        return self._points[1].copy()

    def keyframe_poses(self, last: int | None = None) -> list[tuple[int, np.ndarray]]:
        """``(stamp_ns, row-0 T_world_camera)`` of every keyframe so far (or of the ``last``
        ones), as last refined."""
        log = self.keyframe_log
        stamps = sorted(log)[-last:] if last else sorted(log)
        return [(stamp, self.row0_pose(log[stamp])) for stamp in stamps]

    def close(self) -> None:
        """Stop the mapping thread (async mapping)."""
        if self._mapper is not None:
            self._mapper.close()
            self._mapper = None

    def row0_pose(self, state: FrameState) -> np.ndarray:
        """(4, 4) ``T_world_camera`` of a frame's row 0 (what the pipeline reports)."""
        return state.pose(self.row0_time())


def covariance_from_tracking(result: WindowResult) -> np.ndarray:
    """(6, 6) covariance of ``[position, rotation vector]`` in the world frame from tracking's
    Hessian (the velocities marginalised), ``sigma^2 H^-1``; huge where it cannot be had."""
    if result.hessian is None or result.state is None:
        return np.diag([1e2] * 3 + [1e1] * 3)
    try:
        n = rs_projection.FRAME_PARAMS
        cov = np.linalg.inv(result.hessian + 1e-9 * np.eye(n))[:6, :6] * result.sigma2
    except np.linalg.LinAlgError:
        return np.diag([1e2] * 3 + [1e1] * 3)
    R = result.state.R
    out = np.zeros((6, 6))
    out[:3, :3] = cov[3:6, 3:6]  # position: already in the world frame
    out[3:, 3:] = R @ cov[0:3, 0:3] @ R.T  # rotation increments are in the camera frame
    out[:3, 3:] = cov[3:6, 0:3] @ R.T
    out[3:, :3] = out[:3, 3:].T
    return out if np.isfinite(out).all() else np.diag([1e2] * 3 + [1e1] * 3)


class MappingError(RuntimeError):
    """The window BA on the mapping thread raised (the cause is chained)."""


class Mapper:
    """Runs :meth:`WindowOdometry.map_keyframe` on a background thread (the node's mapping
    path): tracking submits a keyframe when the mapper is idle and picks up the result with
    :meth:`finished` at a later frame. The compiled kernels release the GIL, so on two cores
    tracking and the window BA run side by side."""

    def __init__(self, odometry: WindowOdometry):
        self.odometry = odometry
        self._job: tuple[KeyFrame, FrameState] | None = None
        # the keyframe, its state when submitted, the BA report and the map's points
        self._done: tuple[KeyFrame, FrameState, BAReport, tuple] | None = None
        self._error: Exception | None = None  # what the last job raised, for the caller
        self._cv = threading.Condition()
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="rsvo_mapping", daemon=True)
        self._thread.start()

    @property
    def busy(self) -> bool:
        """A keyframe is being mapped, or its result has not been picked up yet."""
        with self._cv:
            return self._job is not None or self._done is not None

    def submit(self, kf: KeyFrame, state_before: FrameState) -> None:
        with self._cv:
            if self._job is not None or self._done is not None:
                raise RuntimeError("the mapper is busy")
            self._job = (kf, state_before)
            self._cv.notify_all()

    def finished(self) -> tuple[KeyFrame, FrameState, BAReport, tuple] | None:
        """The mapped keyframe, its state when it was submitted, the BA report and the
        points for tracking, once. Raises :class:`MappingError` (once) if the job raised: on
        the tracking thread, where the pipeline counts faults, instead of a thread that dies
        and a keyframe that is never picked up (tracking then waited for it at every frame)."""
        with self._cv:
            done, self._done = self._done, None
            error, self._error = self._error, None
        if error is not None:
            raise MappingError(f"the window BA on the mapping thread failed: "
                               f"{type(error).__name__}: {error}") from error
        return done

    def replace_points(self, points: tuple[np.ndarray, np.ndarray]) -> None:
        """A result not picked up yet hands these points to tracking instead (the map's
        points were recomputed since, for another line delay)."""
        with self._cv:
            if self._done is not None:
                self._done = (*self._done[:3], points)

    def wait_idle(self, timeout: float = 30.0) -> None:
        """Until the current job is done (its result stays to be picked up)."""
        with self._cv:
            self._cv.wait_for(lambda: self._job is None or self._stop, timeout)

    def _run(self) -> None:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._job is not None or self._stop)
                if self._stop:
                    return
                kf, before = self._job
            try:
                report, points = self.odometry._map(kf)
            except Exception as exc:  # noqa: BLE001 - handed to the tracking thread
                with self._cv:
                    self._job, self._error = None, exc
                    self._cv.notify_all()
                continue
            with self._cv:
                self._job, self._done = None, (kf, before, report, points)
                self._cv.notify_all()

    def close(self) -> None:
        with self._cv:
            self._stop = True
            self._cv.notify_all()
        self._thread.join(timeout=30.0)


class DeferredMapper:
    """:class:`Mapper`'s interface without a thread: the window BA runs when the keyframe is
    submitted and its result waits to be picked up (``mapping_lag_s`` with inline
    mapping: the replay gives what a node with the same lag gives, whatever the machine's
    speed). The BA's time is spent in the keyframe's frame."""

    def __init__(self, odometry: WindowOdometry):
        self.odometry = odometry
        self._done: tuple[KeyFrame, FrameState, BAReport, tuple] | None = None

    @property
    def busy(self) -> bool:
        return self._done is not None

    def submit(self, kf: KeyFrame, state_before: FrameState) -> None:
        if self._done is not None:
            raise RuntimeError("the mapper is busy")
        report, points = self.odometry._map(kf)
        self._done = (kf, state_before, report, points)

    def finished(self) -> tuple[KeyFrame, FrameState, BAReport, tuple] | None:
        done, self._done = self._done, None
        return done

    def replace_points(self, points: tuple[np.ndarray, np.ndarray]) -> None:
        if self._done is not None:
            self._done = (*self._done[:3], points)

    def wait_idle(self, timeout: float = 30.0) -> None:
        """Nothing runs in the background."""

    def close(self) -> None:
        """Nothing to stop."""
