"""Large images over Fast DDS: the shipped profile, and a measurement of what it changes.

    export FASTRTPS_DEFAULT_PROFILES_FILE=$(python -m rsvo_ros.ros.dds)
    python -m rsvo_ros.ros.dds --measure --resolution 640x480 1280x720

Without arguments: prints the path of ``fastdds_large_images.xml`` (also installed by colcon as
``share/rsvo_ros/config/fastdds_large_images.xml``), a Fast DDS profile with a shared-memory
segment of 8 MB instead of the default 512 KB.

``--measure``: for each resolution and each profile (Fast DDS's defaults, then the shipped one),
starts a subscriber and a publisher process on this machine, publishes ``--frames``
``sensor_msgs/Image`` messages at ``--rate`` stamped with the wall clock, and prints the
transport time (subscriber callback minus stamp: the message's construction, publish(),
transport and the executor's hand-over) as a markdown table; ``--json`` writes it too. Both
processes load the profile under test (the segment belongs to the publishing participant). Uses
``ROS_DOMAIN_ID`` from the environment; localhost discovery.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from rsvo_ros.sim.synth import resolution_arg

LARGE_IMAGES_PROFILE = Path(__file__).with_name("fastdds_large_images.xml")
PROFILE_ENV = "FASTRTPS_DEFAULT_PROFILES_FILE"
# Fast DDS's default shared-memory segment (bytes): a larger message leaves the fast path
DEFAULT_SHM_SEGMENT_BYTES = 512 * 1024
ENCODING_CHANNELS = {"mono8": 1, "rgb8": 3}


def profile_env(profile: str, base: dict[str, str] | None = None) -> dict[str, str]:
    """Environment for a process that uses ``profile``: ``"default"`` (Fast DDS's own defaults,
    any profile file of the caller's environment removed) or ``"large_images"``."""
    env = dict(os.environ if base is None else base)
    env.pop(PROFILE_ENV, None)
    if profile == "large_images":
        env[PROFILE_ENV] = str(LARGE_IMAGES_PROFILE)
    elif profile != "default":
        raise ValueError(f"profile must be 'default' or 'large_images', got {profile!r}")
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    return env


def measure(width: int, height: int, encoding: str, profile: str, frames: int, rate: float,
            timeout_s: float = 60.0) -> dict:  # fmt: skip
    """One publisher and one subscriber process with ``profile``; transport times (ms) of the
    frames that arrived."""
    env = profile_env(profile)
    role = [sys.executable, "-m", "rsvo_ros.ros.dds", "--frames", str(frames), "--rate",
            str(rate), "--resolution", f"{width}x{height}", "--encoding", encoding, "--role"]
    sub = subprocess.Popen(role + ["sub"], env=env, stdout=subprocess.PIPE, text=True)
    try:
        pub = subprocess.run(role + ["pub"], env=env, capture_output=True, text=True,
                             timeout=timeout_s)  # fmt: skip
        out, _ = sub.communicate(timeout=timeout_s)
    finally:
        if sub.poll() is None:
            sub.kill()
    if pub.returncode != 0:
        raise RuntimeError(f"the publisher failed (exit {pub.returncode}): "
                           f"{(pub.stderr or pub.stdout).strip()[-500:]}")
    if sub.returncode != 0 or not out.strip():
        raise RuntimeError(f"the subscriber failed (exit {sub.returncode})")
    ms = np.array(json.loads(out.strip().splitlines()[-1])["transport_ms"])
    return {"resolution": f"{width}x{height}", "encoding": encoding,
            "image_bytes": width * height * ENCODING_CHANNELS[encoding], "profile": profile,
            "sent": frames, "received": int(len(ms)),
            "transport_ms_median": float(np.median(ms)) if len(ms) else None,
            "transport_ms_p95": float(np.percentile(ms, 95)) if len(ms) else None}


def table(rows: list[dict]) -> str:
    lines = ["| image | bytes | profile | received | transport median / p95 |",
             "|---|---|---|---|---|"]
    for r in rows:
        t = ("-" if r["transport_ms_median"] is None else
             f"{r['transport_ms_median']:.1f} / {r['transport_ms_p95']:.1f} ms")
        lines.append(f"| {r['resolution']} {r['encoding']} | {r['image_bytes'] // 1024} KB | "
                     f"{r['profile']} | {r['received']} / {r['sent']} | {t} |")
    return "\n".join(lines)


def _role(role: str, width: int, height: int, encoding: str, frames: int, rate: float) -> int:
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    rclpy.init()
    node = rclpy.create_node(f"rsvo_dds_{role}")
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    channels = ENCODING_CHANNELS[encoding]
    try:
        if role == "sub":
            got: list[float] = []

            def on_image(m: Image) -> None:
                stamp = m.header.stamp.sec + m.header.stamp.nanosec * 1e-9
                got.append((time.time() - stamp) * 1e3)

            node.create_subscription(Image, "/rsvo_dds_probe/image", on_image, qos)
            t_end = time.monotonic() + 30.0 + 3.0 * frames / rate
            while time.monotonic() < t_end and len(got) < frames:
                rclpy.spin_once(node, timeout_sec=0.05)
            print(json.dumps({"transport_ms": got}))
            return 0
        pub = node.create_publisher(Image, "/rsvo_dds_probe/image", qos)
        t_end = time.monotonic() + 30.0
        while pub.get_subscription_count() == 0:
            if time.monotonic() > t_end:
                print("no subscriber matched within 30 s", file=sys.stderr)
                return 1
            rclpy.spin_once(node, timeout_sec=0.05)
        time.sleep(1.0)  # the subscriber's side of the match
        data = bytes(width * height * channels)
        t0 = time.monotonic()
        for k in range(frames):
            while time.monotonic() < t0 + k / rate:
                time.sleep(0.001)
            ns = time.time_ns()
            img = Image()
            img.header.stamp.sec, img.header.stamp.nanosec = ns // 10**9, ns % 10**9
            img.height, img.width, img.encoding = height, width, encoding
            img.step, img.data = width * channels, data
            pub.publish(img)
        time.sleep(1.0)  # let the last frames arrive before the participant leaves
        return 0
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m rsvo_ros.ros.dds", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--measure", action="store_true",
                   help="measure the transport time with the default and the shipped profile")
    p.add_argument("--resolution", nargs="+", type=resolution_arg, default=[(1280, 720)],
                   metavar="WxH", help="image sizes (default 1280x720)")
    p.add_argument("--encoding", choices=sorted(ENCODING_CHANNELS), default="mono8")
    p.add_argument("--frames", type=int, default=100, help="images per measurement")
    p.add_argument("--rate", type=float, default=15.0, help="images per second")
    p.add_argument("--json", default=None, help="also write the measurements here")
    p.add_argument("--role", choices=["pub", "sub"], help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    sizes = args.resolution
    if args.frames < 1 or args.rate <= 0:
        p.error("--frames must be >= 1 and --rate > 0")
    if args.role:
        w, h = sizes[0]
        return _role(args.role, w, h, args.encoding, args.frames, args.rate)
    if not args.measure:
        print(LARGE_IMAGES_PROFILE)
        return 0
    rmw = os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    if rmw != "rmw_fastrtps_cpp":
        print(f"RMW_IMPLEMENTATION is {rmw}: the profile is for Fast DDS (rmw_fastrtps_cpp)",
              file=sys.stderr)
        return 2
    rows = []
    for w, h in sizes:
        for profile in ("default", "large_images"):
            print(f"{w}x{h} {args.encoding}, {profile} profile: {args.frames} images at "
                  f"{args.rate:g} Hz ...", file=sys.stderr, flush=True)
            rows.append(measure(w, h, args.encoding, profile, args.frames, args.rate))
    print(table(rows))
    if args.json:
        try:
            Path(args.json).write_text(json.dumps(rows, indent=1))
        except OSError as exc:
            print(f"python -m rsvo_ros.ros.dds: cannot write {args.json}: {exc.strerror or exc}",
                  file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
