"""What a per-frame turn rate can reach on hand-held walks: each frame tracked against perfect
landmarks (the renderer's exact RS projections of random scene points, Gaussian pixel noise),
its turn rate compared with the ground truth's.

    python -m rsvo_ros.tools.velocity_floor [--severity 0.5 1 2] [--noise-px 0.3]

For each ``rsvo_synth --motion walk`` severity (640x360, 36 ms readout, seed 0), frames 5-85:
- how far the mean turn rate over the readout (what one constant ``w`` per frame can
  represent) is from the instantaneous row-0 rate (the bag's ground truth, which
  ``summary.json``'s keyframe error is measured against);
- the tracked ``w`` (no velocity prior) against that mean, with the paper's constant velocity
  within a frame and with an angular acceleration during the readout (prior std
  ``ACCELERATION_STD_RAD_S2``, as ``rsvo_replay --angular-acceleration``);
- the tracked row-0 rate (``w + s0 a``, what ``summary.json`` and the Odometry twist report)
  against the instantaneous row-0 rate;
- the row-0 rotation error of the tracked frame.
Medians over the frames, relative to the reference's ``|w|``. Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from rsvo_ros.core.geometry import so3_exp, so3_log
from rsvo_ros.odometry import rs_projection
from rsvo_ros.odometry.local_map import ACCELERATION_STD_RAD_S2
from rsvo_ros.sim.synth import SequenceRenderer, SynthConfig

POINTS = 300
DEPTH_M = (2.0, 8.0)


def frame_errors(renderer: SequenceRenderer, k: int, rng: np.random.Generator,
                 noise_px: float, acc_std: float) -> tuple[float, ...]:
    """For frame ``k``: (readout mean vs instantaneous row-0 rate, tracked w vs readout mean,
    row-0 rotation error in deg, tracked row-0 rate ``w + s0 a`` vs the instantaneous row-0
    rate) of a frame tracked against perfect landmarks."""
    cfg, K = renderer.config, renderer.K
    f, row_ref, tau, H = K[0, 0], K[1, 2], cfg.tau, cfg.height
    _, R0, _, w0, _, row_pose = renderer.frame_pose(k)
    Rm, pm = (a[0] for a in row_pose(np.array([row_ref])))
    uv = np.column_stack([rng.uniform(0, cfg.width, POINTS), rng.uniform(0, H, POINTS)])
    depth = rng.uniform(*DEPTH_M, POINTS)
    X = (np.column_stack([(uv - K[:2, 2]) / f, np.ones(POINTS)]) * depth[:, None]) @ Rm.T + pm
    rows = np.full(POINTS, row_ref)
    for _ in range(8):  # each point at the row that sees it
        Rr, pr = row_pose(rows)
        c = np.einsum("nji,nj->ni", Rr, X - pr)
        rows = K[1, 1] * c[:, 1] / c[:, 2] + row_ref
    seen = (rows >= 0) & (rows <= H - 1)
    x = c[:, :2] / c[:, 2:] + rng.normal(0.0, noise_px / f, (POINTS, 2))
    s = (rows - row_ref) * tau
    start_R, start_p = Rm @ so3_exp(rng.normal(0.0, 0.01, 3)), pm + rng.normal(0.0, 0.02, 3)
    acc_p2 = 1.0 / acc_std**2 if acc_std > 0 else 0.0
    R, _, w, _, a, *_ = rs_projection.track_frame(
        start_R, start_p, np.zeros(3), np.zeros(3), np.zeros(3), X[seen], x[seen], s[seen], f,
        1.5 * f / 1000.0, np.zeros(9), np.zeros(9), acc_p2, 20)  # fmt: skip
    w_mean_row0 = renderer.readout_turn_rate(k)
    w_mean = Rm.T @ R0 @ w_mean_row0  # in the reference-row frame, as the tracked w
    s0 = -row_ref * tau
    R0_est = R @ so3_exp(s0 * (w + 0.5 * s0 * a))
    return (float(np.linalg.norm(w_mean_row0 - w0) / np.linalg.norm(w0)),
            float(np.linalg.norm(w - w_mean) / np.linalg.norm(w_mean)),
            float(np.degrees(np.linalg.norm(so3_log(R0.T @ R0_est)))),
            float(np.linalg.norm(w + s0 * a - w0) / np.linalg.norm(w0)))


def velocity_floor(severity: float, noise_px: float = 0.3, frames: range = range(5, 86, 2),
                   seed: int = 0) -> dict:  # fmt: skip
    renderer = SequenceRenderer(SynthConfig(motion="walk", severity=severity, seed=seed,
                                            frames=max(frames) + 1))  # fmt: skip
    out = {"severity": severity}
    for label, acc in (("constant", 0.0), ("acceleration", ACCELERATION_STD_RAD_S2)):
        rng = np.random.default_rng([seed, 1])
        errs = np.array([frame_errors(renderer, k, rng, noise_px, acc) for k in frames])
        out["readout_mean_vs_instantaneous"] = float(np.median(errs[:, 0]))
        out[f"w_error_{label}"] = float(np.median(errs[:, 1]))
        out[f"row0_rotation_deg_{label}"] = float(np.median(errs[:, 2]))
        out[f"row0_w_error_{label}"] = float(np.median(errs[:, 3]))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m rsvo_ros.tools.velocity_floor",
                                 description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--severity", type=float, nargs="+", default=[0.5, 1.0, 2.0])
    ap.add_argument("--noise-px", type=float, default=0.3)
    args = ap.parse_args(argv)
    if args.noise_px < 0 or any(s < 0 for s in args.severity):
        ap.error("severities and the noise must be >= 0")
    print("| walk severity | readout mean vs instantaneous row-0 w | tracked w vs readout mean, "
          "constant velocity / angular acceleration | tracked row-0 w vs instantaneous, "
          "constant / acceleration | row-0 rotation error, constant / acceleration |")
    print("|---|---|---|---|---|")
    for sev in args.severity:
        r = velocity_floor(sev, args.noise_px)
        print(f"| {sev:g} | {100 * r['readout_mean_vs_instantaneous']:.0f} % | "
              f"{100 * r['w_error_constant']:.0f} / {100 * r['w_error_acceleration']:.0f} % | "
              f"{100 * r['row0_w_error_constant']:.0f} / "
              f"{100 * r['row0_w_error_acceleration']:.0f} % | "
              f"{r['row0_rotation_deg_constant']:.3f} / "
              f"{r['row0_rotation_deg_acceleration']:.3f} deg |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
