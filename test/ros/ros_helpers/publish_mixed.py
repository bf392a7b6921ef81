"""Test helper process: publish a synthetic sequence with bad images mixed in.

usage: publish_mixed.py BAG_FRAMES_SEED
Good frames from rsvo_synth's renderer (vehicle, 320x180), and between them: an unsupported
encoding, a size/step mismatch, an empty image and a truncated payload. Prints how many good
frames it sent.
"""

import sys
import time

import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image

from rsvo_ros.sim.synth import SequenceRenderer, SynthConfig


def main():
    frames = int(sys.argv[1])
    rclpy.init()
    node = rclpy.create_node("mixed_publisher")
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    pub_img = node.create_publisher(Image, "/camera/image_raw", qos)
    pub_info = node.create_publisher(CameraInfo, "/camera/camera_info", qos)
    t_end = time.monotonic() + 30
    while time.monotonic() < t_end and (pub_img.get_subscription_count() == 0
                                        or pub_info.get_subscription_count() == 0):
        time.sleep(0.05)
    time.sleep(1.0)
    cfg = SynthConfig(frames=frames, motion="vehicle", severity=1.0, width=320, height=180)
    renderer = SequenceRenderer(cfg)
    good = 0
    for k, fr in enumerate(renderer):
        ns = round(fr.stamp * 1e9)
        info = CameraInfo()
        info.header.stamp.sec, info.header.stamp.nanosec = ns // 10**9, ns % 10**9
        info.width, info.height = cfg.width, cfg.height
        info.k = [float(x) for x in renderer.K.ravel()]
        pub_info.publish(info)
        time.sleep(0.02)  # the camera info first, as a driver would
        img = Image()
        img.header.stamp = info.header.stamp
        img.header.frame_id = "camera_optical_frame"
        img.height, img.width, img.encoding, img.step = 180, 320, "mono8", 320
        img.data = fr.image.tobytes()
        bad = k % 3 == 1  # every third frame is replaced by a bad one
        if bad:
            kind = (k // 3) % 4
            if kind == 0:
                img.encoding = "32FC1"  # a depth image
            elif kind == 1:
                img.step = 100  # shorter than a row
            elif kind == 2:
                img.height, img.width, img.step, img.data = 0, 0, 0, b""
            else:
                img.data = fr.image.tobytes()[:1000]
        else:
            good += 1
        pub_img.publish(img)
        time.sleep(0.18)  # ~5 Hz
    time.sleep(1.0)
    print(f"sent {good} good frames", flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
