"""Record a nav_msgs/Odometry topic to a TUM file (a separate subscriber process for the demo).

    python -m rsvo_ros.ros.record OUT.tum [--topic /rsvo/odom] [--idle 5] [--timeout 600]

Writes ``OUT.tum.ready`` once a publisher of the topic is discovered, then one TUM line per
message (``stamp tx ty tz qx qy qz qw``); stops ``--idle`` seconds after the last message.
"""

from __future__ import annotations

import argparse
import sys
import time


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m rsvo_ros.ros.record", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out")
    p.add_argument("--topic", default="/rsvo/odom")
    p.add_argument("--idle", type=float, default=5.0)
    p.add_argument("--timeout", type=float, default=600.0)
    args = p.parse_args(argv)

    import rclpy
    from nav_msgs.msg import Odometry
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    rclpy.init()
    node = rclpy.create_node("rsvo_record")
    last = [None]
    count = [0]
    f = open(args.out, "w")

    def on_odom(m):
        s = m.header.stamp.sec + m.header.stamp.nanosec * 1e-9
        pp, q = m.pose.pose.position, m.pose.pose.orientation
        f.write(f"{s:.9f} {pp.x:.9f} {pp.y:.9f} {pp.z:.9f} {q.x:.9f} {q.y:.9f} {q.z:.9f} "
                f"{q.w:.9f}\n")
        f.flush()
        last[0] = time.monotonic()
        count[0] += 1

    node.create_subscription(Odometry, args.topic, on_odom,
                             QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
    t_end = time.monotonic() + args.timeout
    ready = False
    try:
        while time.monotonic() < t_end:
            rclpy.spin_once(node, timeout_sec=0.1)
            if not ready and node.count_publishers(args.topic) > 0:
                ready = True
                time.sleep(1.0)  # let the endpoints match before anyone starts publishing
                open(args.out + ".ready", "w").close()
            if last[0] is not None and time.monotonic() - last[0] > args.idle:
                break
    except KeyboardInterrupt:
        pass
    finally:
        f.close()
        node.destroy_node()
        rclpy.try_shutdown()
    print(f"rsvo_record: {count[0]} messages of {args.topic} -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
