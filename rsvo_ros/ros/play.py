"""rsvo_play: publish a rosbag2's topics live, in real time (stands in for `ros2 bag play`).

Messages are published as the recorded CDR bytes (no re-serialization), each topic with its
recorded type, at the recorded pace scaled by ``--rate``.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from pathlib import Path

import rclpy
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException
from rclpy.qos import QoSProfile, ReliabilityPolicy

EXIT_OK, EXIT_BAD_BAG, EXIT_USAGE = 0, 1, 2
ACK_TIMEOUT_S = 5.0  # at the end: how long to wait for the subscribers to acknowledge


def message_class(msgtype: str):
    """The rclpy class of 'pkg/msg/Name'."""
    pkg, kind, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.{kind}"), name)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="rsvo_play", description="Publish a rosbag2's topics live.")
    p.add_argument("bag", type=Path, help="rosbag2 directory (sqlite3 or mcap)")
    p.add_argument("--rate", type=float, default=1.0, help="playback speed factor (default 1)")
    p.add_argument("--loop", action="store_true", help="start again at the end, forever")
    p.add_argument("--loops", type=int, default=1, metavar="N",
                   help="play the bag N times (default 1; the stamps repeat, as with "
                        "ros2 bag play -l)")
    p.add_argument("--topics", nargs="+", default=None, help="only these topics")
    p.add_argument("--qos", choices=("reliable", "best_effort"), default="reliable",
                   help="publisher reliability (default reliable)")
    p.add_argument("--wait-for-subscribers", type=float, default=0.0, metavar="S",
                   help="wait up to S seconds for every topic to have a subscriber")
    p.add_argument("--start-delay", type=float, default=0.0, metavar="S",
                   help="sleep S seconds after creating the publishers")
    return p


def main(argv: list[str] | None = None) -> int:
    args, ros_args = build_parser().parse_known_args(argv)
    if not (args.rate > 0):
        print("rsvo_play: --rate must be > 0", file=sys.stderr)
        return EXIT_USAGE
    if args.loops < 1:
        print("rsvo_play: --loops must be >= 1", file=sys.stderr)
        return EXIT_USAGE
    from rosbags.rosbag2 import Reader

    try:
        reader = Reader(args.bag)
        reader.open()
    except Exception as exc:  # noqa: BLE001 - rosbags raises several kinds
        hint = ""
        if Path(args.bag).is_file():  # a ROS 1 .bag (rsvo_replay reads those directly)
            hint = (f" (a ROS 1 bag? rsvo_play publishes rosbag2 only: rosbags-convert --src "
                    f"{args.bag} --dst DIR)")
        print(f"rsvo_play: cannot read bag {args.bag}: {exc}{hint}", file=sys.stderr)
        return EXIT_BAD_BAG
    conns = [c for c in reader.connections if args.topics is None or c.topic in args.topics]
    if not conns:
        print(f"rsvo_play: none of the topics {args.topics} in {args.bag}", file=sys.stderr)
        reader.close()
        return EXIT_BAD_BAG
    rclpy.init(args=[sys.argv[0], *ros_args])
    node = rclpy.create_node("rsvo_play")
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE if args.qos == "reliable"
                     else ReliabilityPolicy.BEST_EFFORT)  # fmt: skip
    pubs = {}
    try:
        for c in conns:
            pubs[c.id] = node.create_publisher(message_class(c.msgtype), c.topic, qos)
        deadline = time.monotonic() + args.wait_for_subscribers
        while time.monotonic() < deadline and any(
                p.get_subscription_count() == 0 for p in pubs.values()):
            time.sleep(0.05)
        time.sleep(args.start_delay)
        count = 0
        passes = 0
        while True:
            t_bag0 = None
            t_wall0 = time.monotonic()
            for conn, t_ns, raw in reader.messages(connections=conns):
                if t_bag0 is None:
                    t_bag0 = t_ns
                due = t_wall0 + (t_ns - t_bag0) / 1e9 / args.rate
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                pubs[conn.id].publish(bytes(raw))
                count += 1
            passes += 1
            if not args.loop and passes >= args.loops:
                break
        # reliable delivery needs the writer alive until the readers have acknowledged: the
        # last image was lost now and then when the player exited right after publishing it
        for pub in pubs.values():
            pub.wait_for_all_acked(Duration(seconds=ACK_TIMEOUT_S))
        print(f"rsvo_play: published {count} messages from {args.bag}")
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        reader.close()
        node.destroy_node()
        rclpy.try_shutdown()
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
