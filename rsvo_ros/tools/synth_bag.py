"""rsvo_synth: write a synthetic rolling-shutter rosbag2 with ground truth (CONTRACTS.md format).

A thin shell over :mod:`rsvo_ros.sim.synth` (rendering) and :mod:`rsvo_ros.ros.bagio` (messages).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from rsvo_ros.ros import bagio
from rsvo_ros.sim.synth import LENSES, MOTIONS, SequenceRenderer, SynthConfig, resolution_arg

EXIT_USAGE = 2
STAMP_JITTER_STREAM = 7717  # the stamp jitter's random stream, beside the sequence's seed


def check_stamp_jitter(config: SynthConfig, stamp_jitter_s: float) -> None:
    """``ValueError`` unless ``0 <= stamp_jitter_s`` < one frame interval of ``config``."""
    interval = 1.0 / config.rate_hz
    if not 0.0 <= stamp_jitter_s < interval:
        raise ValueError(f"the stamp jitter must be at least 0 s and under one frame interval "
                         f"({interval:g} s), got {stamp_jitter_s!r}")


def jittered_stamps_ns(config: SynthConfig, stamp_jitter_s: float) -> list[int]:
    """Each frame's stamp (ns) as a camera driver that stamps on arrival gives it: the nominal
    ``k / rate`` plus a uniform delay in ``[0, stamp_jitter_s)``, from a stream seeded by the
    sequence's seed (the same bag twice for the same arguments). ``ValueError`` unless
    ``0 <= stamp_jitter_s`` < one frame interval (the frames keep their order)."""
    check_stamp_jitter(config, stamp_jitter_s)
    nominal = [round(k / config.rate_hz * 1e9) for k in range(config.frames)]
    if stamp_jitter_s == 0:
        return nominal
    rng = np.random.default_rng([config.seed, STAMP_JITTER_STREAM])
    delays = rng.uniform(0.0, stamp_jitter_s, config.frames)
    return [t + round(d * 1e9) for t, d in zip(nominal, delays, strict=True)]


def write_bag(path: Path, config: SynthConfig, storage: str = "sqlite3",
              overwrite: bool = False, progress: bool = True,
              compressed: str | None = None, stamp_jitter_s: float = 0.0) -> dict:  # fmt: skip
    """Render ``config`` frame by frame into a bag at ``path``; returns a small summary.
    ``compressed`` (``"png"`` or ``"jpeg"``): the images as sensor_msgs/CompressedImage on
    ``/camera/image_raw/compressed`` instead of sensor_msgs/Image on ``/camera/image_raw``.
    ``stamp_jitter_s`` > 0: every message of a frame stamped late by up to that
    (:func:`jittered_stamps_ns`; images and ground truth are the nominal instant's, as a
    driver's arrival stamps have them), recorded as ``rsvo.stamp_jitter``.

    Raises FileExistsError if ``path`` exists and ``overwrite`` is False.
    """
    if compressed is not None and compressed not in bagio.COMPRESSIONS:
        raise ValueError(f"compressed must be one of {bagio.COMPRESSIONS}, got {compressed!r}")
    stamps_ns = jittered_stamps_ns(config, stamp_jitter_s)
    path = Path(path)
    if path.exists():
        if not overwrite:
            raise FileExistsError(f"{path} exists; pass --overwrite to replace it")
        shutil.rmtree(path) if path.is_dir() else path.unlink()
    renderer = SequenceRenderer(config)
    K = renderer.K
    writer = bagio.open_writer(path, storage)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=config.frames, desc=f"rsvo_synth {path.name}", unit="frame",
                   file=sys.stderr)  # fmt: skip
    t0 = time.perf_counter()
    ts = bagio.typestore()
    with writer:
        writer.set_custom_data(bagio.LINE_DELAY_KEY, format(float(config.tau), ".12g"))
        writer.set_custom_data("rsvo.motion", config.motion)
        writer.set_custom_data("rsvo.level", str(config.level))
        writer.set_custom_data("rsvo.severity", format(float(config.severity), ".12g"))
        writer.set_custom_data("rsvo.seed", str(config.seed))
        writer.set_custom_data("rsvo.lens", config.lens)
        writer.set_custom_data("rsvo.exposure", format(float(config.exposure), ".12g"))
        writer.set_custom_data("rsvo.noise", format(float(config.noise), ".12g"))
        writer.set_custom_data("rsvo.gain_variation", format(float(config.gain_variation),
                                                              ".12g"))
        writer.set_custom_data("rsvo.frame_rate", format(float(config.rate_hz), ".12g"))
        writer.set_custom_data("rsvo.movers", str(config.movers))
        if compressed is not None:
            writer.set_custom_data("rsvo.compressed", compressed)
        if stamp_jitter_s > 0:
            writer.set_custom_data("rsvo.stamp_jitter", format(float(stamp_jitter_s), ".12g"))
        connections = bagio.frame_connections(
            writer, ts, bagio.IMAGE_TYPE if compressed is None else bagio.COMPRESSED_IMAGE_TYPE)
        for frame, stamp_ns in zip(renderer, stamps_ns, strict=True):
            img = bagio.image_msg(stamp_ns, frame.image) if compressed is None else \
                bagio.compressed_image_msg(stamp_ns, frame.image, compressed)
            bagio.write_frame(writer, connections, stamp_ns, img, K, config.width, config.height,
                              frame.R_world_cam, frame.p_world_cam, config.lens_model,
                              linear=frame.v, angular=frame.w)
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()
    elapsed = time.perf_counter() - t0
    return {"path": str(path), "frames": config.frames, "seconds": elapsed,
            "frames_per_second": config.frames / max(elapsed, 1e-9)}  # fmt: skip


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="rsvo_synth",
        description="Write a synthetic rolling-shutter rosbag2 (images, camera info, "
        "ground-truth odometry with the RS velocities in its twist, line delay as metadata).",
    )
    p.add_argument("out_bag", type=Path, help="output bag directory (must not exist)")
    p.add_argument("--frames", type=int, default=30, help="number of images (default 30)")
    p.add_argument("--motion", choices=MOTIONS, default="handheld",
                   help="paper: 5 Hz loop with random per-frame RS velocities at --level; "
                        "handheld / vehicle / walk: shaken camera at 30 Hz (--rate; default "
                        "handheld)")
    p.add_argument("--level", type=int, default=6, choices=range(1, 7), metavar="1-6",
                   help="RS distortion level of --motion paper (default 6)")
    p.add_argument("--severity", type=float, default=1.0,
                   help="shaking scale of handheld / vehicle motion (default 1.0; 0 = smooth)")
    p.add_argument("--resolution", type=resolution_arg, default=(640, 360), metavar="WxH",
                   help="image size (default 640x360)")
    p.add_argument("--line-delay", type=float, default=None, metavar="S",
                   help="seconds per row (default: a 36 ms readout, the paper's 720 x 50 us)")
    p.add_argument("--lens", choices=("none", *sorted(LENSES)), default="none",
                   help="render through a wide-angle lens of this CameraInfo distortion model "
                        "(written into the camera info; default none)")
    p.add_argument("--storage", choices=bagio.STORAGES, default="sqlite3",
                   help="rosbag2 storage (default sqlite3)")
    p.add_argument("--seed", type=int, default=0, help="scene and motion seed (default 0)")
    p.add_argument("--overwrite", action="store_true", help="replace OUT_BAG if it exists")
    p.add_argument("--compressed", choices=bagio.COMPRESSIONS, default=None,
                   help="write the images as sensor_msgs/CompressedImage on "
                        f"{bagio.IMAGE_TOPIC}/compressed (image_transport's compressed; JPEG "
                        f"quality {bagio.JPEG_QUALITY}) instead of raw sensor_msgs/Image")
    p.add_argument("--exposure", type=float, default=0.0, metavar="S",
                   help="exposure time of each row (s), centred on its readout time: motion "
                        "blur, rendered as the mean of 8 instants (default 0: sharp). Indoor "
                        "hand-held video is often exposed for 5-20 ms")
    p.add_argument("--noise", type=float, default=0.0, metavar="SIGMA",
                   help="Gaussian sensor noise, grey levels (0-255) std, drawn per frame from "
                        "the seed (default 0)")
    p.add_argument("--gain-variation", type=float, default=0.0, metavar="A",
                   help="auto exposure / gain: each frame's brightness times exp(A g(t)), g a "
                        "smooth random signal of unit RMS at 0.2-1.5 Hz (default 0: constant; "
                        "0.2 gives about 0.7-1.5x, up to 10 %% from one frame to the next)")
    p.add_argument("--rate", type=float, default=None, metavar="HZ",
                   help="frames per second of handheld / vehicle / walk (default 30): the same "
                        "motion sampled at another rate; the default readout is then the "
                        "lesser of 36 ms and one frame interval")
    p.add_argument("--movers", type=int, default=0, metavar="N",
                   help="handheld / vehicle / walk: N people (pedestrian-sized textured "
                        "panels) crossing or walking along in front of the camera, spread over "
                        "the sequence, never within 1 m (vehicles 2 m) of the camera's path: "
                        "points that move on their own (default 0)")
    p.add_argument("--stamp-jitter", type=float, default=0.0, metavar="S",
                   help="stamp every frame late by a uniform 0-S seconds, as a driver that "
                        "stamps on arrival does (the images and ground truth stay the nominal "
                        "instant's; under one frame interval; default 0)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        config = SynthConfig(frames=args.frames, motion=args.motion, level=args.level,
                             severity=args.severity, width=args.resolution[0],
                             height=args.resolution[1], line_delay=args.line_delay,
                             seed=args.seed, lens=args.lens, exposure=args.exposure,
                             noise=args.noise,
                             gain_variation=args.gain_variation,
                             frame_rate=args.rate, movers=args.movers)  # fmt: skip
        summary = write_bag(args.out_bag, config, args.storage, args.overwrite,
                            progress=not args.no_progress, compressed=args.compressed,
                            stamp_jitter_s=args.stamp_jitter)
    except (ValueError, FileExistsError) as exc:
        print(f"rsvo_synth: {exc}", file=sys.stderr)
        return EXIT_USAGE
    print(f"rsvo_synth: wrote {summary['frames']} frames to {summary['path']} "
          f"({summary['frames_per_second']:.1f} frames/s, line delay {config.tau:.3e} s/row)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
