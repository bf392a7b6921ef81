"""The line delay from the video itself (``line_delay: auto``).

The images measure each frame's motion during its readout only as the products ``tau w`` and
``tau v`` (the rolling-shutter distortion); the stamps and the trajectory measure ``w`` and
``v`` as the motion between frames. With the velocities held to the trajectory's, only the
right ``tau`` lets the distortion explain the images. So: while the odometry runs (with a
nominal ``tau0``), the window BA problems it solves are kept (keyframes, observations with
their rows, landmarks); each is re-solved for a grid of candidate line delays (the readout as
a fraction of the frame interval) with every keyframe's velocities tied to the motion between
its neighbouring frames by a tight prior, and the candidate of least total reprojection cost
is the estimate (refined by a parabola; its uncertainty from a bootstrap over the windows).

The keyframe's velocity from the trajectory is the derivative of a cubic spline through the
tracked frames around it (``spline_half_width`` each side): under 8-12 Hz shake sampled at
30 Hz a central difference over the two neighbouring frames keeps only 23-59 % of the velocity
(a larger line delay then fits), the 7-frame spline 50-93 %. Near the ends of the tracked
trajectory, or across a gap, the neighbours' central difference is used. With no rotation or
motion there is nothing to measure, and it says so. A global-shutter camera comes out at (or
next to) zero.

Schedule: a first estimate after ``min_windows`` windows, then a new one every
``reestimate_every`` windows (each window's costs are computed once); "converged" (no more
refining) needs both a bootstrap scatter under ``target_rel_std`` and ``converge_windows``
windows, since the scatter over a few windows says nothing about the bias.

Pure numpy + the compiled window BA, no ROS.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.interpolate import CubicSpline

from rsvo_ros.core.geometry import so3_log
from rsvo_ros.odometry.frame import FrameState
from rsvo_ros.odometry.local_map import WindowProblem, free_columns, solve_window


@dataclass
class LineDelayOptions:
    # candidate readouts (fractions of the frame interval; rsvo_synth's default readout is 1.08
    # of its 30 Hz frame interval); a minimum at the top edge is not trusted
    readout_grid: tuple[float, ...] = tuple(np.round(np.arange(0.0, 1.61, 0.1), 2))
    min_windows: int = 5  # window BA problems before a first estimate
    min_frames: int = 30  # frames before a first estimate
    reestimate_every: int = 4  # new windows between estimates while it is uncertain
    max_windows: int = 80  # windows kept (the newest)
    target_rel_std: float = 0.05  # stop refining below this relative uncertainty ...
    converge_windows: int = 16  # ... with at least this many windows in the estimate
    min_rotation_rad_s: float = 0.05  # median keyframe |w| below this: not enough motion
    prior_w_rad_s: float = 0.02  # the velocities held to the trajectory's (tight)
    prior_v_rel: float = 0.02
    # BA iterations per candidate; with warm_start each candidate's solve starts from the
    # previous (smaller) candidate's solution, else from the window's own state: 4 warm
    # iterations give 10 cold ones' estimate to a median 7e-5 of it (at most 1.2 %) on 62
    # windows' sets in 0.43x the time (README, "The calibrator's re-solves, warm-started")
    iterations: int = 4
    warm_start: bool = True
    # tracked frames each side of a keyframe whose cubic spline gives its velocity (0: the
    # central difference over the two neighbouring frames)
    spline_half_width: int = 3
    bootstrap: int = 200
    seed: int = 0


@dataclass
class LineDelayEstimate:
    """``status``: "collecting" (too little data yet), "estimated", "converged" (uncertainty
    below the target: no more refining), "not observable" (too little motion, or the cost has
    no minimum inside the grid: the given value is kept)."""

    status: str
    line_delay_s: float | None = None
    std_s: float | None = None
    readout_fraction: float | None = None  # of the frame interval
    std_fraction: float | None = None
    readout_s: float | None = None  # line delay x image height
    windows: int = 0
    frames: int = 0
    reason: str = ""
    curve: list[tuple[float, float]] = field(default_factory=list)  # (fraction, cost/window)

    def as_dict(self) -> dict:
        return {"status": self.status, "line_delay_s": self.line_delay_s, "std_s": self.std_s,
                "readout_fraction": self.readout_fraction, "std_fraction": self.std_fraction,
                "readout_s": self.readout_s,
                "windows": self.windows, "frames": self.frames, "reason": self.reason}

    def refined(self, line_delay_s: float, std_s: float) -> LineDelayEstimate:
        """This estimate (with a non-zero line delay) refined to ``line_delay_s`` +- ``std_s``
        (status "refined"): the readout and its fraction of the frame interval scale with
        the line delay; the rest is kept."""
        f = line_delay_s / self.line_delay_s
        return replace(self, status="refined", line_delay_s=line_delay_s, std_s=std_s,
                       readout_s=None if self.readout_s is None else self.readout_s * f,
                       readout_fraction=None if self.readout_fraction is None
                       else self.readout_fraction * f,
                       std_fraction=None if self.readout_fraction is None
                       else self.readout_fraction * std_s / self.line_delay_s)  # fmt: skip


@dataclass
class _Window:
    """A window BA problem with row offsets (from the reference row) instead of row times."""

    problem: WindowProblem
    obs_rows: np.ndarray
    lm_rows: np.ndarray
    w_median: float
    costs: np.ndarray | None = None  # per candidate, once evaluated


class LineDelayCalibrator:
    """Collects the window's BA problems (:meth:`add_window`) and estimates the line delay
    (:meth:`estimate`) for an image of ``height`` rows."""

    def __init__(self, height: int, options: LineDelayOptions | None = None):
        self.height = int(height)
        self.options = options or LineDelayOptions()
        self.windows: list[_Window] = []
        self.frames = 0
        self._since_estimate = 0
        self._grid_interval_s: float | None = None
        # tracked (stamp_ns, R, p) in stamp order; replaced whole when trimmed (the estimate
        # may run on another thread)
        self._poses: list[tuple[int, np.ndarray, np.ndarray]] = []

    def add_frame(self) -> None:
        self.frames += 1

    def snapshot(self) -> LineDelayCalibrator:
        """A copy to estimate on elsewhere (another process: it pickles), with the windows and
        poses collected so far (the lists copied: mapping goes on adding to this one)."""
        out = copy.copy(self)
        out.windows = list(self.windows)
        out._poses = list(self._poses)
        return out

    def restart(self) -> None:
        """Forget the windows and poses (the odometry processes its frames again, with the
        estimate: the new run's windows replace them); the frames counted and the readout
        grid's interval are kept."""
        self.windows = []
        self._poses = []
        self._since_estimate = 0

    def add_pose(self, state: FrameState) -> None:
        """A tracked frame's pose (for the keyframes' velocities from the trajectory)."""
        pose = (state.stamp_ns, state.R.copy(), state.p.copy())
        if self._poses and state.stamp_ns < self._poses[-1][0]:
            self._poses = [pose]  # time went back (a looped bag): a new trajectory
            return
        if self._poses and state.stamp_ns == self._poses[-1][0]:
            return
        self._poses.append(pose)
        if len(self._poses) > 4096:  # keep what the kept windows need, else the newest half
            first = self.windows[0].problem.stamps if self.windows else None
            keep = int(first[0]) - 1_000_000_000 if first is not None else self._poses[-2048][0]
            self._poses = [q for q in self._poses if q[0] >= keep]

    def add_window(self, prob: WindowProblem, row_ref: float) -> bool:
        """Keep a BA problem (its observations' sensor rows, ``row_ref`` the rows' origin of
        the row times). Windows of fewer than three keyframes or fewer than two velocity priors
        are not used."""
        if len(prob.R) < 3 or prob.obs_rows is None:
            return False
        has_prior = prob.prior_p2[:, 0] > 0
        if has_prior.sum() < 2:
            return False
        w_med = float(np.median(np.linalg.norm(prob.prior_mu[has_prior, :3], axis=1)))
        self.windows.append(_Window(prob, prob.obs_rows - row_ref, prob.lm_rows - row_ref,
                                    w_med))  # fmt: skip
        if len(self.windows) > self.options.max_windows:
            self.windows.pop(0)
        self._since_estimate += 1
        return True

    def has_data(self) -> bool:
        """The windows and frames a first estimate needs (``min_windows``, ``min_frames``)."""
        return len(self.windows) >= self.options.min_windows \
            and self.frames >= self.options.min_frames

    def due(self) -> bool:
        """Enough new data for a (new) estimate."""
        o = self.options
        return (self.has_data()
                and self._since_estimate >= (o.min_windows if self._grid_interval_s is None
                                             else o.reestimate_every))  # fmt: skip

    def _trajectory(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The tracked poses as arrays: stamps (N,) ns, R (N, 3, 3), p (N, 3)."""
        poses = list(self._poses)  # replaced whole when trimmed: a consistent snapshot
        if not poses:
            return np.zeros(0, np.int64), np.zeros((0, 3, 3)), np.zeros((0, 3))
        stamps, R, p = zip(*poses, strict=True)
        return np.array(stamps, np.int64), np.array(R), np.array(p)

    def _trajectory_velocities(self, pr: WindowProblem,
                               trajectory: tuple[np.ndarray, np.ndarray, np.ndarray]
                               ) -> np.ndarray:  # fmt: skip
        """(K, 6) the keyframes' ``(w, v)`` from the tracked trajectory (:meth:`_trajectory`):
        the derivative at the keyframe of a cubic spline through the frames around it, in the
        keyframe's frame; the window's own prior (the neighbours' central difference) where the
        trajectory has no frames enough around it or a gap."""
        mu = pr.prior_mu.copy()
        half = self.options.spline_half_width
        stamps, Rs, ps = trajectory
        if half <= 0 or pr.stamps is None or len(stamps) < 2 * half + 1:
            return mu
        interval = float(np.median(np.diff(stamps)))
        for k, stamp in enumerate(pr.stamps):
            i = int(np.searchsorted(stamps, stamp))
            if pr.prior_p2[k, 0] <= 0 or i - half < 0 or i + half >= len(stamps) \
                    or stamps[i] != stamp:  # fmt: skip
                continue
            near = slice(i - half, i + half + 1)
            t = (stamps[near] - stamp) * 1e-9
            if t[-1] - t[0] > (2 * half + 1) * interval * 1e-9:
                continue  # a gap (dropped or lost frames)
            R_k = Rs[i]
            phi = so3_log(R_k.T @ Rs[near])
            w = CubicSpline(t, phi, axis=0)(0.0, 1)
            v = R_k.T @ CubicSpline(t, ps[near] - ps[i], axis=0)(0.0, 1)
            if np.isfinite(w).all() and np.isfinite(v).all():
                mu[k] = np.concatenate([w, v])
        return mu

    def _costs(self, win: _Window, taus: np.ndarray,
               trajectory: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
        o = self.options
        pr = win.problem
        mu = self._trajectory_velocities(pr, trajectory)
        p2 = pr.prior_p2.copy()
        has = p2[:, 0] > 0
        speed = np.linalg.norm(mu[:, 3:], axis=1)
        p2[has, :3] = 1.0 / o.prior_w_rad_s**2
        p2[has, 3:] = 1.0 / np.maximum(o.prior_v_rel * speed[has], 1e-3)[:, None] ** 2
        # the accelerations held at zero (the trajectory's velocities are constant over each
        # readout): a free one would take up part of what the readout's length explains
        held = pr.col < 0
        held[:, 12:] = True
        col, n_cols = free_columns(held)
        out = np.empty(len(taus))
        R, p, rho = pr.R, pr.p, pr.rho  # where each candidate's solve starts
        for i, tau in enumerate(taus):
            q = WindowProblem(
                R, p, mu[:, :3].copy(), mu[:, 3:].copy(), np.zeros_like(pr.acc),
                pr.obs_kf, pr.obs_lm, pr.obs_x, win.obs_rows * tau, pr.lm_anchor, pr.lm_x,
                win.lm_rows * tau, rho, pr.focal, pr.robust_px, mu, p2, 0.0, col,
                n_cols)  # fmt: skip
            sol = solve_window(q, o.iterations)
            out[i] = sol.cost if np.isfinite(sol.cost) else np.inf
            if o.warm_start and np.isfinite(sol.cost):  # the next candidate starts here
                R, p, rho = sol.R, sol.p, sol.rho
        return out

    def estimate(self, frame_interval_s: float) -> LineDelayEstimate:
        """The line delay of least re-solved cost over the kept windows."""
        o = self.options
        self._since_estimate = 0
        windows = list(self.windows)  # mapping may add windows meanwhile (another thread)
        base = LineDelayEstimate("collecting", windows=len(windows), frames=self.frames)
        if len(windows) < o.min_windows or self.frames < o.min_frames:
            base.reason = f"{len(windows)} windows, {self.frames} frames so far"
            return base
        if not np.isfinite(frame_interval_s) or frame_interval_s <= 0:
            base.reason = "no frame interval yet"
            return base
        if self._grid_interval_s is None or abs(frame_interval_s - self._grid_interval_s) \
                > 0.05 * self._grid_interval_s:  # the grid follows the stream's cadence
            self._grid_interval_s = frame_interval_s
            for win in self.windows:
                win.costs = None
        fracs = np.asarray(o.readout_grid, float)
        taus = fracs * self._grid_interval_s / self.height
        trajectory = self._trajectory()  # once for all the windows
        for win in windows:
            if win.costs is None:
                win.costs = self._costs(win, taus, trajectory)
        C = np.array([w.costs for w in windows])
        ok = np.isfinite(C).all(axis=1)
        C = C[ok]
        total = C.sum(axis=0)
        base.curve = [(float(f), float(c / max(len(C), 1))) for f, c in zip(fracs, total,
                                                                            strict=True)]
        w_med = float(np.median([w.w_median for w in windows]))
        if w_med < o.min_rotation_rad_s or len(C) < o.min_windows:
            base.status = "not observable"
            base.reason = (f"too little rotation (median {w_med:.3f} rad/s at the keyframes)"
                           if w_med < o.min_rotation_rad_s else "too few usable windows")
            return base
        f_best, std_f = grid_minimum(fracs, C, o.bootstrap, o.seed)
        if f_best is None:
            base.status = "not observable"
            base.reason = "the cost has no minimum inside the readout grid"
            return base
        scale = self._grid_interval_s / self.height
        base.status = "estimated"
        base.readout_fraction, base.std_fraction = f_best, std_f
        base.line_delay_s, base.std_s = f_best * scale, std_f * scale
        base.readout_s = base.line_delay_s * self.height
        # converged: no more refining. A global shutter (0) too, but like any estimate only
        # over enough windows: an RS camera whose first windows say 0 must not stay at 0
        if len(C) >= o.converge_windows and (f_best == 0.0 or std_f <= o.target_rel_std * f_best):
            base.status = "converged"
        base.reason = f"readout {f_best:.3f} +- {std_f:.3f} frame intervals"
        return base


def grid_minimum(x: np.ndarray, costs: np.ndarray, bootstrap: int,
                 seed: int = 0) -> tuple[float | None, float]:  # fmt: skip
    """The minimum over the even grid ``x`` of the summed cost curves ``costs`` (M, len(x))
    (:func:`parabola_min`; None at the top edge) and its bootstrap std over the M curves (a
    resample whose minimum is at the top edge counts as the top edge)."""
    best = parabola_min(x, costs.sum(axis=0))
    if best is None or bootstrap <= 0:
        return best, float("nan")
    rng = np.random.default_rng(seed)
    boot = []
    for _ in range(bootstrap):
        f = parabola_min(x, costs[rng.integers(0, len(costs), len(costs))].sum(axis=0))
        boot.append(x[-1] if f is None else f)
    return best, float(np.std(boot))


def parabola_min(x: np.ndarray, y: np.ndarray) -> float | None:
    """The minimum of ``y(x)`` on an even grid, refined by a parabola through its neighbours;
    the first grid point when the minimum is there (zero line delay), None at the last one."""
    j = int(np.argmin(y))
    if j == len(x) - 1:
        return None
    if j == 0:
        return float(x[0])
    y0, y1, y2 = y[j - 1], y[j], y[j + 1]
    den = y0 - 2 * y1 + y2
    d = 0.5 * (y0 - y2) / den if den > 0 else 0.0
    return float(x[j] + np.clip(d, -0.5, 0.5) * (x[1] - x[0]))


# ---------------------------------------------------------------------- refining an estimate
#
# The window BA fixes each keyframe's turn rate only relative to the others: all of a window's
# rates shifted together, with its landmarks sheared to match, explain the images almost as
# well (rolling-shutter SfM with one readout direction; docs/notebook.md, "The map's shear").
# Frames tracked against the map inherit that shift. Over a few frames the turn rates during
# the readouts and the turns between the frames' poses measure the same turning, so the
# tracked frames' mean world rate minus their mean turn rate is the map's shift
# (:func:`map_rate_shear`); the window removes it (``WindowOptions.shear_from_turns``).
# Then, with the line delay the odometry runs at, ``tau0 w`` summed over blocks of a few frames
# (what the images measure) against the turn over the same frames gives the line delay
# (:func:`refine_line_delay`). Removing the shift pulls that estimate towards ``tau0`` (through
# the blocks' common part, which ``RefineOptions.intercept`` leaves out; the window's shift
# moves with the window, so some pull stays), so it refines a first estimate (rsvo_calibrate),
# it does not replace it.

MIN_SHEAR_FRAMES = 10


def _world_rates(R: np.ndarray, w: np.ndarray, dt_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The frames' rates in the world (N, 3) and the turn rates between consecutive poses
    (N - 1, 3), over the intervals ``dt_s`` (N - 1,)."""
    U = np.einsum("nij,nj->ni", R, w)
    turns = so3_log(np.einsum("nji,njk->nik", R[:-1], R[1:]))
    return U, np.einsum("nij,nj->ni", R[:-1], turns) / dt_s[:, None]


def map_rate_shear(stamps_ns: np.ndarray, R: np.ndarray, w: np.ndarray) -> np.ndarray | None:
    """(3,) world-frame turn rate the tracked frames (stamps (N,) ns, ``R`` (N, 3, 3) world <-
    camera, ``w`` (N, 3) camera-frame rates) have beyond the turns between their poses; None
    with fewer than ``MIN_SHEAR_FRAMES`` frames or a gap (an interval over 1.6x the median)."""
    stamps_ns = np.asarray(stamps_ns, np.int64)
    if len(stamps_ns) < MIN_SHEAR_FRAMES:
        return None
    dt = np.diff(stamps_ns) * 1e-9
    if not (dt > 0).all() or dt.max() > 1.6 * np.median(dt):
        return None
    U, D = _world_rates(R, w, dt)
    shear = 0.5 * (U[:-1].mean(axis=0) + U[1:].mean(axis=0)) - D.mean(axis=0)
    return shear if np.isfinite(shear).all() else None


@dataclass
class RefinedLineDelay:
    """:func:`refine_line_delay`'s result; ``status`` "refined" or "not observable"."""

    status: str
    line_delay_s: float | None = None
    std_s: float | None = None
    blocks: int = 0
    frames: int = 0
    reason: str = ""

    def as_dict(self) -> dict:
        return {"status": self.status, "line_delay_s": self.line_delay_s, "std_s": self.std_s,
                "blocks": self.blocks, "frames": self.frames, "reason": self.reason}


@dataclass
class RefineOptions:
    block: int = 5  # frames summed per block
    min_blocks: int = 6
    min_rotation_rad_s: float = 0.05  # rms turn rate over the blocks below this: not observable
    bootstrap: int = 200
    seed: int = 0
    # the blocks' mean removed before the regression (a slope with an intercept per axis): the
    # refining pass's window holds the tracked frames' mean world rate to the turns at the line
    # delay it runs with (WindowOptions.shear_from_turns), so the blocks' common part carries
    # that line delay back, not the camera's. On the line-delay table's 33 rolling-shutter bags
    # and 16 fresh ones the estimate after 150 frames came within 10 % on 28 and 14 with it,
    # 26 and 11 without (docs/notebook.md, "The refinement's misses are the frames' rates")
    intercept: bool = True


def refine_line_delay(stamps_ns: np.ndarray, R: np.ndarray, w: np.ndarray,
                      line_delays: np.ndarray,
                      options: RefineOptions | None = None) -> RefinedLineDelay:  # fmt: skip
    """The line delay from tracked frames (as :func:`map_rate_shear`; ``line_delays`` (N,) the
    line delay each frame was tracked with): over blocks of consecutive frames without a gap,
    the world sums of ``line_delay w`` regressed on the sums of the turn rates between the
    poses (through zero, or with ``options.intercept`` after removing the blocks' mean per
    axis); the uncertainty is the bootstrap std over the blocks."""
    o = options or RefineOptions()
    stamps_ns = np.asarray(stamps_ns, np.int64)
    n = len(stamps_ns)
    out = RefinedLineDelay("not observable", frames=n)
    if n < o.block * o.min_blocks + 2:
        out.reason = f"{n} tracked frames, too few for {o.min_blocks} blocks of {o.block}"
        return out
    line_delays = np.asarray(line_delays, float)
    if not (line_delays > 0).any():
        out.reason = "the frames ran with a zero line delay: nothing to refine"
        return out
    dt_ns = np.diff(stamps_ns)
    interval = float(np.median(dt_ns))
    U, D = _world_rates(R, w, dt_ns * 1e-9)
    U = U * line_delays[:, None]
    gap = (dt_ns <= 0) | (dt_ns > 1.5 * interval)
    SU, SD = [], []
    for a in range(1, n - o.block - 1, o.block):
        if gap[a - 1:a + o.block].any():
            continue
        SU.append(U[a:a + o.block].sum(axis=0))
        # the turns around the block's frames: each frame's rate between its two intervals
        SD.append(0.5 * (D[a - 1:a + o.block - 1].sum(axis=0) + D[a:a + o.block].sum(axis=0)))
    out.blocks = len(SU)
    if len(SU) < o.min_blocks:
        out.reason = f"{len(SU)} blocks of {o.block} frames without a gap"
        return out
    SU, SD = np.array(SU), np.array(SD)
    # the turning left to regress on: about the blocks' mean with the intercept
    left = SD - SD.mean(axis=0) if o.intercept else SD
    rms = float(np.sqrt(np.mean(np.sum(left**2, axis=1)))) / o.block
    if not np.isfinite(rms) or rms < o.min_rotation_rad_s:
        out.reason = (f"too little rotation ({rms:.3f} rad/s rms over the blocks"
                      f"{' about their mean' if o.intercept else ''})")
        return out

    def slope(idx: np.ndarray) -> float:
        su, sd = SU[idx], SD[idx]
        if o.intercept:
            su, sd = su - su.mean(axis=0), sd - sd.mean(axis=0)
        den = float(np.sum(sd**2))
        return float(np.sum(su * sd)) / den if den > 0 else float("nan")

    tau = slope(np.arange(len(SU)))
    if not np.isfinite(tau) or tau <= 0:
        out.reason = f"the readouts' turning does not follow the turns (slope {tau:.3g})"
        return out
    rng = np.random.default_rng(o.seed)
    boot = [slope(rng.integers(0, len(SU), len(SU))) for _ in range(o.bootstrap)]
    out.status = "refined"
    out.line_delay_s = tau
    out.std_s = float(np.nanstd(boot)) if boot else float("nan")
    out.reason = (f"{tau * 1e6:.2f} +- {out.std_s * 1e6:.2f} us/row from {len(SU)} blocks of "
                  f"{o.block} frames")
    return out
