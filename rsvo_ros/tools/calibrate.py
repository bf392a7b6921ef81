"""rsvo_calibrate: the line delay of a rolling-shutter camera from a bag of its video.

Runs the odometry over the bag with ``line_delay: auto`` (RS model, window backend), then
(unless ``--no-refine``) a second time at that estimate with the map's shear removed, and
refines it from the frames' turn rates during the readout against the turns between them
(``PipelineOptions.line_delay_refine``; README, "Unknown line delay"). Prints the estimate with
its uncertainty, the readout time (line delay x image height) and the readout as a fraction of
the frame interval; writes a ROS 2 parameter file the node loads with
``rsvo_node --ros-args --params-file FILE``. The camera must move (rotate) during the bag.
Exit codes: 0 estimated, 1 the bag cannot be used or the line delay is not observable in it,
2 bad arguments.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from pathlib import Path

import numpy as np

from rsvo_ros.core.readout import READOUTS
from rsvo_ros.odometry.line_delay import LineDelayEstimate
from rsvo_ros.odometry.pipeline import PipelineOptions
from rsvo_ros.ros import bagio
from rsvo_ros.ros.params import params_yaml
from rsvo_ros.tools.replay import ReplayConfig, ReplayError, replay

EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="rsvo_calibrate", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bag", type=Path, help="rosbag2 directory (sqlite3 or mcap) or ROS 1 .bag file")
    p.add_argument("--output", "-o", type=Path, default=Path("rsvo_line_delay.yaml"),
                   help="parameter file to write (default rsvo_line_delay.yaml)")
    p.add_argument("--image-topic", default=bagio.IMAGE_TOPIC)
    p.add_argument("--camera-info-topic", default=bagio.CAMERA_INFO_TOPIC)
    p.add_argument("--camera-file", type=Path, default=None, metavar="YAML",
                   help="intrinsics from a ROS camera calibration or Kalibr camchain YAML "
                        "instead of the camera info topic")
    p.add_argument("--camera-entry", default=None, metavar="CAM",
                   help="the Kalibr camchain's entry (default cam0)")
    p.add_argument("--uncalibrated-focal-factor", type=float, default=0.0, metavar="F",
                   help="a camera info without calibration (K all zero): assume a pinhole "
                        "camera of focal length F image widths, as rsvo_replay does (default 0: "
                        "refused)")
    p.add_argument("--max-frames", type=int, default=None,
                   help="use only the first N images (default: all)")
    p.add_argument("--readout-direction", choices=READOUTS, default="down",
                   help="which way the rolling shutter reads the images as they are in the bag "
                        "(rsvo_replay --readout-direction): down (default), up, right, left; "
                        "the estimate is then per line read")
    p.add_argument("--no-refine", action="store_true",
                   help="keep the first estimate (one pass) instead of refining it in a second "
                        "pass over the bag (README, \"Unknown line delay\")")
    p.add_argument("--no-progress", action="store_true")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.max_frames is not None and args.max_frames < 10:
        print("rsvo_calibrate: --max-frames must be at least 10", file=sys.stderr)
        return EXIT_USAGE
    if not (np.isfinite(args.uncalibrated_focal_factor)
            and 0 <= args.uncalibrated_focal_factor <= 10):
        print("rsvo_calibrate: --uncalibrated-focal-factor must be in [0, 10] image widths",
              file=sys.stderr)
        return EXIT_USAGE

    def run(out: Path, options: PipelineOptions, line_delay: float | None = None) -> dict:
        cfg = ReplayConfig(args.bag, out, "rs", args.image_topic, args.camera_info_topic,
                           line_delay=line_delay, progress=not args.no_progress,
                           options=options, max_frames=args.max_frames,
                           camera_file=args.camera_file, camera_entry=args.camera_entry,
                           uncalibrated_focal_factor=args.uncalibrated_focal_factor)  # fmt: skip
        return replay(cfg)

    with tempfile.TemporaryDirectory(prefix="rsvo_calibrate_") as tmp:
        try:
            # the calibrator's estimate: the re-runs of the first frames mend the replay's
            # trajectory, not the estimate (README); the second pass below refines it over
            # the whole bag instead of the first 150 frames
            summary = run(Path(tmp) / "replay",
                          PipelineOptions(line_delay_auto=True, readout=args.readout_direction,
                                          line_delay_rerun_max_frames=0,
                                          line_delay_auto_refine_frames=0))  # fmt: skip
        except ReplayError as exc:
            print(f"rsvo_calibrate: {exc}", file=sys.stderr)
            return EXIT_FAILED
        except ValueError as exc:
            print(f"rsvo_calibrate: {exc}", file=sys.stderr)
            return EXIT_USAGE
        e = summary["line_delay_auto"]
        refined = None
        if not args.no_refine and e["line_delay_s"]:  # 0: a global shutter, kept
            try:
                second = run(Path(tmp) / "refine",
                             PipelineOptions(line_delay_refine=True,
                                             readout=args.readout_direction),
                             line_delay=float(e["line_delay_s"]))  # fmt: skip
                refined = second["line_delay_refined"]
            except (ReplayError, ValueError) as exc:  # the first estimate is not lost
                refined = {"status": "failed", "reason": f"the second pass failed: {exc}"}
    if e["line_delay_s"] is None:
        print(f"rsvo_calibrate: no estimate: {e['status']} ({e['reason']}); the camera must "
              "move and rotate during the bag", file=sys.stderr)
        return EXIT_FAILED
    print(f"rsvo_calibrate: line delay {e['line_delay_s'] * 1e6:.2f} +- {e['std_s'] * 1e6:.2f} "
          f"us/row, readout {e['readout_s'] * 1e3:.2f} ms ({e['readout_fraction']:.3f} +- "
          f"{e['std_fraction']:.3f} frame intervals); {e['status']} from {e['windows']} "
          f"windows of {summary['frames_in']} frames")
    if refined is not None:
        if refined["status"] == "refined":
            first = dict(e)
            e = refined_estimate(e, refined)
            print(f"rsvo_calibrate: refined in a second pass: line delay "
                  f"{e['line_delay_s'] * 1e6:.2f} +- {e['std_s'] * 1e6:.2f} us/row, readout "
                  f"{e['readout_s'] * 1e3:.2f} ms ({e['readout_fraction']:.3f} frame intervals; "
                  f"first {first['line_delay_s'] * 1e6:.2f} us/row; {refined['blocks']} blocks of "
                  f"{refined['frames']} tracked frames)")
        else:
            print(f"rsvo_calibrate: kept the first estimate: the second pass could not refine "
                  f"it ({refined['reason']})")
    if e["bag_line_delay_s"] is not None:
        print(f"rsvo_calibrate: the bag records {e['bag_line_delay_s'] * 1e6:.2f} us/row")
    args.output.write_text(params_yaml(e, f"rsvo_calibrate {args.bag}",
                                       readout_direction=args.readout_direction))
    print(f"rsvo_calibrate: wrote {args.output} (rsvo_node --ros-args --params-file "
          f"{args.output})")
    return EXIT_OK


def refined_estimate(first: dict, refined: dict) -> dict:
    """The first estimate's dict (LineDelayEstimate.as_dict) with the second pass's refined
    line delay and its std (the readout and the fractions scaled with it)."""
    fields = {f.name for f in dataclasses.fields(LineDelayEstimate)} - {"curve"}
    estimate = LineDelayEstimate(**{k: first[k] for k in fields})
    return {**first, **estimate.refined(refined["line_delay_s"], refined["std_s"]).as_dict(),
            "first_line_delay_s": first["line_delay_s"]}


if __name__ == "__main__":
    sys.exit(main())
