"""How much of a synthetic camera's turning during one readout each motion model explains.

    python -m rsvo_ros.tools.readout_motion [--frames 90] [--cases walk:1:0:1e-4 ...]

For each frame of an ``rsvo_synth`` sequence (case ``motion:severity:seed:line_delay``; the
line delay ``default`` is rsvo_synth's), the true rotation of every 8th row's camera relative to
the reference row's (the principal point's) is fitted over the readout by

- ``gs``: nothing (a global shutter: no turning during the readout),
- ``cv``: a constant angular velocity (``Exp(s w)``, the paper's model),
- ``ca``: a constant angular acceleration (``Exp(s w + s^2/2 a)``, ``angular_acceleration_std``),

and what is left is reported as RMS pixels at the focal length (median and 90th percentile over
the frames). Translation is left out (a few millimetres over a readout). Pure numpy on the
renderer's continuous trajectory; nothing is rendered.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from rsvo_ros.core.geometry import so3_log
from rsvo_ros.sim.synth import SequenceRenderer, SynthConfig, intrinsics

DEFAULT_CASES = ("walk:0.5:0:default", "walk:1:0:default", "walk:2:100:default",
                 "walk:1:0:5e-5", "handheld:1:0:default", "vehicle:1:0:5e-5",
                 "vehicle:2:301:default")  # fmt: skip
ROW_STEP = 8


def parse_case(text: str, frames: int) -> SynthConfig:
    """``motion:severity:seed:line_delay`` to a :class:`SynthConfig`."""
    try:
        motion, severity, seed, line_delay = text.split(":")
        return SynthConfig(frames=frames, motion=motion, severity=float(severity),
                           seed=int(seed),
                           line_delay=None if line_delay == "default" else float(line_delay))
    except (ValueError, TypeError) as exc:
        raise ValueError(f"case must be motion:severity:seed:line_delay, got {text!r} "
                         f"({exc})") from None


def unexplained_px(config: SynthConfig) -> dict[str, np.ndarray]:
    """Per frame (frames 2 to N-2), the RMS rotation (px) each model leaves unexplained."""
    renderer = SequenceRenderer(config)
    trajectory = renderer.trajectory
    if trajectory is None:
        raise ValueError("the paper motion has no continuous trajectory")
    K = intrinsics(config.width, config.height)
    focal, row_ref, tau = K[0, 0], K[1, 2], config.tau
    rows = np.arange(0, config.height, float(ROW_STEP))
    s = (rows - row_ref) * tau
    bases = {"gs": None, "cv": s[:, None], "ca": np.column_stack([s, s**2 / 2])}
    out = {name: [] for name in bases}
    for k in range(2, config.frames - 2):
        t0 = k / config.rate_hz
        R_rows, _ = trajectory.pose(t0 + rows * tau)
        R_ref, _ = trajectory.pose(np.array([t0 + row_ref * tau]))
        phi = so3_log(np.einsum("ji,njk->nik", R_ref[0], R_rows))  # (n, 3)
        for name, A in bases.items():
            e = phi if A is None else phi - A @ np.linalg.lstsq(A, phi, rcond=None)[0]
            out[name].append(focal * np.sqrt(np.mean(np.sum(e**2, axis=1))))
    return {name: np.array(v) for name, v in out.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m rsvo_ros.tools.readout_motion",
                                 description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=90)
    ap.add_argument("--cases", nargs="+", default=list(DEFAULT_CASES),
                    metavar="MOTION:SEVERITY:SEED:LINE_DELAY")
    args = ap.parse_args(argv)
    if args.frames < 5:
        print("readout_motion: --frames must be at least 5", file=sys.stderr)
        return 2
    print("| case | readout (ms) | gs: RMS px, median (p90) | cv | ca |")
    print("|---|---|---|---|---|")
    for case in args.cases:
        try:
            config = parse_case(case, args.frames)
            res = unexplained_px(config)
        except ValueError as exc:
            print(f"readout_motion: {exc}", file=sys.stderr)
            return 2
        cells = " | ".join(f"{np.median(v):.2f} ({np.percentile(v, 90):.2f})"
                           for v in res.values())
        print(f"| {case} | {config.tau * config.height * 1e3:.1f} | {cells} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
