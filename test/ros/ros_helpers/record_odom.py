"""Test helper process: record /rsvo/odom (and /diagnostics) to a JSON file.

usage: record_odom.py OUT.json EXPECTED TIMEOUT_S
Writes OUT.json.ready once a /rsvo/odom publisher is discovered (the test starts the player
only then: volatile messages published before discovery are lost). Stops after EXPECTED
odometry messages (then 2 s more and two diagnostics published after them, so the last one
counts every frame), 5 s after the last one (a lossy link), or at TIMEOUT_S.
"""

import json
import sys
import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry, Path
from rclpy.qos import QoSProfile, ReliabilityPolicy

IDLE_S = 5.0


def main():
    out, expected, timeout = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
    rclpy.init()
    node = rclpy.create_node("odom_recorder")
    odom, diags, paths = [], [], []

    def on_odom(m):
        p, q = m.pose.pose.position, m.pose.pose.orientation
        odom.append({"stamp_ns": m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec,
                     "frame_id": m.header.frame_id, "child": m.child_frame_id,
                     "t_recv": time.time(),
                     "pose": [p.x, p.y, p.z, q.x, q.y, q.z, q.w]})

    def on_diag(m):
        for st in m.status:
            if st.name.startswith("rsvo_node"):
                level = st.level
                level = int.from_bytes(level, "little") if isinstance(level, bytes) else level
                row = {kv.key: kv.value for kv in st.values}
                row.update(message=st.message, level=int(level), t_recv=time.monotonic())
                diags.append(row)

    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(Odometry, "/rsvo/odom", on_odom, qos)
    node.create_subscription(Path, "/rsvo/path", lambda m: paths.append(len(m.poses)), qos)
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    t_end = time.monotonic() + timeout
    done_at = None
    ready = False
    while time.monotonic() < t_end:
        rclpy.spin_once(node, timeout_sec=0.1)
        if not ready and node.count_publishers("/rsvo/odom") > 0:
            ready = True
            time.sleep(1.0)  # let the endpoints match
            open(out + ".ready", "w").close()
        if len(odom) >= expected and done_at is None:
            done_at = time.monotonic()
        if (done_at is not None and time.monotonic() - done_at > 2.0
                and sum(d["t_recv"] > done_at for d in diags) >= 2):
            break
        if odom and time.time() - odom[-1]["t_recv"] > IDLE_S:
            break
    with open(out, "w") as f:
        json.dump({"odom": odom, "diagnostics": diags, "path_lengths": paths}, f)
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
