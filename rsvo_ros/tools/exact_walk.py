"""The window backend on exact rolling-shutter tracks of a rendered walk: no KLT, no images.

    python -m rsvo_ros.tools.exact_walk --seed 2106 --rate 15 --start 166 --stop 300
    python -m rsvo_ros.tools.exact_walk ... --severity 0          # no shake
    python -m rsvo_ros.tools.exact_walk ... --line-delay 0        # a global shutter
    python -m rsvo_ros.tools.exact_walk ... --readout-fit quadratic
    python -m rsvo_ros.tools.exact_walk ... --readout-fit linear --noise-axes x

Scene points are cast from random pixels of every second frame onto the corridor's surfaces;
each frame sees those its reference-row camera has a free line of sight to, at their exact RS
pixels (the renderer's per-row poses, :func:`~rsvo_ros.sim.synth.project_points`), with
``--noise-px`` Gaussian noise, at most ``--points`` of them, under fixed track ids. The frames go
to :class:`~rsvo_ros.odometry.window.WindowOdometry` as the pipeline would give them. So what
the odometry does here is the estimator's and the window's, not the tracker's.

``--readout-fit quadratic`` replaces each frame's rotation during its readout by its
least-squares quadratic in the row time (what the model's turn rate and angular acceleration
can represent; the positions stay exact): the part a frame's model cannot fit is then gone.
``--readout-fit linear`` replaces the rotation and the position by their least-squares lines
in the row time: each readout is then the paper's constant velocity exactly (no angular
acceleration either). ``--noise-axes x`` (``y``) puts the noise in the columns (rows) only.

Prints one JSON line: the estimate's size against the truth (path length over each
``CHUNK_FRAMES`` frames, estimate / truth) from the first frame the map tracked, its log-slope
per frame, ``scale_change`` (last chunk / first), tracking's residual (median and p90 of each
frame's RMS, px at the image's focal; 0 noise: the model's misfit), and how frames ended.
"""

from __future__ import annotations

import argparse
import collections
import json
import sys

import numpy as np

from rsvo_ros.core.geometry import so3_exp, so3_log
from rsvo_ros.odometry.frame import Observations
from rsvo_ros.odometry.pipeline import PipelineOptions
from rsvo_ros.odometry.window import WindowOdometry
from rsvo_ros.sim.synth import SequenceRenderer, SynthConfig, project_points, resolution_arg
from rsvo_ros.tools.replay import set_window_options, window_option_arg

CHUNK_FRAMES = 10
RAYS_PER_FRAME = 120  # scene points cast from each second frame
SIGHT_TOLERANCE = 0.01  # a point is seen if the first hit on its ray is this close (share)


READOUT_FITS = ("exact", "quadratic", "linear")
NOISE_AXES = {"xy": (1.0, 1.0), "x": (1.0, 0.0), "y": (0.0, 1.0)}


def fitted_readout(row_pose, row_ref: float, tau: float, height: int, fit: str):
    """``row_pose`` with each row's rotation replaced by its least-squares polynomial in the
    row time ``s`` about ``row_ref``: ``quadratic`` (``s``, ``s^2``; positions as they are) or
    ``linear`` (``s``; the position too: the paper's constant velocity within the frame)."""
    if fit not in ("quadratic", "linear"):
        raise ValueError(f"fit {fit!r}: quadratic or linear")
    rows = np.arange(0.0, height + 1.0, 10.0)
    R_rows, p_rows = row_pose(rows)
    R_ref, p_ref = (np.asarray(a)[0] for a in row_pose(np.array([row_ref])))
    s = (rows - row_ref) * tau
    basis = (lambda t: np.column_stack([t, t * t])) if fit == "quadratic" else \
        (lambda t: t[:, None])  # fmt: skip
    logs = np.array([so3_log(R_ref.T @ R) for R in np.asarray(R_rows)])
    coef = np.linalg.lstsq(basis(s), logs, rcond=None)[0]
    if fit == "linear":
        vel = np.linalg.lstsq(s[:, None], np.asarray(p_rows) - p_ref, rcond=None)[0][0]

    def fitted(r, dt=0.0):
        r = np.asarray(r, float)
        sr = (r - row_ref) * tau
        R = np.array([R_ref @ so3_exp(t) for t in basis(sr) @ coef])
        if fit == "linear":
            return R, p_ref + sr[:, None] * vel
        return R, np.asarray(row_pose(r)[1])

    return fitted


def noisy(px: np.ndarray, rng: np.random.Generator, noise_px: float,
          axes: str = "xy") -> np.ndarray:
    """``px`` (n, 2) plus Gaussian noise of std ``noise_px`` in the coordinates ``axes`` names
    (``xy``, ``x``: the columns, ``y``: the rows). The same draws whatever the axes."""
    return px + rng.normal(0.0, noise_px, px.shape) * np.array(NOISE_AXES[axes])


def exact_walk(seed: int, rate: float, start: int, stop: int, width: int = 1280,
               height: int = 720, severity: float = 1.0, line_delay: float | None = None,
               readout_fit: str = "exact", noise_px: float = 0.3, points: int = 500,
               window_options: list[tuple[str, float]] = (),
               noise_axes: str = "xy") -> dict:  # fmt: skip
    if readout_fit not in READOUT_FITS:
        raise ValueError(f"readout_fit {readout_fit!r}: one of {', '.join(READOUT_FITS)}")
    if noise_axes not in NOISE_AXES:
        raise ValueError(f"noise_axes {noise_axes!r}: one of {', '.join(NOISE_AXES)}")
    if not 0 <= start < stop - 2 * CHUNK_FRAMES:
        raise ValueError(f"frames {start}..{stop}: need 0 <= start and at least "
                         f"{2 * CHUNK_FRAMES + 1} frames")
    cfg = SynthConfig(frames=stop, motion="walk", severity=severity, width=width,
                      height=height, seed=seed, frame_rate=rate, line_delay=line_delay)
    renderer = SequenceRenderer(cfg)
    K, scene = renderer.K, renderer.scene
    K_inv = np.linalg.inv(K)
    row_ref = float(K[1, 2])
    rng = np.random.default_rng([seed, 5])
    cast = []
    for k in range(start, stop, 2):
        _, R, p, *_ = renderer.frame_pose(k)
        uv1 = np.column_stack([rng.uniform(0, width, RAYS_PER_FRAME),
                               rng.uniform(0, height, RAYS_PER_FRAME), np.ones(RAYS_PER_FRAME)])
        d = uv1 @ K_inv.T @ np.asarray(R).T
        lam, _ = scene.first_hit(np.asarray(p), d)
        hit = np.isfinite(lam)
        cast.append(np.asarray(p) + lam[hit, None] * d[hit])
    X = np.concatenate(cast)
    order = np.argsort(np.random.default_rng([seed, 6]).random(len(X)))  # who is kept first
    rank = np.empty(len(X), np.int64)
    rank[order] = np.arange(len(X))
    options = PipelineOptions()
    set_window_options(options, list(window_options))
    odometry = WindowOdometry(K, cfg.tau, options.window)
    est, gt, residual = [], [], []
    outcomes: collections.Counter = collections.Counter()
    first_tracked = None
    for k in range(start, stop):
        stamp, R0, p0, _, _, row_pose = renderer.frame_pose(k)
        if readout_fit != "exact":
            row_pose = fitted_readout(row_pose, row_ref, cfg.tau, height, readout_fit)
        px = project_points(X, row_pose, K, height)
        inside = np.isfinite(px).all(1) & (px[:, 0] >= 0) & (px[:, 0] <= width - 1) \
            & (px[:, 1] >= 0) & (px[:, 1] <= height - 1)  # fmt: skip
        idx = np.flatnonzero(inside)
        R_ref, p_ref = (np.asarray(a)[0] for a in row_pose(np.array([row_ref])))
        ray = X[idx] - p_ref
        lam, _ = scene.first_hit(p_ref, ray)
        idx = idx[np.abs(lam - 1.0) < SIGHT_TOLERANCE]  # nothing in between
        idx = idx[np.argsort(rank[idx])[:points]]
        q = noisy(px[idx], rng, noise_px, noise_axes)
        x = (q - K[:2, 2]) / np.diag(K)[:2]
        res = odometry.track(round(stamp * 1e9), Observations(
            idx.astype(np.int64), x, odometry.row_time(q[:, 1]), q, q[:, 1]))  # fmt: skip
        outcomes[f"{res.status}: {res.reason.split(' (')[0] or 'tracked'}"] += 1
        if res.status == "posed" and res.reason == "" and first_tracked is None:
            first_tracked = k
        if res.hessian is not None:
            residual.append(float(np.sqrt(res.sigma2)))
        if res.state is not None and first_tracked is not None:
            est.append(res.state.pose(odometry.row0_time())[:3, 3])
            gt.append(np.asarray(p0).reshape(3))
    out = {"seed": seed, "rate_hz": rate, "frames": [start, stop], "severity": severity,
           "line_delay": cfg.tau, "readout_fit": readout_fit, "noise_px": noise_px,
           "noise_axes": noise_axes,
           "points": len(X), "window_options": dict(window_options),
           "first_tracked": first_tracked, "outcomes": dict(outcomes),
           "residual_px_median": float(np.median(residual)) if residual else None,
           "residual_px_p90": float(np.percentile(residual, 90)) if residual else None,
           "size": [], "size_slope_per_frame": None, "scale_change": None}
    E, G = np.array(est), np.array(gt)
    for i in range(0, len(E) - CHUNK_FRAMES, CHUNK_FRAMES):
        de = np.linalg.norm(np.diff(E[i:i + CHUNK_FRAMES + 1], axis=0), axis=1).sum()
        dg = np.linalg.norm(np.diff(G[i:i + CHUNK_FRAMES + 1], axis=0), axis=1).sum()
        if dg > 0 and de > 0:
            out["size"].append([first_tracked + i, float(de / dg)])
    if len(out["size"]) >= 2:
        at, size = np.array(out["size"]).T
        out["size_slope_per_frame"] = float(np.polyfit(at, np.log(size), 1)[0])
        out["scale_change"] = float(size[-1] / size[0])
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m rsvo_ros.tools.exact_walk", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=2106)
    ap.add_argument("--rate", type=float, default=15.0, help="frames per second of the walk")
    ap.add_argument("--start", type=int, default=166, help="first frame")
    ap.add_argument("--stop", type=int, default=300, help="frame after the last")
    ap.add_argument("--resolution", type=resolution_arg, default=(1280, 720), metavar="WxH",
                    help="image size (default 1280x720)")
    ap.add_argument("--severity", type=float, default=1.0, help="the walk's shake")
    ap.add_argument("--line-delay", type=float, default=None,
                    help="s per row (default: the renderer's, the lesser of 36 ms and a frame "
                         "interval over the height)")
    ap.add_argument("--readout-fit", choices=READOUT_FITS, default="exact",
                    help="each readout as rendered, or its rotation fitted by a quadratic, or "
                         "its rotation and position by lines in the row time (the paper's "
                         "constant velocity exactly)")
    ap.add_argument("--noise-px", type=float, default=0.3, help="Gaussian noise std (px)")
    ap.add_argument("--noise-axes", choices=tuple(NOISE_AXES), default="xy",
                    help="where the noise goes: both coordinates, the columns or the rows")
    ap.add_argument("--points", type=int, default=500, help="tracks per frame at most")
    ap.add_argument("--window-option", type=window_option_arg, action="append", default=[],
                    metavar="NAME=VALUE", help="a numeric WindowOptions field (repeatable)")
    args = ap.parse_args(argv)
    width, height = args.resolution
    if args.rate <= 0 or args.severity < 0 or args.noise_px < 0 or args.points < 20 \
            or (args.line_delay is not None and args.line_delay < 0):  # fmt: skip
        ap.error("--rate must be positive, --points at least 20, the others >= 0")
    try:
        out = exact_walk(args.seed, args.rate, args.start, args.stop, width, height,
                         args.severity, args.line_delay, args.readout_fit, args.noise_px,
                         args.points, args.window_option, args.noise_axes)  # fmt: skip
    except ValueError as exc:
        ap.error(str(exc))
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
