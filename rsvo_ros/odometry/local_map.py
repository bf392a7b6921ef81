"""The local map of the window backend: keyframes, anchored inverse-depth landmarks, and the
sliding-window rolling-shutter bundle adjustment over them.

- Landmarks are track ids with an inverse depth ``rho`` along the bearing of their first
  observation in the window, in the camera of that observation's own row (its anchor keyframe
  and row time): ``X = p_a(s_a) + R_a(s_a) (x_a, y_a, 1) / rho``. They are triangulated when a
  keyframe sees a track that an earlier keyframe of the window saw, from the two observations'
  own row cameras.
- The window BA (:meth:`LocalMap.optimize`) refines every keyframe's pose and ``(w, v)`` and
  every landmark's ``rho`` (Cauchy loss, :func:`rsvo_ros.odometry.rs_projection.window_lm`,
  a Schur complement on the inverse depths). Gauge: the oldest ``fixed_keyframes`` poses are
  held (the first fixes position and orientation, the second the scale); their velocities stay
  free. Each keyframe's velocity has a loose prior on the one tracking measured for it.
- Leaving keyframes are dropped (not marginalised): the two oldest of the window are held
  instead, which keeps the gauge and what the dropped ones established. Their landmarks are
  re-anchored in the next keyframe that observed them, or dropped.
- Culling: observations left more than ``outlier_px`` off after the BA are rejected; landmarks
  with no observation besides their anchor are dropped.

Pure numpy + the compiled kernels, no ROS.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from rsvo_ros.odometry import rs_projection
from rsvo_ros.odometry.frame import KeyFrame

ACCELERATION_STD_RAD_S2 = 50.0  # the default prior std of a frame's angular acceleration


@dataclass
class MapOptions:
    window_size: int = 7  # keyframes in the window (issue: 5-10)
    gauge: str = "poses"  # "scale": the oldest pose and one coordinate of the next one (the
    # scale) are held; "poses": the oldest fixed_keyframes poses
    fixed_keyframes: int = 2
    min_parallax_deg: float = 1.0  # a new landmark's rays must meet at least at this angle
    max_triangulation_px: float = 2.0  # reprojection error of a new landmark in both views
    robust_px: float = 1.0  # Cauchy scale of the BA
    outlier_px: float = 3.0  # observations this far off after the BA are rejected
    ba_iterations: int = 10
    # ... or fewer: the BA stops once a step lowers its cost by no more than this fraction.
    # On the 1280x720 walks' windows the cost falls by 2e-5 at the fifth step, 1e-6 at the
    # seventh (medians), and 10 steps were run on 55 of 71 windows with the solver's own
    # 1e-8; stopping at 1e-5 (README, "The window BA stops when it has converged"). 0: until
    # a step gains nothing
    ba_rel_tol: float = 1e-5
    # each keyframe's velocity prior, centred on the motion between its neighbouring frames
    # (RS structure from motion alone is degenerate: under near-constant velocity a sheared
    # scene and wrong velocities explain the images as well; the trajectory tells them apart)
    prior_w_rad_s: float = 0.3  # angular std (rad/s)
    prior_v_rel: float = 0.3  # linear std, relative to the neighbours' speed
    prior_v_floor: float = 0.05  # ... and at least this (map units/s)
    # each frame's angular acceleration during its readout, in tracking and in the window BA
    # (zero-mean prior of this std, rad/s^2; a 10 Hz shake of 1 rad/s). 0: held at zero, the
    # paper's constant velocity within a frame. On 88 synthetic bags the acceleration made
    # every group's per-frame rotation error smaller (0.57-0.88x) and the walks' ATE too
    # (0.58-0.92x), for vehicles' ATE 0.96-1.06x (docs/notebook.md, "Angular acceleration
    # during the readout")
    prior_acc_rad_s2: float = ACCELERATION_STD_RAD_S2


def acc_prior_p2(std_rad_s2: float) -> float:
    """The squared inverse std of the angular accelerations' zero-mean prior; 0 (a std of 0)
    holds them where they are (tracking) and fixes their columns (the window BA)."""
    return 1.0 / std_rad_s2**2 if std_rad_s2 > 0 else 0.0


@dataclass
class Landmark:
    anchor: int  # keyframe id
    x: np.ndarray  # (2,) normalized bearing in the anchor's row camera
    s: float  # the anchor observation's row time
    rho: float  # inverse depth along (x, y, 1)


@dataclass
class BAReport:
    cost: float
    iterations: int
    time_ms: float
    observations: int
    landmarks: int
    rejected: int
    dropped: int


@dataclass
class WindowProblem:
    """One window BA: the keyframes' states (K,), the observations (n,) of landmarks (M,)
    with their anchors, the velocity priors, and the free parameters (``col`` (K, 15): the
    column of each frame parameter, -1 where held)."""

    R: np.ndarray
    p: np.ndarray
    w: np.ndarray
    v: np.ndarray
    acc: np.ndarray  # (K, 3) angular accelerations
    obs_kf: np.ndarray
    obs_lm: np.ndarray
    obs_x: np.ndarray
    obs_s: np.ndarray
    lm_anchor: np.ndarray
    lm_x: np.ndarray
    lm_s: np.ndarray
    rho: np.ndarray
    focal: float
    robust_px: float
    prior_mu: np.ndarray  # (K, 6)
    prior_p2: np.ndarray  # (K, 6) squared inverse stds
    acc_p2: float  # the accelerations' zero-mean prior (squared inverse std)
    col: np.ndarray
    n_cols: int
    lm_ids: list = field(default_factory=list)
    obs_tid: list = field(default_factory=list)
    obs_rows: np.ndarray | None = None  # (n,) sensor rows of the observations
    lm_rows: np.ndarray | None = None  # (M,) sensor rows of the landmarks' anchor observations
    stamps: np.ndarray | None = None  # (K,) the keyframes' stamps (ns)


@dataclass
class WindowSolution:
    R: np.ndarray
    p: np.ndarray
    w: np.ndarray
    v: np.ndarray
    acc: np.ndarray
    rho: np.ndarray
    residuals: np.ndarray  # (n, 2) px
    cost: float
    iterations: int


def solve_window(prob: WindowProblem, iterations: int,
                 rel_tol: float = rs_projection.WINDOW_LM_REL_TOL) -> WindowSolution:
    """The window BA's solver: Levenberg-Marquardt with a Schur complement on the inverse
    depths, compiled (:func:`rsvo_ros.odometry.rs_projection.window_lm`), for ``iterations``
    or until a step lowers the cost by no more than the fraction ``rel_tol``. The README
    compares it with scipy's sparse least squares and GTSAM on the same windows."""
    R, p, w, v, acc, rho, res, cost, it = rs_projection.window_lm(
        prob.R, prob.p, prob.w, prob.v, prob.acc, prob.obs_kf, prob.obs_lm, prob.obs_x,
        prob.obs_s, prob.lm_anchor, prob.lm_x, prob.lm_s, prob.rho, prob.focal, prob.robust_px,
        prob.prior_mu, prob.prior_p2, prob.acc_p2, prob.col, prob.n_cols, iterations,
        rel_tol)  # fmt: skip
    return WindowSolution(R, p, w, v, acc, rho, res, float(cost), int(it))


def free_columns(held: np.ndarray) -> tuple[np.ndarray, int]:
    """The window system's column of each frame parameter (``held`` (K, 15) True: -1), in
    frame-major order, and the number of free ones."""
    col = -np.ones(held.shape, np.int64)
    n_cols = int((~held).sum())
    col[~held] = np.arange(n_cols)
    return col, n_cols


def triangulate(Ra, pa, xa, Rb, pb, xb):
    """Midpoint triangulation of rays ``p + lambda R (x, y, 1)`` of two views, vectorized.

    Returns the depths (n,) along each view's bearing (its z in that camera) and the parallax
    angles (n,) in degrees."""
    ba = np.einsum("nij,nj->ni", Ra, np.column_stack([xa, np.ones(len(xa))]))
    bb = np.einsum("nij,nj->ni", Rb, np.column_stack([xb, np.ones(len(xb))]))
    d = pb - pa
    aa, bb2, ab = (ba * ba).sum(1), (bb * bb).sum(1), (ba * bb).sum(1)
    ad, bd = (ba * d).sum(1), (bb * d).sum(1)
    det = aa * bb2 - ab * ab
    with np.errstate(divide="ignore", invalid="ignore"):
        la = (bb2 * ad - ab * bd) / det
        lb = (ab * ad - aa * bd) / det
        cos = ab / np.sqrt(aa * bb2)
    return la, lb, np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


class LocalMap:
    """Keyframes (oldest first) and the landmarks they share (track id -> :class:`Landmark`)."""

    def __init__(self, focal: float, options: MapOptions | None = None):
        self.focal = float(focal)
        self.options = options or MapOptions()
        self.last_problem: WindowProblem | None = None
        # (3,) world turn rate the keyframes' rates have too much (the map's shear, set by the
        # window before each BA): their priors are centred on their own rates minus it (None:
        # on the neighbours' central difference)
        self.rate_shift: np.ndarray | None = None
        self.keyframes: list[KeyFrame] = []
        self.landmarks: dict[int, Landmark] = {}
        self._index: dict[int, dict[int, int]] = {}  # keyframe id -> track id -> obs index

    # ------------------------------------------------------------------ building

    def add_keyframe(self, kf: KeyFrame) -> int:
        """Insert a keyframe and triangulate the tracks it shares with earlier keyframes of the
        window. Returns the number of new landmarks."""
        self.keyframes.append(kf)
        self._index[kf.id] = {int(i): n for n, i in enumerate(kf.obs.ids)}
        return self._triangulate(kf)

    def _triangulate(self, kf: KeyFrame) -> int:
        o = self.options
        new_ids = [int(i) for i in kf.obs.ids if int(i) not in self.landmarks]
        added = 0
        for older in self.keyframes[:-1]:  # earliest first: the largest baselines
            idx_old = self._index[older.id]
            shared = [i for i in new_ids if i in idx_old and i not in self.landmarks]
            if not shared:
                continue
            ia = np.array([idx_old[i] for i in shared])
            ib = np.array([self._index[kf.id][i] for i in shared])
            Ra, pa = older.state.row_cameras(older.obs.s[ia])
            Rb, pb = kf.state.row_cameras(kf.obs.s[ib])
            xa, xb = older.obs.x[ia], kf.obs.x[ib]
            la, lb, angle = triangulate(Ra, pa, xa, Rb, pb, xb)
            ok = np.isfinite(la) & (la > 0) & (lb > 0) & (angle >= o.min_parallax_deg)
            X = pa + la[:, None] * np.einsum("nij,nj->ni", Ra, np.column_stack(
                [xa, np.ones(len(xa))]))  # fmt: skip
            for R, p, x in ((Ra, pa, xa), (Rb, pb, xb)):
                Xc = np.einsum("nji,nj->ni", R, X - p)
                with np.errstate(divide="ignore", invalid="ignore"):
                    err = self.focal * np.linalg.norm(Xc[:, :2] / Xc[:, 2:] - x, axis=1)
                ok &= (Xc[:, 2] > 0) & (err < o.max_triangulation_px)
            for n in np.flatnonzero(ok):
                self.landmarks[shared[n]] = Landmark(older.id, xa[n].copy(),
                                                     float(older.obs.s[ia[n]]),
                                                     float(1.0 / la[n]))  # fmt: skip
                added += 1
        return added

    def slide(self) -> int:
        """Drop the oldest keyframes beyond the window; re-anchor their landmarks in the next
        keyframe that observed them (else drop them). Returns the landmarks dropped."""
        dropped = 0
        while len(self.keyframes) > self.options.window_size:
            old = self.keyframes[0]
            ids, X = self.points(np.array([i for i, lm in self.landmarks.items()
                                           if lm.anchor == old.id], np.int64))  # fmt: skip
            self.keyframes.pop(0)
            del self._index[old.id]
            moved: dict[int, list[int]] = {}  # new anchor's position -> rows of ids, X
            for n, tid in enumerate(ids.tolist()):
                k = next((k for k, kf in enumerate(self.keyframes)
                          if tid in self._index[kf.id] and tid not in kf.rejected), None)
                if k is None:
                    del self.landmarks[tid]
                    dropped += 1
                else:
                    moved.setdefault(k, []).append(n)
            for k, rows in moved.items():  # vectorized per new anchor (landmark by landmark
                kf = self.keyframes[k]  # it held the GIL 20-50 ms a keyframe at 1280x720)
                at = np.array([self._index[kf.id][int(ids[n])] for n in rows], np.int64)
                R, p = kf.state.row_cameras(kf.obs.s[at])
                depth = np.einsum("nji,nj->ni", R, X[rows] - p)[:, 2]
                for n, j, d in zip(rows, at.tolist(), depth.tolist(), strict=True):
                    tid = int(ids[n])
                    if not d > 0:
                        del self.landmarks[tid]
                        dropped += 1
                        continue
                    self.landmarks[tid] = Landmark(kf.id, kf.obs.x[j].copy(),
                                                   float(kf.obs.s[j]), float(1.0 / d))
        return dropped

    # ------------------------------------------------------------------ queries

    def points(self, ids: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Track ids (M,) and world points (M, 3) of the landmarks (all, or ``ids``)."""
        ids = np.array(sorted(self.landmarks), np.int64) if ids is None else np.asarray(ids)
        if not len(ids):
            return np.zeros(0, np.int64), np.zeros((0, 3))
        kf_pos = {kf.id: k for k, kf in enumerate(self.keyframes)}
        lms = [self.landmarks[int(i)] for i in ids]
        R, p, w, v, acc = self._state_arrays()
        X = rs_projection.landmark_points(
            R, p, w, v, acc, np.array([kf_pos[lm.anchor] for lm in lms], np.int64),
            np.array([lm.x for lm in lms]), np.array([lm.s for lm in lms]),
            np.array([lm.rho for lm in lms]))  # fmt: skip
        return ids, X

    def _state_arrays(self):
        st = [kf.state for kf in self.keyframes]
        return (np.stack([s.R for s in st]), np.stack([s.p for s in st]),
                np.stack([s.w for s in st]), np.stack([s.v for s in st]),
                np.stack([s.a for s in st]))  # fmt: skip

    # ------------------------------------------------------------------ the window BA

    def problem(self) -> WindowProblem | None:
        """The window BA as arrays (None when there is nothing to optimise)."""
        o = self.options
        K = len(self.keyframes)
        lm_ids = list(self.landmarks)
        if K < 2 or not lm_ids:
            return None
        kf_pos = {kf.id: k for k, kf in enumerate(self.keyframes)}
        lm_anchor = np.array([kf_pos[self.landmarks[t].anchor] for t in lm_ids], np.int64)
        # each keyframe's observations of landmarks anchored elsewhere, not rejected there:
        # vectorized (per observation in Python it held the GIL 5 ms a window at 1280x720)
        lm_arr = np.array(lm_ids, np.int64)
        order = np.argsort(lm_arr, kind="stable")
        lm_sorted = lm_arr[order]
        obs_kf, obs_lm, obs_x, obs_s, obs_tid, obs_rows = [], [], [], [], [], []
        for k, kf in enumerate(self.keyframes):
            ids = np.asarray(kf.obs.ids, np.int64)
            at = np.minimum(np.searchsorted(lm_sorted, ids), len(lm_sorted) - 1)
            j = order[at]
            keep = (lm_sorted[at] == ids) & (lm_anchor[j] != k)
            if kf.rejected:
                keep &= ~np.isin(ids, np.fromiter(kf.rejected, np.int64, len(kf.rejected)))
            n = np.flatnonzero(keep)
            obs_kf.append(np.full(len(n), k, np.int64))
            obs_lm.append(j[n])
            obs_x.append(kf.obs.x[n])
            obs_s.append(kf.obs.s[n])
            obs_tid.extend(ids[n].tolist())
            obs_rows.append(kf.obs.rows[n])
        if not obs_tid:
            return None
        held = np.zeros((K, rs_projection.FRAME_PARAMS), bool)
        if o.gauge == "poses":
            held[:min(o.fixed_keyframes, K), :6] = True
        else:  # the first pose, and the second's position along their baseline (the scale)
            held[0, :6] = True
            base = self.keyframes[1].state.p - self.keyframes[0].state.p
            held[1, 3 + int(np.argmax(np.abs(base)))] = True
        if o.prior_acc_rad_s2 <= 0:
            held[:, 12:15] = True  # constant velocity within a frame
        col, n_cols = free_columns(held)  # held poses keep their velocities free
        mu, p2 = np.zeros((K, 6)), np.zeros((K, 6))
        for k, kf in enumerate(self.keyframes):
            prior = kf.trajectory_velocity()
            if prior is None:
                continue
            w_t, v_t = prior
            mu[k] = np.concatenate([w_t, v_t])
            sv = max(o.prior_v_rel * float(np.linalg.norm(v_t)), o.prior_v_floor)
            p2[k] = np.repeat([1.0 / o.prior_w_rad_s**2, 1.0 / sv**2], 3)
        R, p, w, v, acc = self._state_arrays()
        if self.rate_shift is not None:
            has = p2[:, 0] > 0
            own = w - np.einsum("kji,j->ki", R, self.rate_shift)  # R_k^T (R_k w_k - shift)
            mu[has, :3] = own[has]
        anchor_rows = [self.keyframes[k].obs.rows[self._index[self.keyframes[k].id][t]]
                       for k, t in zip(lm_anchor.tolist(), lm_ids, strict=True)]
        return WindowProblem(
            R, p, w, v, acc, np.concatenate(obs_kf), np.concatenate(obs_lm),
            np.concatenate(obs_x).astype(float), np.concatenate(obs_s).astype(float), lm_anchor,
            np.array([self.landmarks[t].x for t in lm_ids]),
            np.array([self.landmarks[t].s for t in lm_ids]),
            np.array([self.landmarks[t].rho for t in lm_ids]), self.focal, o.robust_px, mu, p2,
            acc_prior_p2(o.prior_acc_rad_s2), col, n_cols, lm_ids, obs_tid,
            np.concatenate(obs_rows).astype(float), np.array(anchor_rows, float),
            np.array([kf.state.stamp_ns for kf in self.keyframes], np.int64))  # fmt: skip

    def set_row_times(self, row_time) -> None:
        """Recompute every observation's row time with ``row_time(rows)`` (another line delay),
        and the landmarks' anchor row times with them."""
        for kf in self.keyframes:
            kf.obs.s = row_time(kf.obs.rows)
        by_id = {kf.id: kf for kf in self.keyframes}
        for tid, lm in self.landmarks.items():
            kf = by_id[lm.anchor]
            lm.s = float(kf.obs.s[self._index[kf.id][tid]])

    def optimize(self, iterations: int | None = None) -> BAReport:
        """The window BA (:func:`solve_window`); then rejects outlying observations and drops
        landmarks left with no observation but their anchor."""
        t0 = time.perf_counter()
        prob = self.problem()
        self.last_problem = prob  # read by the line-delay calibration
        if prob is None:
            return BAReport(0.0, 0, 0.0, 0, len(self.landmarks), 0, 0)
        sol = solve_window(prob, iterations or self.options.ba_iterations, self.options.ba_rel_tol)
        for k, kf in enumerate(self.keyframes):
            kf.state.R, kf.state.p = sol.R[k], sol.p[k]
            kf.state.w, kf.state.v, kf.state.a = sol.w[k], sol.v[k], sol.acc[k]
        for j, t in enumerate(prob.lm_ids):
            self.landmarks[t].rho = float(sol.rho[j])
        bad = np.linalg.norm(sol.residuals, axis=1) > self.options.outlier_px
        for k, tid in zip(prob.obs_kf[bad].tolist(), np.array(prob.obs_tid)[bad].tolist(),
                          strict=True):  # fmt: skip
            self.keyframes[k].rejected.add(tid)
        dropped = self._drop_unobserved()
        return BAReport(sol.cost, sol.iterations, (time.perf_counter() - t0) * 1e3,
                        len(prob.obs_kf), len(self.landmarks), int(bad.sum()), dropped)

    def _drop_unobserved(self) -> int:
        count = {t: 0 for t in self.landmarks}
        for kf in self.keyframes:
            for tid in kf.obs.ids.tolist():
                lm = self.landmarks.get(tid)
                if lm is not None and lm.anchor != kf.id and tid not in kf.rejected:
                    count[tid] += 1
        gone = [t for t, c in count.items() if c == 0]
        for t in gone:
            del self.landmarks[t]
        return len(gone)
