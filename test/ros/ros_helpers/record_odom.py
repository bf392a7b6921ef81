"""Test helper process: record /rsvo/odom (and /diagnostics, /tf, the map points, the keyframe
path, and finally /tf_static as a late subscriber sees it) to a JSON file.

usage: record_odom.py OUT.json EXPECTED TIMEOUT_S
Writes OUT.json.ready once a /rsvo/odom publisher is discovered (the test starts the player
only then: volatile messages published before discovery are lost). Stops after EXPECTED
odometry messages (then 2 s more and two diagnostics published after them, so the last one
counts every frame), 5 s after the last one (a lossy link), or at TIMEOUT_S.
"""

import json
import os
import sys
import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry, Path
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from tf2_msgs.msg import TFMessage

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

    tfs, clouds, keyframes, static = [], [], [], []

    def stamp(h):
        return h.stamp.sec * 1_000_000_000 + h.stamp.nanosec

    def on_tf(m):
        for t in m.transforms:
            tr, q = t.transform.translation, t.transform.rotation
            tfs.append({"stamp_ns": stamp(t.header), "parent": t.header.frame_id,
                        "child": t.child_frame_id, "pose": [tr.x, tr.y, tr.z, q.x, q.y, q.z,
                                                            q.w]})

    def on_cloud(m):
        clouds.append({"frame_id": m.header.frame_id, "width": m.width, "height": m.height,
                       "point_step": m.point_step, "bytes": len(m.data),
                       "fields": [[f.name, f.offset, f.datatype, f.count] for f in m.fields]})

    def on_static(m):
        for t in m.transforms:
            tr, q = t.transform.translation, t.transform.rotation
            static.append({"parent": t.header.frame_id, "child": t.child_frame_id,
                           "pose": [tr.x, tr.y, tr.z, q.x, q.y, q.z, q.w]})

    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(TFMessage, "/tf", on_tf, qos)
    node.create_subscription(PointCloud2, "/rsvo/map_points", on_cloud, qos)
    node.create_subscription(Path, "/rsvo/keyframes", lambda m: keyframes.append(
        [stamp(p.header) for p in m.poses]), qos)
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
    # a late subscriber (after every odometry message) still gets the latched static transform
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    node.create_subscription(TFMessage, "/tf_static", on_static, latched)
    t_static = time.monotonic() + 5.0
    while time.monotonic() < t_static and not static:
        rclpy.spin_once(node, timeout_sec=0.1)
    tf_hashes = sorted({str(i.topic_type_hash) for i in node.get_publishers_info_by_topic("/tf")})
    # written whole, then renamed: the test polls for OUT.json and must never read half of it
    with open(out + ".part", "w") as f:
        json.dump({"odom": odom, "diagnostics": diags, "path_lengths": paths, "tf": tfs,
                   "clouds": clouds, "keyframes": keyframes, "tf_static": static,
                   "tf_type_hashes": tf_hashes}, f)
    os.replace(out + ".part", out)
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
