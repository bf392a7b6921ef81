"""Real rolling-shutter pairs with global-shutter twins: every model against the twins.

``rsvo_bench --real DIR``. ``DIR`` holds one folder per pair with ``rs_0.png``, ``rs_1.png``
(consecutive rolling-shutter frames) and ``gs_0_m.png``, ``gs_1_m.png`` (each frame's
global-shutter twin at the time of its middle row), as ``data/realdata/bsrsc``.

Per pair:
- the reference motion: OpenCV's USAC_MAGSAC essential matrix + recoverPose on KLT tracks of the
  GS twins: the relative motion of the two frames' middle-row cameras;
- the RS tracks (KLT, forward-backward checked), the same for every method;
- each RS pixel's GS-twin position: KLT from the RS frame into its twin (where that point is at
  the middle row's time); "doing nothing" is the distance between the two;
- every method: OpenCV USAC_MAGSAC + recoverPose, and ours (``gs``, ``mvo``, ``rs`` two-view,
  ``rs`` stream mode with ``frame_interval``); rotation and translation-direction error of the
  middle-row motion against the reference, and the unrolling error: each inlier RS pixel moved
  by the estimated velocities and depth to its frame's middle-row time, against its GS-twin
  position.

K is a guess (``f`` = image width, principal point at the centre); the line delay is
``readout x frame_interval / height`` (the dataset's assumption: readout = frame interval).
``--readout auto`` also reports the readout estimated from the RS tracks alone
(:func:`estimate_readout`) and the unrolling error with it.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from rsvo_ros.core.geometry import angle_between_deg, pose_at_row, rotation_angle_deg, so3_exp
from rsvo_ros.odometry.line_delay import LineDelayOptions, grid_minimum, parabola_min
from rsvo_ros.odometry.tracker import FeatureTracker, TrackerOptions
from rsvo_ros.sim.realistic import HELD_OUT_SEEDS, TUNING_SEEDS, realistic_pair
from rsvo_ros.twoview import LMOptions, estimate_relative_pose
from rsvo_ros.twoview.search import constant_velocity
from rsvo_ros.twoview.solver import cauchy_cost, levenberg_marquardt, residuals
from rsvo_ros.twoview.state import NUM_PARAMS, RSBatch, make_correspondences

PAIR_FILES = ("rs_0.png", "rs_1.png", "gs_0_m.png", "gs_1_m.png")
DEFAULT_FRAME_INTERVAL_S = 1.0 / 30.0  # only the ratio readout / interval matters
DEFAULT_READOUT = 1.0  # readout time in frame intervals (the BS-RSC code's assumption)
MAX_FEATURES = 1000
PYRAMID_LEVELS = 5  # real consecutive frames move by up to ~170 px
MAGSAC_THRESHOLD_PX = 1.0
# label -> (model, stream mode); "opencv" is findEssentialMat(USAC_MAGSAC) + recoverPose
METHODS = {
    "OpenCV USAC_MAGSAC (GS)": ("opencv", False),
    "ours gs": ("gs", False),
    "ours mvo": ("mvo", False),
    "ours rs, two-view": ("rs", False),
    "ours rs, stream": ("rs", True),
}


class RealDataError(Exception):
    """A directory that does not hold real pairs in the expected layout."""


@dataclass
class RealPair:
    name: str
    rs: tuple[np.ndarray, np.ndarray]  # uint8 gray
    gs: tuple[np.ndarray, np.ndarray]

    @property
    def shape(self) -> tuple[int, int]:
        return self.rs[0].shape


def load_pairs(root: Path) -> list[RealPair]:
    """Every folder of ``root`` that holds the four images; RealDataError if none does or an
    image cannot be read or sizes differ."""
    root = Path(root)
    if not root.is_dir():
        raise RealDataError(f"{root} is not a directory")
    pairs = []
    for folder in sorted(p for p in root.iterdir() if p.is_dir()):
        if not all((folder / f).exists() for f in PAIR_FILES):
            continue
        imgs = []
        for f in PAIR_FILES:
            img = cv2.imread(str(folder / f), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise RealDataError(f"cannot read {folder / f}")
            imgs.append(img)
        if len({im.shape for im in imgs}) != 1:
            raise RealDataError(f"{folder}: the four images differ in size")
        pairs.append(RealPair(folder.name, (imgs[0], imgs[1]), (imgs[2], imgs[3])))
    if not pairs:
        raise RealDataError(f"no pair folders with {', '.join(PAIR_FILES)} in {root}")
    return pairs


def intrinsics_guess(width: int, height: int, focal: float | None = None) -> np.ndarray:
    """K with ``f`` = ``focal`` (default: the image width), principal point at the centre."""
    f = float(width if focal is None else focal)
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0, 0, 1.0]])


def _klt(img_a: np.ndarray, img_b: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """KLT of (N, 2) ``pts`` from ``img_a`` into ``img_b`` with a forward-backward check:
    positions (N, 2) and a mask (N,)."""
    o = TrackerOptions()
    lk = dict(winSize=(o.window_px, o.window_px), maxLevel=PYRAMID_LEVELS,
              criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    p0 = np.asarray(pts, np.float32).reshape(-1, 1, 2)
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(img_a, img_b, p0, None, **lk)
    p0b, st2, _ = cv2.calcOpticalFlowPyrLK(img_b, img_a, p1, None, **lk)
    fb = np.linalg.norm((p0b - p0).reshape(-1, 2), axis=1)
    ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < o.fb_threshold_px)
    return p1.reshape(-1, 2).astype(float), ok


def _tracks(img_a: np.ndarray, img_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pipeline's tracker (bucketed corners, KLT, forward-backward) from a to b, with
    enough pyramid levels for real frame-to-frame motion."""
    tracker = FeatureTracker(TrackerOptions(max_features=MAX_FEATURES,
                                            pyramid_levels=PYRAMID_LEVELS))
    tracker.track(img_a)
    pair = tracker.track(img_b)
    return pair.pts_prev, pair.pts_curr


def opencv_magsac(pts_prev: np.ndarray, pts_curr: np.ndarray, K: np.ndarray,
                  seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """``findEssentialMat(USAC_MAGSAC)`` + ``recoverPose``: R, unit t, inlier mask."""
    cv2.setRNGSeed(seed)
    E, mask = cv2.findEssentialMat(pts_prev, pts_curr, K, method=cv2.USAC_MAGSAC, prob=0.999,
                                   threshold=MAGSAC_THRESHOLD_PX)
    if E is None or E.shape[0] < 3:
        return np.eye(3), np.zeros(3), np.zeros(len(pts_prev), bool)
    _, R, t, _ = cv2.recoverPose(E[:3], pts_prev, pts_curr, K, mask=mask.copy())
    return R, t.ravel() / np.linalg.norm(t), mask.ravel().astype(bool)


@dataclass
class PairTracks:
    """What every method of one pair shares."""

    name: str
    K: np.ndarray
    pts: tuple[np.ndarray, np.ndarray]  # RS tracks (N, 2) in frames 0 and 1
    twin: tuple[np.ndarray, np.ndarray]  # (N, 2) GS-twin positions, nan where KLT failed
    R_ref: np.ndarray  # middle-row motion from the GS twins: X_1 = R X_0 + t
    t_ref: np.ndarray
    ref_inlier_ratio: float
    ref_tracks: int
    rows: tuple[np.ndarray, np.ndarray] | None = None  # sensor rows when pts are undistorted


def prepare(pair: RealPair, focal: float | None = None) -> PairTracks:
    """Tracks, GS-twin positions and the reference motion of one pair."""
    h, w = pair.shape
    K = intrinsics_guess(w, h, focal)
    g0, g1 = _tracks(*pair.gs)
    R_ref, t_ref, ref_mask = opencv_magsac(g0, g1, K)
    p0, p1 = _tracks(*pair.rs)
    twins = []
    for k, pts in enumerate((p0, p1)):
        q, ok = _klt(pair.rs[k], pair.gs[k], pts)
        q[~ok] = np.nan
        twins.append(q)
    return PairTracks(pair.name, K, (p0, p1), (twins[0], twins[1]), R_ref, t_ref,
                      float(ref_mask.mean()) if len(ref_mask) else 0.0, len(g0))


def realistic_tracks(seed: int, readout: float = DEFAULT_READOUT) -> PairTracks:
    """A :mod:`rsvo_ros.sim.realistic` pair as :class:`PairTracks` (exact reference)."""
    pair = realistic_pair(seed, readout)
    return PairTracks(f"seed {seed} ({pair.motion})", pair.K, (pair.pts_prev, pair.pts_curr),
                      (pair.twin_prev, pair.twin_curr), pair.R_mid, pair.t_mid, 1.0, 0,
                      (pair.rows_prev, pair.rows_curr))


def unroll(pts: np.ndarray, depths: np.ndarray, w: np.ndarray, v: np.ndarray, K: np.ndarray,
           line_delay: float, row_to: float, rows: np.ndarray | None = None) -> np.ndarray:
    """Where RS pixels (N, 2) would be seen by the same frame's camera at row ``row_to``.

    Convention (CONTRACTS.md): ``X_row0 = Exp(r tau w) X_row_r + r tau v``; each point is
    ``depth * K^-1 [u, v, 1]`` in the camera of its own (sensor) row ``r`` (``rows``, default
    ``pts[:, 1]``; depths and ``v`` in the same unit). Returns (N, 2) pixels, nan where the
    depth is not positive.
    """
    x = np.column_stack([pts, np.ones(len(pts))]) @ np.linalg.inv(K).T
    X_r = x * depths[:, None]
    s = (pts[:, 1] if rows is None else rows) * line_delay
    X_0 = np.einsum("nij,nj->ni", so3_exp(s[:, None] * w), X_r) + s[:, None] * v
    s_to = row_to * line_delay
    X_to = (X_0 - s_to * v) @ so3_exp(s_to * w)  # Exp(s w)^T (X_0 - s v), row vectors
    with np.errstate(invalid="ignore", divide="ignore"):
        uv = X_to @ K.T
        out = uv[:, :2] / uv[:, 2:]
    out[~(depths > 0) | ~(X_to[:, 2] > 0)] = np.nan
    return out


@dataclass
class MethodResult:
    pair: str
    method: str
    ok: bool
    rot_err_deg: float = float("nan")
    dir_err_deg: float = float("nan")
    inlier_ratio: float = 0.0
    unroll_px: list[float] = field(default_factory=list)  # per point: estimate vs twin
    nothing_px: list[float] = field(default_factory=list)  # per point: RS pixel vs twin
    time_ms: float = 0.0
    reason: str = ""


def evaluate_pair(tracks: PairTracks, readout: float = DEFAULT_READOUT,
                  frame_interval: float = DEFAULT_FRAME_INTERVAL_S, seed: int = 0,
                  methods: tuple[str, ...] = tuple(METHODS)) -> list[MethodResult]:  # fmt: skip
    """Each of ``methods`` (default: every one of :data:`METHODS`) on one pair."""
    p0, p1 = tracks.pts
    r0, r1 = tracks.rows if tracks.rows is not None else (p0[:, 1], p1[:, 1])
    K = tracks.K
    height = 2.0 * K[1, 2] + 1.0
    tau = readout * frame_interval / height
    row_mid = (height - 1.0) / 2.0
    out = []
    for label in methods:
        model, stream = METHODS[label]
        t0 = time.perf_counter()
        if model == "opencv":
            R, t, mask = opencv_magsac(p0, p1, K, seed)
            dt_ms = (time.perf_counter() - t0) * 1e3
            ok = np.linalg.norm(t) > 0
            res = MethodResult(tracks.name, label, bool(ok), inlier_ratio=float(mask.mean()),
                               time_ms=dt_ms)  # fmt: skip
            if ok:
                res.rot_err_deg = float(rotation_angle_deg(tracks.R_ref @ R.T))
                res.dir_err_deg = angle_between_deg(tracks.t_ref, t)
            out.append(res)
            continue
        est = estimate_relative_pose(p0, p1, K, tau if model == "rs" else 0.0, model=model,
                                     seed=seed, rows_prev=r0, rows_curr=r1,
                                     frame_interval=frame_interval if stream else None)
        res = MethodResult(tracks.name, label, est.ok, inlier_ratio=est.inlier_ratio,
                           time_ms=est.time_s * 1e3, reason=est.reason)  # fmt: skip
        if est.ok:
            line = tau if model == "rs" else 0.0
            R_m, t_m, _ = pose_at_row(est.R, est.t, est.w_prev, est.v_prev, est.w_curr,
                                      est.v_curr, row_mid, line)
            res.rot_err_deg = float(rotation_angle_deg(tracks.R_ref @ R_m.T))
            res.dir_err_deg = angle_between_deg(tracks.t_ref, t_m)
            for pts, rows, twin, depth, w, v in (
                    (p0, r0, tracks.twin[0], est.depths_prev, est.w_prev, est.v_prev),
                    (p1, r1, tracks.twin[1], est.depths_curr, est.w_curr, est.v_curr)):
                moved = unroll(pts, depth, w, v, K, line, row_mid, rows)
                use = est.inliers & np.isfinite(twin).all(1) & np.isfinite(moved).all(1)
                res.unroll_px += np.linalg.norm(moved[use] - twin[use], axis=1).tolist()
                res.nothing_px += np.linalg.norm(pts[use] - twin[use], axis=1).tolist()
        out.append(res)
    return out


def summarize(results: list[MethodResult]) -> dict:
    """Per method over all pairs: rotation error mean, direction error median, and the pooled
    unrolling and doing-nothing medians (px)."""
    summary = {}
    for label in METHODS:
        rs = [r for r in results if r.method == label]
        rot = [r.rot_err_deg for r in rs if r.ok]
        dirs = [r.dir_err_deg for r in rs if r.ok]
        un = np.concatenate([r.unroll_px for r in rs]) if rs else np.zeros(0)
        no = np.concatenate([r.nothing_px for r in rs]) if rs else np.zeros(0)
        summary[label] = {
            "pairs": len(rs), "failed": sum(not r.ok for r in rs),
            "rot_err_deg_mean": float(np.mean(rot)) if rot else None,
            "rot_err_deg_max": float(np.max(rot)) if rot else None,
            "dir_err_deg_median": float(np.median(dirs)) if dirs else None,
            "dir_err_deg_max": float(np.max(dirs)) if dirs else None,
            "unroll_px_median": float(np.median(un)) if len(un) else None,
            "nothing_px_median": float(np.median(no)) if len(no) else None,
            "time_ms_median": float(np.median([r.time_ms for r in rs])) if rs else None,
        }  # fmt: skip
    return summary


@dataclass
class ReadoutEstimate:
    """The readout (frame intervals) estimated from the RS tracks of several pairs alone.

    ``status``: "estimated", or "not observable" (the pooled cost has no minimum inside the
    grid, or the pairs disagree: bootstrap std over the pairs above :data:`MAX_READOUT_STD`)."""

    status: str
    readout: float | None
    std: float
    per_pair: dict[str, float | None]  # each pair's own minimum
    curve: list[tuple[float, float]]  # (readout, mean cost per point, px^2) pooled
    reason: str = ""


MAX_READOUT_STD = 0.25  # frame intervals: pairs that scatter more than this do not agree


def readout_curve(tracks: PairTracks, grid: np.ndarray, frame_interval: float,
                  robust_scale: float | None = None, rounds: int = 6) -> np.ndarray:  # fmt: skip
    """Mean Cauchy cost per point (px^2) of the pair's constant-velocity fit for each readout
    of ``grid`` (frame intervals): the pose (5 DOF, from OpenCV's USAC_MAGSAC) refined with
    both frames' velocities held to the motion between the frames over ``frame_interval``
    (re-centred ``rounds`` times). The RS distortion is then fixed by the readout alone, as in
    the line-delay calibration of a video (:mod:`rsvo_ros.odometry.line_delay`); only the
    ratio readout / interval matters."""
    p0, p1 = tracks.pts
    rows = tracks.rows if tracks.rows is not None else (None, None)
    K = tracks.K
    height = 2.0 * K[1, 2] + 1.0
    scale = robust_scale or LMOptions().robust_scale_px
    R, t, _ = opencv_magsac(p0, p1, K)
    if not np.linalg.norm(t) > 0:
        return np.full(len(grid), np.nan)
    out = []
    for f in grid:
        corr = make_correspondences(p0, p1, K, f * frame_interval / height, K[1, 2], *rows)
        state = RSBatch.from_pose(R, t)
        for _ in range(rounds):
            state.vel = constant_velocity(state, frame_interval)
            state, _, _ = levenberg_marquardt(state, corr, 10, robust_scale=scale,
                                              basis=np.eye(NUM_PARAMS)[:, :5])
        state.vel = constant_velocity(state, frame_interval)
        out.append(float(cauchy_cost(residuals(state, corr), scale)[0]) / len(p0))
    return np.array(out)


def estimate_readout(tracks: list[PairTracks],
                     frame_interval: float = DEFAULT_FRAME_INTERVAL_S,
                     grid: tuple[float, ...] | None = None, bootstrap: int = 200,
                     seed: int = 0) -> ReadoutEstimate:  # fmt: skip
    """The readout of least pooled :func:`readout_curve` cost over the pairs (a parabola
    through the grid's minimum; the bootstrap over the pairs gives its std). The candidates are
    the line-delay calibration's (``LineDelayOptions.readout_grid``).

    A diagnostic, not a calibration: with the same velocity in both frames their distortions
    nearly cancel in the relative pose, so the cost is flat to a few per cent over the grid,
    and on the realistic pairs (rendered with readout 1.0) the pooled minimum is near 0
    (README). The video calibration (``line_delay: auto``) has many frames whose velocities
    differ."""
    x = np.asarray(grid or LineDelayOptions().readout_grid, float)
    curves = [readout_curve(tr, x, frame_interval) for tr in tracks]
    ok = [i for i, c in enumerate(curves) if np.isfinite(c).all()]
    per_pair = {tracks[i].name: parabola_min(x, curves[i]) for i in ok}
    if not ok:
        return ReadoutEstimate("not observable", None, float("nan"), per_pair, [],
                               "no pair has a GS pose to start from")
    C = np.array([curves[i] for i in ok])
    curve = [(float(f), float(c)) for f, c in zip(x, C.mean(axis=0), strict=True)]
    best, std = grid_minimum(x, C, bootstrap, seed)
    if best is None:
        return ReadoutEstimate("not observable", None, std, per_pair, curve,
                               "the pooled cost has no minimum inside the readout grid")
    if len(ok) < 2 or not std <= MAX_READOUT_STD:
        return ReadoutEstimate("not observable", best, std, per_pair, curve,
                               f"the pairs disagree: {best:.2f} +- {std:.2f} frame intervals "
                               f"over {len(ok)} pair(s)")
    return ReadoutEstimate("estimated", best, std, per_pair, curve,
                           f"{best:.2f} +- {std:.2f} frame intervals over {len(ok)} pairs")


def _f(x, spec=".3f"):
    return "-" if x is None else format(x, spec)


def format_tables(results: list[MethodResult], summary: dict) -> str:
    lines = ["| method | rotation error, mean (deg) | direction error, median (deg) | "
             "RS pixel to its GS-twin position, median (px) | time, median (ms) |",
             "|---|---|---|---|---|"]
    for label, s in summary.items():
        unroll = "-" if s["unroll_px_median"] is None else (
            f"{s['unroll_px_median']:.2f} (doing nothing {s['nothing_px_median']:.2f})")
        lines.append(f"| {label} | {_f(s['rot_err_deg_mean'])} | "
                     f"{_f(s['dir_err_deg_median'], '.2f')} | {unroll} | "
                     f"{_f(s['time_ms_median'], '.1f')} |")
    lines += ["", "| pair | method | rotation (deg) | direction (deg) | inliers | "
              "unrolled / doing nothing (px) |", "|---|---|---|---|---|---|"]
    for r in results:
        un = "-" if not r.unroll_px else (f"{np.median(r.unroll_px):.2f} / "
                                          f"{np.median(r.nothing_px):.2f}")
        state = "" if r.ok else f" (no pose: {r.reason})"
        lines.append(f"| {r.pair} | {r.method}{state} | {_f(r.rot_err_deg)} | "
                     f"{_f(r.dir_err_deg, '.2f')} | {100 * r.inlier_ratio:.0f} % | {un} |")
    return "\n".join(lines)


def plot(path: Path, pairs: list[RealPair], tracks: list[PairTracks], readout: float,
         frame_interval: float, method: str = "ours rs, stream", seed: int = 0,
         magnify: float = 4.0) -> None:  # fmt: skip
    """One row per pair: the RS frame with, per tracked point, the displacement to its GS-twin
    position (green: what the RS exposure did) and what is left after unrolling with the
    estimated velocities (red), both ``magnify`` times longer; and the GS twin."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    model, stream = METHODS[method]
    fig, axes = plt.subplots(len(pairs), 2, figsize=(12, 4.3 * len(pairs)), squeeze=False)
    for row, (pair, tr) in enumerate(zip(pairs, tracks, strict=True)):
        p0 = tr.pts[0]
        h = pair.shape[0]
        tau = readout * frame_interval / h
        est = estimate_relative_pose(tr.pts[0], tr.pts[1], tr.K, tau, model=model, seed=seed,
                                     frame_interval=frame_interval if stream else None)
        ax = axes[row, 0]
        ax.imshow(pair.rs[0], cmap="gray")
        twin = tr.twin[0]
        good = np.isfinite(twin).all(1)
        d_true = twin - p0
        ax.quiver(p0[good, 0], p0[good, 1], magnify * d_true[good, 0],
                  magnify * d_true[good, 1], color="lime", angles="xy", scale_units="xy",
                  scale=1, width=0.0025, label="RS pixel -> GS twin")
        title = f"{pair.name}: RS frame 0"
        if est.ok:
            moved = unroll(p0, est.depths_prev, est.w_prev, est.v_prev, tr.K, tau, (h - 1) / 2)
            use = good & est.inliers & np.isfinite(moved).all(1)
            left = twin - moved
            ax.quiver(p0[use, 0], p0[use, 1], magnify * left[use, 0], magnify * left[use, 1],
                      color="red", angles="xy", scale_units="xy", scale=1, width=0.0025,
                      label=f"left after unrolling ({method})")
            title += (f"; median {np.median(np.linalg.norm(d_true[use], axis=1)):.1f} px -> "
                      f"{np.median(np.linalg.norm(left[use], axis=1)):.1f} px")
        ax.set_title(title + f" (arrows x{magnify:g})", fontsize=9)
        ax.legend(loc="lower left", fontsize=7)
        ax.axis("off")
        axes[row, 1].imshow(pair.gs[0], cmap="gray")
        axes[row, 1].set_title(f"{pair.name}: GS twin of frame 0 (middle-row time)", fontsize=9)
        axes[row, 1].axis("off")
    fig.suptitle(f"real RS pairs: readout {readout:g} frame interval(s)", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def _auto_report(est: ReadoutEstimate, tracks: list[PairTracks], assumed: float,
                 assumed_results: list[MethodResult], frame_interval: float,
                 seed: int) -> dict:  # fmt: skip
    """The estimate, and the stream mode's unrolling (pooled median, px) with it and with the
    assumed readout (from ``assumed_results``, the evaluation at ``assumed``)."""
    method = "ours rs, stream"

    def pooled(results: list[MethodResult], field: str) -> float:
        return float(np.median(sum((getattr(r, field) for r in results
                                    if r.method == method), [])))

    out = asdict(est) | {"assumed_readout": assumed,
                         "unroll_px_median_assumed": pooled(assumed_results, "unroll_px"),
                         "nothing_px_median": pooled(assumed_results, "nothing_px"),
                         "unroll_px_median_estimate": None}
    if est.readout is not None:
        res = [r for tr in tracks
               for r in evaluate_pair(tr, est.readout, frame_interval, seed, (method,))]
        out["unroll_px_median_estimate"] = pooled(res, "unroll_px")
    return out


def run(root: Path, output: Path, readout: float | str = DEFAULT_READOUT,
        frame_interval: float = DEFAULT_FRAME_INTERVAL_S, focal: float | None = None,
        seed: int = 0, draw: bool = True) -> dict:  # fmt: skip
    """Evaluate every pair of ``root``; writes ``real.json`` (and ``real_pairs.png``) into
    ``output`` and returns the report. ``readout="auto"``: also estimated from the RS tracks
    alone (:func:`estimate_readout`); ``report["readout_auto"]`` holds the estimate and the
    stream mode's unrolling error with it and with the assumed :data:`DEFAULT_READOUT`, which
    the evaluation keeps (two frames barely observe the readout: see
    :func:`estimate_readout`)."""
    auto = readout == "auto"
    if not auto and not (isinstance(readout, (int, float)) and np.isfinite(readout)
                         and readout >= 0):  # fmt: skip
        raise ValueError(f"readout must be 'auto' or finite and >= 0 frame intervals, got "
                         f"{readout!r}")
    if not (np.isfinite(frame_interval) and frame_interval > 0):
        raise ValueError(f"frame interval must be > 0 s, got {frame_interval}")
    pairs = load_pairs(root)
    tracks = [prepare(p, focal) for p in pairs]
    readout = DEFAULT_READOUT if auto else readout
    results = [r for tr in tracks for r in evaluate_pair(tr, readout, frame_interval, seed)]
    auto_report = None
    if auto:
        est = estimate_readout(tracks, frame_interval, seed=seed)
        auto_report = _auto_report(est, tracks, readout, results, frame_interval, seed)
    summary = summarize(results)
    report = {
        "root": str(root), "readout_frame_intervals": readout, "readout_auto": auto_report,
        "frame_interval_s": frame_interval, "focal_px": focal, "seed": seed,
        "pairs": [{"name": t.name, "tracks": len(t.pts[0]), "ref_tracks": t.ref_tracks,
                   "ref_inlier_ratio": t.ref_inlier_ratio,
                   "ref_rotation_deg": float(rotation_angle_deg(t.R_ref)),
                   "ref_t": t.t_ref.tolist()} for t in tracks],
        "summary": summary,
        "results": [{k: v for k, v in asdict(r).items() if k not in ("unroll_px", "nothing_px")}
                    | {"unroll_px_median": float(np.median(r.unroll_px)) if r.unroll_px
                       else None,
                       "nothing_px_median": float(np.median(r.nothing_px)) if r.nothing_px
                       else None} for r in results],
        "table": format_tables(results, summary),
    }  # fmt: skip
    output.mkdir(parents=True, exist_ok=True)
    import json

    with open(output / "real.json", "w") as f:
        json.dump(report, f, indent=1)
    if draw:
        plot(output / "real_pairs.png", pairs, tracks, readout, frame_interval, seed=seed)
    return report


def run_realistic(output: Path, count: int | None = None, seed: int = 0,
                  readout: float | str = DEFAULT_READOUT) -> dict:  # fmt: skip
    """Every method on the realistic synthetic pairs: the tuning seeds and the held-out seeds,
    summarized separately; writes ``realistic.json`` into ``output``. ``readout="auto"``: the
    pairs are rendered with :data:`DEFAULT_READOUT` and each group also reports the readout
    estimated from its RS tracks (:func:`estimate_readout`) against it."""
    import json

    groups = {"tuning": list(TUNING_SEEDS), "held-out": list(HELD_OUT_SEEDS)}
    auto = readout == "auto"
    readout = DEFAULT_READOUT if auto else readout  # the truth the pairs are rendered with
    report = {"readout_frame_intervals": readout, "groups": {}}
    for name, seeds in groups.items():
        seeds = seeds[:count] if count else seeds
        tracks = [realistic_tracks(s, readout) for s in seeds]
        results = [r for tr in tracks for r in evaluate_pair(tr, readout, seed=seed)]
        summary = summarize(results)
        report["groups"][name] = {"seeds": [seeds[0], seeds[-1]], "summary": summary,
                                  "table": format_tables(results, summary).split("\n\n")[0]}
        if auto:  # the estimate from the RS tracks alone, against the rendered readout
            report["groups"][name]["readout_auto"] = _auto_report(
                estimate_readout(tracks, seed=seed), tracks, readout, results,
                DEFAULT_FRAME_INTERVAL_S, seed)
    output.mkdir(parents=True, exist_ok=True)
    with open(output / "realistic.json", "w") as f:
        json.dump(report, f, indent=1)
    return report
