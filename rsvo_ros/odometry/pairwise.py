"""The pairwise backend: estimate each frame pair, chain the poses with a consistent scale (the
paper's method).

Pure numpy (no rclpy); :class:`rsvo_ros.odometry.pipeline.OdometryPipeline` feeds it.

Chaining as in the paper: ``T_{k+1} = T_k [R t; 0 1]^-1`` with ``X_curr = R X_prev + t``, i.e.
``T_world_curr = T_world_prev @ inv(T_curr_prev)``, applied to the cameras of the frames'
middle rows (the reference row of the RS solver): their relative motion needs no velocity to be
right, while the row-0 one inherits the velocities' errors (which from two views stay large
under noise). Each frame's row-0 pose, what the pipeline reports (CONTRACTS.md), is where the
chain of middle-row cameras was at the row-0 time: ``row_mid * tau`` before the frame's middle
row, interpolated between consecutive middle-row poses; for a turning camera (below) the
rotation is instead its middle row's turned back over the first half of its readout at
:func:`row0_turn_rate` (the motion between the middle rows plus a part of the change of the
fitted rates: a hand-held shake turns the camera too fast for an interpolation between middle
rows 33 ms apart). With a global shutter (``tau = 0``, or the GS models, whose reference row is row
0) this is the plain chain.

Motion prior (RS, ``PipelineOptions.motion_prior``): the frames are one continuous motion, so
each pair's velocity prior is centred on the constant velocity of that pair's own motion over
its stamps' interval, with a much tighter translation part than the paper's experiment allows
(from two views the velocities' common part, above all the linear velocity under forward
motion, is barely observed: on the synthetic vehicle it came out 100-1000 % off, and warped
the depths that carry the scale), and the previous pair's middle-row motion is one more start
of the search. Measured over 16 vehicle sequences, the tighter prior and the extra start give
the gain; where the prior is centred (constant velocity or zero) changes the ATE little, but
only the constant velocity leaves the velocities unbiased.

Short baselines (``ROTATION_ONLY_PARALLAX_PX``): a pair whose tracks a turning camera explains
to within a pixel or so (a hand-held walk's consecutive frames) is posed by that camera's
rotation (odometry/rotation.py), the baseline direction that makes each track's rays coplanar
with it, and the last baseline: the pair estimator's rotation there was 1-2.7 deg per frame
off, the turning camera's 0.1-0.4 deg (docs/notebook.md, "Short baselines"). After such a
pair the next one is first fitted as a turning camera from the last motion and turn rate, and
the pair estimator runs only where that leaves more than the limit
(:meth:`PairwiseChain._turning_first`: a walk's first frames then cost a third of the time; a
pure rotation that the pair estimator would hold for want of parallax is posed as the turn it
is).

Scale: the first pair's baseline is ``initial_scale``; each later pair's ``|t|`` makes the
depths of the points it shares with the previous pair agree (a line fitted to their inverse
depths, which the estimator gives in each point's own row camera); without enough shared points
it keeps the previous baseline.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from rsvo_ros.core.geometry import pose_at_row, pose_from_row, pose_inverse, so3_exp, so3_log
from rsvo_ros.core.lens import undistort_points
from rsvo_ros.odometry.frame import FrameState
from rsvo_ros.odometry.rotation import direction_given_rotation, fit_rotation
from rsvo_ros.odometry.tracker import TrackedPair
from rsvo_ros.twoview import LMOptions, RansacOptions, RelativePoseResult, estimate_relative_pose

MIN_SHARED_FOR_SCALE = 8  # shared triangulated points needed to measure the relative scale
MAX_DEPTH_IN_BASELINES = 40.0  # farther points do not vote on the scale
MAX_SCALE_STEP = 1.25  # largest change of the baseline from one pair to the next
# after a restart from another estimate (the window's map was lost), the baseline stays within
# this factor of the one it restarted with: measured, a chain bridging a stop-and-look-around
# (no translation to measure the scale from) otherwise grew it 1.25x per pair, to 1e15 m
RESTART_BASELINE_RANGE = 4.0
HOLD_COVARIANCE_GROWTH = 4.0  # covariance multiplier of a held (not estimated) pose
# a pair whose tracks a turning camera explains to within this (median px at 1000 px focal,
# each frame's rows turning at its rate; odometry/rotation.py) has too little baseline for the
# pair estimator's rotation: the chain takes the turning camera's rotation, the direction that
# makes each track's rays coplanar with it, and the last baseline (0: never)
ROTATION_ONLY_PARALLAX_PX = 3.0
# ... and where a constant turn rate per frame leaves up to this many times that, the pair is
# fitted again with the rate's change over the readout (the severity-2 walks' pairs it brought
# under the limit had 1.1-1.7x; a vehicle's 2-3x is its translation, and the second fit costs
# about 3 ms)
ACCELERATION_FIT_UP_TO = 2.0
# A pair estimate whose rotation std (its covariance) is over this many degrees is replaced by a
# turning camera's fit at any translation parallax: the first pairs of a shaken RS vehicle (12-30
# px of parallax, over the turning camera's limit) had 2-7 deg of rotation error with a 3.5 deg
# std, where a rotation-only fit is within 1.6 deg (docs/notebook.md, "Where the vehicles' ATE now
# comes from"). Such a pair's scale is the last baseline (no depths), so a chain that runs for the
# whole sequence (the pairwise backend) takes fewer of them than the window's bootstrap, whose map
# measures the scale after 2-6 frames. Chosen among 1.0, 0.5, 0.3, 0.2 and 0.01 on the vehicle
# table and the fresh vehicles (33 bags; geometric means against the previous rule, 1.0 with the
# direction from the small-residual tracks only): window ATE 0.88 / 0.84 / 0.85 / 0.88 and RPE 0.83
# / 0.73 / 0.71 / 0.66 for 0.5 / 0.3 / 0.2 / 0.01 (bags worse by over 20 %: 0 / 1 / 1 / 5);
# pairwise backend ATE 1.03 / 1.19 (vehicle table) and 0.86 / 0.94 (fresh) for 0.5 / 0.3, RPE 0.85
# / 0.77 and 0.76 / 0.67. Then checked on the held-out vehicles. 0: never
UNCERTAIN_PAIR_ROTATION_DEG = 0.5  # the pairwise backend
# ... and where the direction given that rotation puts under this share of the tracks in front
# of both cameras, the chain keeps the last pair's direction. On the 33 vehicles' 34 uncertain
# pairs the direction was 1-28 deg off (ground truth) at a share of 0.85-1.0, 36-122 deg at
# 0.58-0.78 and 91 deg once at 0.82, 3 deg once at 0.74 (README)
UNCERTAIN_MIN_FRONT = 0.8
BOOTSTRAP_UNCERTAIN_ROTATION_DEG = 0.3  # the window backend's chain (until a map; after a loss)
# row0_turn_rate's share of the change of the fitted rates. Measured on rendered walks with 8-15 Hz
# shake (docs/notebook.md, "Row 0 of a turning camera"): with the renderer's exact middle-row poses
# and rates the row-0 rotations were 0.77 deg per frame off for an interpolation between the middle
# rows (share 0), 0.20 deg at 1/2, 0.135 deg at 0.4 and 0.23 deg at 0.3; with the chain's fitted
# rates (their difference is noisy) the walks' RPE was least at 0.3 (0.86x of 1/2 on the tuning
# walks; 0.15: 0.99x, 0.4: 0.89x, 0.7: 1.33x)
ROW0_RATE_CHANGE_SHARE = 0.3
DEFAULT_POSITION_VARIANCE = 1e-2  # m^2 per pair when a fit gives no usable covariance


def uncertain_rotation_or_auto(deg: float, name: str) -> float | None:
    """A user's uncertain-rotation setting: -1 is the backend's choice (None), else a finite
    number of degrees >= 0; ``ValueError`` naming the setting otherwise."""
    if deg == -1:
        return None
    if not (np.isfinite(deg) and deg >= 0):
        raise ValueError(f"{name} must be -1 (the backend's choice) or a number of degrees "
                         f">= 0, got {deg}")  # fmt: skip
    return float(deg)


@dataclass
class PairStep:
    """What the pairwise chain says about one frame: the pose (``T_world_camera`` at row 0)
    and covariance are the chain's after the step."""

    status: str  # "posed", "held"
    reason: str
    num_inliers: int = 0
    inlier_ratio: float = 0.0
    scale: float = 0.0
    relative: RelativePoseResult | None = None


@dataclass
class _Turn:
    """A turning camera's middle-row motion ``X_curr = R X_prev + t`` (unit ``t``), the
    translation parallax it leaves (median px), the turn rates it held and fitted, each
    track's residual (px; nan for the tracks not fitted) and the share of tracks in front of
    both cameras with that direction."""

    R: np.ndarray
    t: np.ndarray
    parallax_px: float
    w_prev: np.ndarray
    w_curr: np.ndarray
    residual_px: np.ndarray
    front: float = 1.0


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


def row0_turn_rate(R_curr_prev: np.ndarray, interval: float, w_prev: np.ndarray,
                   w_curr: np.ndarray, share: float | None = None) -> np.ndarray:  # fmt: skip
    """The turn rate (rad/s, current camera frame) that takes the current frame's middle-row
    camera back to its row 0, from a pair's middle-row motion ``X_curr = R_curr_prev X_prev``
    over ``interval`` s and the two frames' fitted turn rates.

    Each fitted rate stands for its frame's turn during the readout, but two views observe only
    their difference ``d`` (the images see how the distortion changed; its common part moves
    every row alike); the turn between the middle rows is about the mean of the two frames'
    rates times the interval, so the current frame's own rate is ``Log(R) / interval + d / 2``
    and the mean over the first half of its readout lies between that and ``Log(R) /
    interval``: ``Log(R) / interval + share d`` (``share``: ``ROW0_RATE_CHANGE_SHARE``)."""
    share = ROW0_RATE_CHANGE_SHARE if share is None else share
    r = so3_log(R_curr_prev.T)  # the turn between the middle rows (its axis: either frame's)
    d = np.asarray(w_curr, float) - R_curr_prev @ np.asarray(w_prev, float)  # current camera
    return r / max(interval, 1e-9) + share * d


def _interpolate(T: np.ndarray, a: float) -> np.ndarray:
    """The fraction ``a`` of the motion ``T`` (4, 4): rotation ``Exp(a Log R)``, translation
    ``a p`` (constant velocity between two poses; ``a`` outside [0, 1] extrapolates)."""
    out = np.eye(4)
    out[:3, :3] = so3_exp(a * so3_log(T[:3, :3]))
    out[:3, 3] = a * T[:3, 3]
    return out


class PairwiseChain:
    """The chain of frame pairs; :meth:`step` with each tracked pair after the first frame."""

    def __init__(self, K: np.ndarray, D: np.ndarray | None, line_delay: float, model: str,
                 mode: str, ransac: RansacOptions, lm: LMOptions, initial_scale: float,
                 motion_prior: bool, max_scale_change: float, seed: int,
                 rotation_only_parallax_px: float = ROTATION_ONLY_PARALLAX_PX,
                 uncertain_rotation_deg: float = UNCERTAIN_PAIR_ROTATION_DEG):  # fmt: skip
        self.K, self.D, self.line_delay = K, D, line_delay
        self.rotation_only_parallax_px = rotation_only_parallax_px
        self.uncertain_rotation_deg = uncertain_rotation_deg
        self.model, self.mode, self.ransac, self.lm = model, mode, ransac, lm
        self.initial_scale, self.motion_prior = initial_scale, motion_prior
        self.max_scale_change, self.seed = max_scale_change, seed
        self.T_world_cam = np.eye(4)
        self._T_world_mid: np.ndarray | None = None  # the last posed frame's middle-row camera
        self.covariance = np.zeros((6, 6))
        self._prev_depths: dict[int, float] = {}  # track id -> metric depth in the last frame
        self._last_baseline = initial_scale  # metres between middle-row cameras
        self._baseline_range: tuple[float, float] | None = None  # set by restart()
        # the last estimated motion between middle-row cameras: (R, unit t, seconds)
        self._last_motion: tuple[np.ndarray, np.ndarray, float] | None = None
        # the last pair's current frame's turn rate, when a turning camera posed that pair
        self._last_turn_rate: np.ndarray | None = None

    def restart(self, T_world_cam: np.ndarray, baseline: float) -> None:
        """Go on from another estimate's pose with its last baseline (metres between frames;
        0: keep this chain's)."""
        self.T_world_cam = np.array(T_world_cam, float)
        self._T_world_mid = None
        self._prev_depths = {}
        self._last_motion = None
        self._last_turn_rate = None
        if baseline > 0:
            self._last_baseline = baseline
            self._baseline_range = (baseline / RESTART_BASELINE_RANGE,
                                    baseline * RESTART_BASELINE_RANGE)

    def step(self, pair: TrackedPair, interval: float, idx: int) -> PairStep:
        """One frame pair (``interval`` s apart); updates the chain's pose and covariance."""
        pts_prev = undistort_points(pair.pts_prev, self.K, self.D)
        pts_curr = undistort_points(pair.pts_curr, self.K, self.D)
        moving = self.motion_prior and self.model == "rs"
        quick = self._turning_first(pts_prev, pts_curr, pair, interval)
        if quick is not None:
            rel, turned = quick
        else:
            rel, turned, early = self._estimate_pair(pts_prev, pts_curr, pair, interval, idx,
                                                     moving)
            if early is not None:
                return early
        return self._chain(pair, interval, rel, turned)

    def _estimate_pair(self, pts_prev: np.ndarray, pts_curr: np.ndarray, pair: TrackedPair,
                       interval: float, idx: int, moving: bool):  # fmt: skip
        """The pair estimator's motion, and the turning camera started from it: ``(rel,
        turned, None)``, or ``(rel, None, PairStep)`` when the pair is held."""
        try:
            rel = estimate_relative_pose(
                pts_prev, pts_curr, self.K, self.line_delay, model=self.model,
                seed=self.seed + idx, mode=self.mode,
                ransac=self.ransac, lm=self.lm,
                rows_prev=pair.rows_prev, rows_curr=pair.rows_curr,
                frame_interval=interval if moving else None,
                predicted=self._predicted_motion(interval) if moving else None,
            )  # fmt: skip
        except ValueError as exc:  # e.g. all tracks collapsed onto one point
            self.hold()
            return None, None, PairStep("held", f"estimation refused the pair: {exc}")
        if not rel.ok:
            self.hold()
            return rel, None, PairStep("held", f"no pose for this pair: {rel.reason}",
                                       num_inliers=rel.num_inliers,
                                       inlier_ratio=rel.inlier_ratio, relative=rel)
        # the middle-row motion in units of |t| (the GS models' reference row is 0: nothing to
        # re-express, whatever the line delay)
        row_mid = float(rel.row_ref)
        R_m, t_m, (w_p, _, w_c, _) = pose_at_row(rel.R, rel.t, rel.w_prev, rel.v_prev,
                                                 rel.w_curr, rel.v_curr, row_mid,
                                                 self.line_delay)  # fmt: skip
        unit = float(np.linalg.norm(t_m))
        if not np.isfinite(unit) or unit < 1e-9:
            self.hold()
            return rel, None, PairStep("held", "no translation between the middle rows",
                                       relative=rel)
        turned = self._turning_camera(pts_prev, pts_curr, pair, row_mid, rel.inliers, R_m, w_p,
                                      w_c, interval)
        if (turned is None and self.uncertain_rotation_deg > 0 and self.model == "rs"
                and _rotation_std_deg(rel) > self.uncertain_rotation_deg):
            # the velocities and the rotation traded off: a turning camera's rotation instead
            # (its direction given that rotation, the scale from the last baseline)
            turned = self._turning_camera(pts_prev, pts_curr, pair, row_mid, rel.inliers, R_m,
                                          w_p, w_c, interval, max_parallax_px=np.inf)
            if (turned is not None and turned.front < UNCERTAIN_MIN_FRONT
                    and self._last_motion is not None):  # fmt: skip
                # its direction leaves many tracks behind a camera: the last pair's direction
                # (constant velocity in the camera's frame) instead
                R_last, t_last, _ = self._last_motion
                centre_last = -R_last.T @ t_last  # its camera in the camera before it
                turned.t = -turned.R @ centre_last
        return rel, turned, None

    def _chain(self, pair: TrackedPair, interval: float, rel: RelativePoseResult,
               turned: _Turn | None) -> PairStep:
        """Chain the pair's middle-row motion (the turning camera's, else the pair
        estimator's) and its row-0 pose."""
        row_mid, tau = float(rel.row_ref), self.line_delay
        w_row0 = None  # the turning camera's row-0 turn rate
        if turned is not None:
            R_m, t_m, par, w_p, w_c = turned.R, turned.t, turned.parallax_px, turned.w_prev, \
                turned.w_curr  # fmt: skip
            w_row0 = row0_turn_rate(R_m, interval, w_p, w_c)
            unit = 1.0
            d_curr = np.full(len(pair.ids), np.nan)  # no depths from no baseline
            scale, scale_note = self._last_baseline, (
                f"rotation of a turning camera ({par:.2f} px of translation parallax), the "
                "last baseline")
            # the current frame's own rate, for the next pair's turning camera to hold: the
            # turn between the middle rows plus half the change of the fitted rates (two views
            # see only that change; the fitted rate itself carries an unseen common part)
            self._last_turn_rate = row0_turn_rate(R_m, interval, w_p, w_c, share=0.5)
        else:
            R_m, t_m, _ = pose_at_row(rel.R, rel.t, rel.w_prev, rel.v_prev, rel.w_curr,
                                      rel.v_curr, row_mid, tau)
            unit = float(np.linalg.norm(t_m))
            d_curr = rel.depths_curr  # in each point's own row camera
            scale, scale_note = self._relative_scale(pair.ids, rel, rel.depths_prev, unit)
            self._last_turn_rate = None
        T_curr_prev = np.eye(4)
        T_curr_prev[:3, :3], T_curr_prev[:3, 3] = R_m, t_m * scale
        M = pose_inverse(T_curr_prev)  # the current middle-row camera in the previous one
        # row 0 is exposed row_mid * tau before the middle row: where the frames' middle-row
        # cameras were at that time, interpolated along the motion between them; a turning
        # camera's rotation is its middle row's turned back at row0_turn_rate instead (with the
        # pair estimator's rates the same made the strongest-shake walks' RPE 1.13-1.17x worse;
        # README)
        lead = row_mid * tau / max(interval, 1e-9)
        T_world_mid = self._T_world_mid
        if T_world_mid is None:  # the first pair: place the previous frame's middle row
            T_world_mid = self.T_world_cam @ pose_inverse(_interpolate(M, -lead))
        T_mid_new = T_world_mid @ M
        T_new = T_world_mid @ _interpolate(M, 1.0 - lead)
        if w_row0 is not None and lead > 0:
            T_new[:3, :3] = T_mid_new[:3, :3] @ so3_exp(-row_mid * tau * w_row0)
        if not (np.isfinite(T_new).all() and np.isfinite(T_mid_new).all()):
            self.hold()
            return PairStep("held", "non-finite chained pose", relative=rel)
        self.T_world_cam = T_new
        self._T_world_mid = T_mid_new
        self._accumulate_covariance(rel, scale)
        depth = d_curr * scale
        good = rel.inliers & np.isfinite(depth) & (depth > 0)
        self._prev_depths = dict(zip(pair.ids[good].tolist(), depth[good].tolist(), strict=True))
        self._last_baseline = scale * unit
        self._last_motion = (R_m, t_m / unit, interval)
        return PairStep("posed", scale_note, num_inliers=rel.num_inliers,
                        inlier_ratio=rel.inlier_ratio, scale=scale, relative=rel)

    # ------------------------------------------------------------------ internals

    def _turning_first(self, pts_prev: np.ndarray, pts_curr: np.ndarray, pair: TrackedPair,
                       interval: float) -> tuple[RelativePoseResult, _Turn] | None:  # fmt: skip
        """After a turning camera's pair, the next pair is first fitted as one, started from
        the last motion (scaled to ``interval``) with the previous frame's own turn rate held
        (``_last_turn_rate``: the turn between the middle rows plus half the change of the
        fitted rates; the last fitted rate itself was worse, README), on all its tracks
        (Cauchy loss): under the parallax limit it is posed so, without the pair
        estimator (a walk's first frames: about a third of the time of a pair estimate); else
        None, and the pair estimator runs as before. Returns the pose as the pair estimator's
        result would carry it (row 0, inliers within 3x the limit; no depths, no
        covariance) and the turning camera."""
        if self._last_turn_rate is None or self._last_motion is None:
            return None
        R_pred, _ = self._predicted_motion(interval)
        row_mid = float(self.K[1, 2]) if self.model == "rs" else 0.0
        w = self._last_turn_rate
        turned = self._turning_camera(pts_prev, pts_curr, pair, row_mid,
                                      np.ones(len(pair.ids), bool), R_pred, w, w, interval)
        if turned is None:
            return None
        limit, tau = self._parallax_limit_px(), self._fit_line_delay()
        R0, t0, (w_p, _, w_c, _) = pose_from_row(turned.R, turned.t, turned.w_prev,
                                                 np.zeros(3), turned.w_curr, np.zeros(3),
                                                 row_mid, tau)  # fmt: skip
        n = len(pair.ids)
        rel = RelativePoseResult(
            True, self.model, R0, t0 / max(float(np.linalg.norm(t0)), 1e-12),
            turned.residual_px <= 3.0 * limit, w_p, np.zeros(3), w_c, np.zeros(3),
            reason="a turning camera's pair: no pair estimate", row_ref=row_mid,
            depths_prev=np.full(n, np.nan), depths_curr=np.full(n, np.nan))  # fmt: skip
        return rel, turned

    def _parallax_limit_px(self) -> float:
        """``rotation_only_parallax_px`` (given at 1000 px focal) at this camera's focal."""
        return self.rotation_only_parallax_px * 0.5 * (self.K[0, 0] + self.K[1, 1]) / 1000.0

    def _fit_line_delay(self) -> float:
        """The line delay of the turning-camera fits: 0 for the GS models (every row at the
        frame's time), whatever the camera's."""
        return self.line_delay if self.model == "rs" else 0.0

    def _turning_camera(self, pts_prev: np.ndarray, pts_curr: np.ndarray, pair: TrackedPair,
                        row_mid: float, inl: np.ndarray, R_m: np.ndarray, w_p: np.ndarray,
                        w_c: np.ndarray, interval: float,
                        max_parallax_px: float | None = None) -> _Turn | None:  # fmt: skip
        """The middle-row motion of a pair with under ``rotation_only_parallax_px`` of
        translation parallax, from a turning camera's fit on the tracks ``inl`` started from
        the middle-row rotation ``R_m`` (``X_curr = R_m X_prev``) and turn rates ``w_p`` (the
        previous frame's, held), ``w_c``; None above it (``max_parallax_px``: another limit,
        px at this camera's focal). The GS models' fit is a global shutter's (every row at the
        frame's time)."""
        focal = 0.5 * (self.K[0, 0] + self.K[1, 1])
        tau = self._fit_line_delay()
        limit = self._parallax_limit_px() if max_parallax_px is None else max_parallax_px
        if limit <= 0 or inl.sum() < 20:
            return None
        f, c = np.array([self.K[0, 0], self.K[1, 1]]), self.K[:2, 2]
        xa, xb = (pts_prev[inl] - c) / f, (pts_curr[inl] - c) / f
        sa = (pair.rows_prev[inl] - row_mid) * tau
        sb = (pair.rows_curr[inl] - row_mid) * tau
        first = FrameState(0, np.eye(3), np.zeros(3), w_p, np.zeros(3))
        robust = 1.5 * focal / 1000.0
        fit = fit_rotation(first, xa, sa, xb, sb, R_m.T, w_c, focal, robust)
        if tau > 0 and (not fit.ok or limit < fit.parallax_px < ACCELERATION_FIT_UP_TO * limit):
            # a strong shake changes the turn rate within a readout: the rows' wobble left by
            # a constant rate is then taken up by its change (only where the constant rate
            # leaves too much: fitted on every pair, the mild walks' ATE got up to 1.46x worse)
            fit = fit_rotation(first, xa, sa, xb, sb, fit.R if fit.ok else R_m.T,
                               fit.w if fit.ok else w_c, focal, robust, acceleration=True)
        if not fit.ok or fit.parallax_px > limit:
            return None
        # the direction with the rows turning at the fitted rates, and at the rotation's own
        # rate over the interval: the fitted rates can take up part of a forward step's
        # expansion (a pitch rate over the rows moves points up and down as the step does;
        # with a 7 ms readout the directions were 100-130 deg off), the constant rate leaves
        # the shake's wobble. The one that puts more tracks in front of the camera is taken
        w_cv = so3_log(fit.R) / max(interval, 1e-9)
        # with translation parallax allowed, a track's residual under the rotation is its
        # parallax, not a sign of an outlier: every inlier votes on the direction
        keep_px = None if np.isfinite(limit) else np.inf
        candidates = [c for c in (
            direction_given_rotation(w_p, xa, sa, fit, xb, sb, robust, focal, keep_px),
            direction_given_rotation(w_cv, xa, sa, dataclasses.replace(fit, w=w_cv,
                                                                       a=np.zeros(3)), xb, sb,
                                     robust, focal, keep_px)) if c is not None]  # fmt: skip
        if not candidates:
            return None
        centre, front = max(candidates, key=lambda c: c[1])
        residual = np.full(len(inl), np.nan)
        residual[inl] = fit.residual_px
        return _Turn(fit.R.T, -fit.R.T @ centre, fit.parallax_px, np.asarray(w_p, float),
                     fit.w, residual, front)

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
        lim = self.max_scale_change
        if not (np.isfinite(measured) and last / lim <= measured <= last * lim):
            return last / unit, f"baseline {measured:.3g} rejected: kept the previous one"
        baseline = float(np.clip(measured, last / MAX_SCALE_STEP, last * MAX_SCALE_STEP))
        if self._baseline_range is not None:
            baseline = float(np.clip(baseline, *self._baseline_range))
        return baseline / unit, ""

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

    def hold(self) -> None:
        """Keep the pose; the uncertainty grows; depths of the skipped pair are unknown."""
        self._last_turn_rate = None
        grow = np.diag([DEFAULT_POSITION_VARIANCE] * 3 + [1e-3] * 3) * HOLD_COVARIANCE_GROWTH
        self.covariance = self.covariance + grow * max(self._last_baseline, 1e-3) ** 2
        self._prev_depths = {}


def _rotation_std_deg(rel: RelativePoseResult) -> float:
    """The pair estimate's rotation std (deg; inf without a usable covariance)."""
    var = float(np.trace(rel.covariance[:3, :3]))
    return float(np.degrees(np.sqrt(var))) if np.isfinite(var) and var >= 0 else np.inf
