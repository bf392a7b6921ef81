"""A long run of the pipeline in process, frames fed at a camera's rate (the README's async A/B).

    python -m rsvo_ros.tools.paced_run --frames 900 --rate 15 --mapping async --seed 0

Renders a hand-held walk (``rsvo_synth``'s scene), feeds its frames to :class:`OdometryPipeline`
no faster than ``--rate`` (with async mapping the window BA runs beside tracking, as in the
node; inline mapping is not paced, as in the replay), and prints one JSON line: ATE after Sim(3)
alignment, frame time median and p95, and how many frames ended how. ``--window-option
NAME=VALUE`` sets a numeric :class:`WindowOptions` field (for A/B runs), ``--slow-ms`` lists
frames that took longer.
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
import time

import numpy as np

from rsvo_ros.odometry.pipeline import OdometryPipeline, PipelineOptions
from rsvo_ros.sim.synth import SequenceRenderer, SynthConfig
from rsvo_ros.tools.replay import accuracy, set_window_options, window_option_arg


def paced_run(frames: int, rate: float, mapping: str, seed: int, width: int, height: int,
              window_options: list[tuple[str, float]],
              slow_ms: float | None = None) -> dict:  # fmt: skip
    cfg = SynthConfig(frames=frames, motion="walk", width=width, height=height, seed=seed)
    renderer = SequenceRenderer(cfg)
    rendered = list(renderer)
    options = PipelineOptions()
    options.window.async_mapping = mapping == "async"
    set_window_options(options, window_options)
    pipeline = OdometryPipeline(renderer.K, None, cfg.tau, options)
    est, gt, times, slow = {}, {}, [], []
    outcomes: collections.Counter = collections.Counter()
    t0 = time.monotonic()
    try:
        for k, frame in enumerate(rendered):
            while options.window.async_mapping and time.monotonic() < t0 + k / rate:
                time.sleep(0.001)
            stamp = round(frame.stamp * 1e9)
            res = pipeline.process(stamp, frame.image)
            times.append(res.time_ms)
            outcomes[f"{res.status}: {res.reason.split(' (')[0] or 'tracked'}"] += 1
            if slow_ms is not None and res.time_ms > slow_ms:
                slow.append([k, round(res.time_ms, 1), res.reason or "tracked"])
            gt[stamp], est[stamp] = frame.pose(), res.T_world_cam
    finally:
        pipeline.close()
    out = {"frames": frames, "rate_hz": rate, "mapping": mapping, "seed": seed,
           "resolution": f"{width}x{height}", "window_options": dict(window_options),
           "ate_m": accuracy(gt, est)["ate_m"]["rmse"],
           "frame_ms_median": float(np.median(times)),
           "frame_ms_p95": float(np.percentile(times, 95)), "outcomes": dict(outcomes)}
    if slow_ms is not None:
        out["slow_frames"] = slow
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=900)
    ap.add_argument("--rate", type=float, default=15.0, help="frames per second fed (async)")
    ap.add_argument("--mapping", choices=("async", "inline"), default="async")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--resolution", default="640x480", help="WIDTHxHEIGHT")
    ap.add_argument("--window-option", type=window_option_arg, action="append", default=[],
                    metavar="NAME=VALUE", help="a numeric WindowOptions field (repeatable)")
    ap.add_argument("--slow-ms", type=float, default=None, help="list frames slower than this")
    args = ap.parse_args(argv)
    try:
        width, height = (int(v) for v in args.resolution.lower().split("x"))
    except ValueError:
        ap.error(f"--resolution {args.resolution!r}: expected WIDTHxHEIGHT, e.g. 640x480")
    if args.frames < 2 or args.rate <= 0:
        ap.error("--frames must be at least 2 and --rate positive")
    print(json.dumps(paced_run(args.frames, args.rate, args.mapping, args.seed, width, height,
                               args.window_option, args.slow_ms)))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
