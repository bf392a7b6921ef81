"""A long run of the pipeline in process, frames fed at a camera's rate (the README's async A/B).

    python -m rsvo_ros.tools.paced_run --frames 900 --rate 15 --mapping async --seed 0

Renders a hand-held walk (``rsvo_synth``'s scene), feeds its frames to :class:`OdometryPipeline` no
faster than ``--rate`` (with async mapping the window BA runs beside tracking, as in the node;
inline mapping is not paced, as in the replay), and prints one JSON line: ATE after Sim(3)
alignment (``ate_m``; None with ``ate_error`` where evo refuses the poses, e.g. a run too short to
move), frame time median and p95, and how many frames ended how. ``--window-option NAME=VALUE``
sets a numeric :class:`WindowOptions` field (for A/B runs), ``--slow-ms`` lists frames that took
longer (index, frame, tracker and window BA time in ms, outcome). ``--drop`` (async) applies the
node's newest-frame policy: a frame that arrives while another is processed waits, and a newer one
replaces it (the replaced one is dropped and counted); the ATE is then over the frames that were
processed. It measures the pipeline's own pace without DDS, image transport or another process on
the cores (the live probe, ``python -m rsvo_ros.ros.latency``, has those). ``--drop-every N``
leaves out every N-th frame (a camera or a node that loses frames regularly; deterministic with
inline mapping), and ``--no-flow-prediction`` turns off the tracker's start from the last image
motion after such a gap (``TrackerOptions.predict_flow``); ``--no-klt-shift-retry`` tracks with KLT
alone (``TrackerOptions.shift_retry``; the re-tracked frames are counted either way).
``--motion-at-rate`` samples the motion at ``--rate`` (a camera at that rate; by default the
motion's own frames, the walk's at 30 Hz, are fed at ``--rate``). ``--motion`` renders a vehicle or
hand-held sequence instead of the walk; ``--decimation D`` tracks at 1/D of the resolution,
``--decimation auto`` (with ``--drop``) starts at full resolution and steps down as the node's
``tracking_decimation_mode: auto`` does (:class:`AutoDecimation`; the steps are listed).
``--mapping async`` picks each window BA up when it finishes (``WindowOptions.mapping_lag_s``
0, the figures of the sessions before the forty-second); the node's own pick-up since then is
``--window-option mapping_lag_s=0.05`` (its parameter ``mapping_lag_s``).
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
import time

import numpy as np

from rsvo_ros.odometry.pipeline import OdometryPipeline, PipelineOptions
from rsvo_ros.odometry.tracker import MAX_DECIMATION, AutoDecimation
from rsvo_ros.sim.synth import SequenceRenderer, SynthConfig, resolution_arg
from rsvo_ros.tools.replay import accuracy, set_window_options, window_option_arg
from rsvo_ros.twoview.estimator import warm_up


def paced_run(frames: int, rate: float, mapping: str, seed: int, width: int, height: int,
              window_options: list[tuple[str, float]], slow_ms: float | None = None,
              drop: bool = False, drop_every: int = 0,
              flow_prediction: bool = True, motion: str = "walk",
              decimation: int | str = 1, shift_retry: bool = True,
              motion_at_rate: bool = False) -> dict:  # fmt: skip
    cfg = SynthConfig(frames=frames, motion=motion, width=width, height=height, seed=seed,
                      frame_rate=rate if motion_at_rate else None)
    renderer = SequenceRenderer(cfg)
    rendered = list(renderer)
    options = PipelineOptions()
    options.window.async_mapping = mapping == "async"
    set_window_options(options, window_options)
    options.tracker.predict_flow = flow_prediction
    options.tracker.shift_retry = shift_retry
    auto = AutoDecimation() if decimation == "auto" else None
    options.tracker.decimation = 1 if auto is not None else int(decimation)
    steps = []
    pipeline = OdometryPipeline(renderer.K, None, cfg.tau, options)
    track_ms = []
    tracker_track = pipeline.tracker.track

    def timed_track(*a, **kw):  # the tracker's share of each frame's time
        t = time.perf_counter()
        try:
            return tracker_track(*a, **kw)
        finally:
            track_ms.append(1e3 * (time.perf_counter() - t))

    pipeline.tracker.track = timed_track
    warm_up()  # as the node does before its first image (the solver's kernels loaded)
    est, gt, times, slow, delays = {}, {}, [], [], []
    outcomes: collections.Counter = collections.Counter()
    dropped, busy_s, from_shift = 0, 0.0, 0
    t0 = time.monotonic()
    try:
        k = 0
        while k < len(rendered):
            if drop:
                # the newest frame that has arrived (the ones it replaced are dropped)
                newest = min(int((time.monotonic() - t0) * rate), len(rendered) - 1)
                dropped += max(newest - k, 0)
                if newest > k:  # as the node: the newest dropped one is the stream's clock
                    pipeline.note_dropped(round(rendered[newest - 1].stamp * 1e9))
                k = max(k, newest)
            if drop_every and k % drop_every == drop_every - 1:
                dropped += 1
                k += 1
                continue
            frame = rendered[k]
            while options.window.async_mapping and time.monotonic() < t0 + k / rate:
                time.sleep(0.001)
            stamp = round(frame.stamp * 1e9)
            tracked_before = len(track_ms)
            res = pipeline.process(stamp, frame.image)
            busy_s += res.time_ms * 1e-3
            from_shift += res.image_shift is not None
            if auto is not None:  # as the node: after the frame, with the counts so far
                newest = min(int((time.monotonic() - t0) * rate), len(rendered) - 1)
                step = auto.update(max(newest, k) + 1, dropped + max(newest - k - 1, 0),
                                   busy_s, time.monotonic() - t0, pipeline.image_size)
                if step is not None:
                    pipeline.tracker.set_decimation(step.factor)
                    steps.append([k, step.factor])
            times.append(res.time_ms)
            outcomes[f"{res.status}: {res.reason.split(' (')[0] or 'tracked'}"] += 1
            if slow_ms is not None and res.time_ms > slow_ms:
                # the tracker's time in this frame (0 where it was not tracked)
                slow.append([k, round(res.time_ms, 1), round(sum(track_ms[tracked_before:]), 1),
                             round(res.mapping_ms, 1), res.reason or "tracked"])
            gt[stamp], est[stamp] = frame.pose(), res.T_world_cam
            delays.append(1e3 * (time.monotonic() - t0 - k / rate))
            k += 1
    finally:
        pipeline.close()
    out = {"frames": frames, "rate_hz": rate, "mapping": mapping, "seed": seed,
           "resolution": f"{width}x{height}", "window_options": dict(window_options),
           "flow_prediction": flow_prediction, "klt_shift_retry": shift_retry,
           "frames_tracked_from_shift": from_shift, "motion": motion,
           "motion_rate_hz": cfg.rate_hz,
           "decimation": decimation, "decimation_steps": steps,
           "ate_m": None,
           "frame_ms_median": float(np.median(times)),
           "frame_ms_p95": float(np.percentile(times, 95)),
           "track_ms_median": float(np.median(track_ms)) if track_ms else None,
           "track_ms_p95": float(np.percentile(track_ms, 95)) if track_ms else None,
           "track_s_total": float(np.sum(track_ms)) * 1e-3, "outcomes": dict(outcomes)}
    try:  # too few or degenerate poses (a run that never initialised): said, not raised
        out["ate_m"] = accuracy(gt, est)["ate_m"]["rmse"]
    except Exception as exc:  # noqa: BLE001 - any evo failure is reported
        out["ate_error"] = f"{type(exc).__name__}: {exc}"
    if drop or drop_every:
        out.update(processed=len(times), dropped=dropped)
    if drop:
        # from the frame's arrival (its time in the stream) to its result
        out.update(delay_ms_median=float(np.median(delays)),
                   delay_ms_p95=float(np.percentile(delays, 95)))
    if slow_ms is not None:
        out["slow_frames"] = slow
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=900)
    ap.add_argument("--rate", type=float, default=15.0, help="frames per second fed (async)")
    ap.add_argument("--mapping", choices=("async", "inline"), default="async")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--resolution", type=resolution_arg, default=(640, 480), metavar="WxH",
                    help="image size (default 640x480)")
    ap.add_argument("--window-option", type=window_option_arg, action="append", default=[],
                    metavar="NAME=VALUE", help="a numeric WindowOptions field (repeatable)")
    ap.add_argument("--slow-ms", type=float, default=None, help="list frames slower than this")
    ap.add_argument("--drop", action="store_true",
                    help="async: the node's newest-frame policy (frames that arrive while one is "
                         "processed are replaced by newer ones and dropped)")
    ap.add_argument("--drop-every", type=int, default=0, metavar="N",
                    help="leave out every N-th frame (0: none)")
    ap.add_argument("--no-flow-prediction", action="store_true",
                    help="KLT starts from no motion after a gap too (TrackerOptions.predict_flow)")
    ap.add_argument("--no-klt-shift-retry", action="store_true",
                    help="KLT alone, no re-tracking from the images' global shift where it keeps "
                         "too few tracks (TrackerOptions.shift_retry)")
    ap.add_argument("--motion", choices=("walk", "vehicle", "handheld"), default="walk")
    ap.add_argument("--motion-at-rate", action="store_true",
                    help="sample the motion at --rate (a camera at that rate: at 15 Hz twice the "
                         "walk's motion per frame); default: the motion's own rate (the walk's "
                         "30 Hz frames) fed at --rate")
    ap.add_argument("--decimation", default="1", metavar="D|auto",
                    help=f"track at 1/D of the resolution (1-{MAX_DECIMATION}), or auto (with "
                         "--drop): start at full resolution and step down as the node's "
                         "tracking_decimation_mode auto does")
    args = ap.parse_args(argv)
    if args.decimation != "auto":
        if not args.decimation.isdigit() or not 1 <= int(args.decimation) <= MAX_DECIMATION:
            ap.error(f"--decimation must be 1-{MAX_DECIMATION} or auto, got "
                     f"{args.decimation!r}")
        args.decimation = int(args.decimation)
    elif not args.drop:
        ap.error("--decimation auto needs --drop (it steps down when frames are dropped)")
    width, height = args.resolution
    if args.frames < 2 or args.rate <= 0:
        ap.error("--frames must be at least 2 and --rate positive")
    if args.drop_every < 0 or args.drop_every == 1:
        ap.error("--drop-every must be 0 (none) or at least 2")
    if args.drop and args.mapping != "async":
        ap.error("--drop needs --mapping async (inline mapping is not paced, as in the replay)")
    print(json.dumps(paced_run(args.frames, args.rate, args.mapping, args.seed, width, height,
                               args.window_option, args.slow_ms, args.drop, args.drop_every,
                               not args.no_flow_prediction, args.motion,
                               args.decimation, not args.no_klt_shift_retry,
                               args.motion_at_rate)))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
