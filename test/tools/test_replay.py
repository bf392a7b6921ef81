"""rsvo_replay over rosbag2 files: outputs, accounting of every frame, bad input."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import Reader
from scipy.spatial.transform import Rotation

from rsvo_ros.odometry.pairwise import (
    BOOTSTRAP_UNCERTAIN_ROTATION_DEG,
    UNCERTAIN_PAIR_ROTATION_DEG,
)
from rsvo_ros.odometry.tracker import DEFAULT_WINDOW_PX
from rsvo_ros.ros import bagio
from rsvo_ros.sim.synth import SequenceRenderer, SynthConfig
from rsvo_ros.tools.replay import main as replay_main
from rsvo_ros.tools.replay import scale_rate
from rsvo_ros.tools.synth_bag import write_bag


@pytest.fixture(scope="module")
def vehicle_bag(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("bags") / "vehicle"
    write_bag(path, SynthConfig(frames=8, motion="vehicle", severity=1.0, width=320,
                                height=180, seed=1), "mcap", progress=False)
    return path


def _topics(path):
    with Reader(path) as r:
        return {c.topic: c.msgcount for c in r.connections}


@pytest.mark.parametrize("model, extra", [("gs", []), ("rs", []), ("rs", ["--no-motion-prior"]),
                                          ("rs", ["--backend", "pairwise"])])
def test_replay_writes_every_output(vehicle_bag, tmp_path, model, extra, capsys):
    out = tmp_path / model
    assert replay_main([str(vehicle_bag), "--output", str(out), "--model", model,
                        "--no-progress", *extra]) == 0
    assert "frames posed" in capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["motion_prior"] == ("--no-motion-prior" not in extra)
    assert summary["backend"] == ("pairwise" if "pairwise" in extra else "window")
    if summary["backend"] == "window":  # its keyframes, and their velocities against the truth
        kf = summary["keyframes"]
        assert kf["count"] >= 2 and kf["w_compared"] >= 2
        assert 0 <= kf["w_rel_error_median"] < 5
        vel = kf["velocities"]  # every keyframe's row-0 velocities, in stamp order
        assert len(vel) == kf["count"]
        assert [r["stamp_ns"] for r in vel] == sorted(r["stamp_ns"] for r in vel)
        assert np.isfinite([r["w"] + r["v"] for r in vel]).all()
        assert any(f["keyframe"] for f in summary["frames"])
    assert summary["frames_in"] == 8 == summary["frames_in_bag"]
    assert summary["frames_posed"] + summary["frames_skipped"] == summary["frames_in"]
    assert summary["frames_posed"] >= 7
    lines = (out / "trajectory.tum").read_text().splitlines()
    assert len(lines) == summary["frames_posed"]
    vals = np.array([[float(x) for x in ln.split()] for ln in lines])
    assert vals.shape[1] == 8 and np.isfinite(vals).all()
    assert np.allclose(np.linalg.norm(vals[:, 4:], axis=1), 1.0)  # unit quaternions
    topics = _topics(out / "odometry")
    n = summary["frames_posed"]
    assert {t: topics[t] for t in ("/rsvo/odom", "/tf")} == {"/rsvo/odom": n, "/tf": n}
    # the path at most every 0.1 s of bag time (30 Hz: every third frame) and with the last
    # frame; that one holds every pose
    stamps = np.round(vals[:, 0] * 1e9).astype(np.int64)
    written = [stamps[0]]
    for s in stamps[1:]:
        if s - written[-1] >= 100_000_000:
            written.append(s)
    if written[-1] != stamps[-1]:
        written.append(stamps[-1])
    assert topics["/rsvo/path"] == len(written) < n
    with Reader(out / "odometry") as r:
        conns = [c for c in r.connections if c.topic == "/rsvo/path"]
        paths = [bagio.deserialize(raw, c.msgtype) for c, _t, raw in r.messages(connections=conns)]
    assert [p.header.stamp.sec * 10**9 + p.header.stamp.nanosec for p in paths] == written
    last = paths[-1].poses
    assert [p.header.stamp.sec * 10**9 + p.header.stamp.nanosec for p in last] == list(stamps)
    assert np.allclose([last[-1].pose.position.x, last[-1].pose.position.y,
                        last[-1].pose.position.z], vals[-1, 1:4], atol=1e-6)
    # map points and keyframes at most once per second of bag time, and at the end
    assert 1 <= topics["/rsvo/map_points"] == topics["/rsvo/keyframes"] <= 3
    with Reader(out / "odometry") as r:
        conns = [c for c in r.connections if c.topic in ("/tf", "/rsvo/map_points")]
        last = {}
        for c, _t, raw in r.messages(connections=conns):
            last[c.topic] = bagio.deserialize(raw, c.msgtype)
    (tf,) = last["/tf"].transforms
    assert (tf.header.frame_id, tf.child_frame_id) == ("odom", "camera_optical_frame")
    cloud = last["/rsvo/map_points"]
    assert [(f.name, f.offset, f.datatype) for f in cloud.fields] == \
        [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)]
    assert cloud.header.frame_id == "odom" and len(cloud.data) == 12 * cloud.width
    if summary["backend"] == "window":
        assert cloud.width >= 20
        assert (out / "keyframes.tum").read_text().count("\n") == summary["keyframes"]["count"]
    # the odometry's twist: none for the first pose (covariance 1e6), then the motion since the
    # last pose in the camera frame, with a measured covariance once there are enough of them
    with Reader(out / "odometry") as r:
        conns = [c for c in r.connections if c.topic == "/rsvo/odom"]
        odoms = [bagio.deserialize(raw, c.msgtype) for c, _t, raw in r.messages(connections=conns)]
    covs = np.array([np.reshape(o.twist.covariance, (6, 6)) for o in odoms])
    known = [i for i in range(len(odoms)) if not np.all(covs[i].diagonal() == 1e6)]
    assert np.allclose(covs[0].diagonal(), 1e6)
    assert summary["twist"]["known"] == len(known) and (not known or known[0] >= 2)
    for i in known:
        ang = odoms[i].twist.twist.angular
        dt = vals[i, 0] - vals[i - 1, 0]
        R0, R1 = (Rotation.from_quat(vals[j, 4:]).as_matrix() for j in (i - 1, i))
        assert np.allclose([ang.x, ang.y, ang.z], Rotation.from_matrix(R0.T @ R1).as_rotvec() / dt,
                           atol=1e-6)
        lin = odoms[i].twist.twist.linear
        assert np.allclose([lin.x, lin.y, lin.z], R1.T @ (vals[i, 1:4] - vals[i - 1, 1:4]) / dt,
                           atol=1e-6)
    assert summary["twist"].get("angular_compared", 0) == len(known)
    assert summary["twist"].get("interval_compared", 0) == len(known)
    acc = summary["accuracy"]
    assert acc["matched_poses"] == summary["frames_posed"]
    assert np.isfinite(acc["ate_m"]["rmse"]) and acc["ate_m"]["rmse"] < 1.0
    assert (out / "trajectory.png").stat().st_size > 10_000


def _write_bad_bag(path: Path) -> int:
    """Good frames mixed with an unsupported encoding, a truncated image, a duplicate and a
    backwards stamp, and one image before any camera info. Returns the image count."""
    cfg = SynthConfig(frames=8, motion="vehicle", severity=0.5, width=320, height=180, seed=3)
    renderer = SequenceRenderer(cfg)
    frames = list(renderer)
    ts = bagio.typestore()
    writer = bagio.open_writer(path, "sqlite3")
    n = 0
    with writer:
        writer.set_custom_data(bagio.LINE_DELAY_KEY, str(cfg.tau))
        ci = writer.add_connection(bagio.IMAGE_TOPIC, bagio.IMAGE_TYPE, typestore=ts)
        cc = writer.add_connection(bagio.CAMERA_INFO_TOPIC, bagio.CAMERA_INFO_TYPE, typestore=ts)
        for k, fr in enumerate(frames):
            stamp = 1_000_000_000 + round(fr.stamp * 1e9)
            msg = bagio.image_msg(stamp, fr.image)
            if k == 2:
                msg.encoding = "32FC1"  # a depth image
            if k == 4:
                msg.data = msg.data[: len(msg.data) // 2]
            writer.write(ci, stamp, bagio.serialize(msg))
            n += 1
            if k == 0:
                continue  # the first image comes before any camera info
            writer.write(cc, stamp, bagio.serialize(
                bagio.camera_info_msg(stamp, renderer.K, cfg.width, cfg.height)))
            if k == 5:  # the same image again, then one from a few ms ago (a late frame)
                writer.write(ci, stamp + 1, bagio.serialize(bagio.image_msg(stamp, fr.image)))
                writer.write(ci, stamp + 2, bagio.serialize(
                    bagio.image_msg(stamp - 10_000_000, frames[3].image)))
                n += 2
            if k == 6:  # a corrupt header: 1000 s in the future
                writer.write(ci, stamp + 1, bagio.serialize(
                    bagio.image_msg(stamp + 1000 * 10**9, frames[6].image)))
                n += 1
    return n


def test_the_odometry_twist_follows_the_true_turn_rate(tmp_path):
    """A smooth drive: after its first frames every odometry message carries a twist with a
    measured covariance, and the published turn rate is near the truth."""
    bag = tmp_path / "drive"
    write_bag(bag, SynthConfig(frames=24, motion="vehicle", severity=0.3, width=320,
                               height=180, seed=4), "sqlite3", progress=False)  # fmt: skip
    out = tmp_path / "out"
    assert replay_main([str(bag), "--output", str(out), "--no-progress"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    tw = summary["twist"]
    assert tw["frames"] == summary["frames_posed"] == 24
    assert tw["known"] >= 12 and tw["angular_compared"] == tw["interval_compared"] == tw["known"]
    # against the true motion over the same intervals, and the true rate at the stamps
    assert tw["angular_error_vs_interval_deg_s_median"] < 0.2 * tw["angular_interval_deg_s_median"]
    assert tw["linear_rel_error_vs_interval_median"] < 0.2  # after the Sim(3) scale
    assert tw["angular_error_deg_s_median"] < 0.5 * tw["angular_true_deg_s_median"]
    assert tw["angular_within_2_sigma"] > 0.8


def test_bad_messages_are_counted_and_the_rest_is_processed(tmp_path):
    bag = tmp_path / "bad"
    n = _write_bad_bag(bag)
    out = tmp_path / "out"
    assert replay_main([str(bag), "--output", str(out), "--model", "gs", "--no-progress"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["frames_in"] == n
    assert s["frames_posed"] + s["frames_skipped"] == n
    reasons = " | ".join(s["skipped_reasons"])
    for word in ("unsupported encoding", "bytes", "duplicate", "backwards", "far ahead"):
        assert word in reasons, reasons
    assert s["frames_posed"] >= 4
    assert s["time_resets"] == 0 and len(s["trajectories"]) == 1  # the clock was kept


def test_looped_bag_gives_two_trajectories(tmp_path, capsys):
    """The sequence twice with the same stamps (``ros2 bag play -l``): time jumps back, the
    odometry resets and the second trajectory is the first again."""
    cfg = SynthConfig(frames=10, motion="vehicle", severity=1.0, width=320, height=180, seed=1)
    frames = list(SequenceRenderer(cfg))
    renderer = SequenceRenderer(cfg)
    bag = tmp_path / "looped"
    ts = bagio.typestore()
    with bagio.open_writer(bag, "sqlite3") as writer:
        writer.set_custom_data(bagio.LINE_DELAY_KEY, str(cfg.tau))
        ci = writer.add_connection(bagio.IMAGE_TOPIC, bagio.IMAGE_TYPE, typestore=ts)
        cc = writer.add_connection(bagio.CAMERA_INFO_TOPIC, bagio.CAMERA_INFO_TYPE, typestore=ts)
        t_log = 0
        for _loop in range(2):
            for fr in frames:
                stamp = 1_000_000_000 + round(fr.stamp * 1e9)
                t_log += 1
                writer.write(cc, t_log, bagio.serialize(
                    bagio.camera_info_msg(stamp, renderer.K, cfg.width, cfg.height)))
                writer.write(ci, t_log, bagio.serialize(bagio.image_msg(stamp, fr.image)))
    out = tmp_path / "out"
    assert replay_main([str(bag), "--output", str(out), "--no-progress"]) == 0
    assert "time went back 1 time(s): the odometry reset and started 2 trajectories" in \
        capsys.readouterr().out
    s = json.loads((out / "summary.json").read_text())
    assert s["time_resets"] == 1 and s["frames_posed"] == 20
    assert s["twist"]["frames"] == 20  # both passes' odometry, though their stamps repeat
    assert [t["frames"] for t in s["trajectories"]] == [10, 10]
    assert s["frames"][10]["status"] == "first" and "time jumped back" in s["frames"][10]["reason"]
    poses = np.array([[float(x) for x in ln.split()[1:]]
                      for ln in (out / "trajectory.tum").read_text().splitlines()])
    assert np.allclose(poses[:10], poses[10:], atol=1e-9)  # a reset is a fresh start
    assert np.ptp(poses[:10, :3], axis=0).max() > 0.01  # and it moved


@pytest.mark.parametrize("case, message", [
    ("missing", "cannot read bag"),
    ("image_topic", "no image topic /nope"),
    ("camera_info", "camera info topic"),
    ("line_delay", "--line-delay"),
    ("truncated", "cannot read bag"),
    ("line_delay_text", "not a number"),
])
def test_unusable_bags_fail_with_one_line(vehicle_bag, tmp_path, capsys, case, message):
    args = [str(vehicle_bag), "--output", str(tmp_path / "o"), "--no-progress"]
    if case == "missing":
        args[0] = str(tmp_path / "does-not-exist")
    elif case == "image_topic":
        args += ["--image-topic", "/nope"]
    elif case == "camera_info":
        args += ["--camera-info-topic", "/nope"]
    elif case == "line_delay":
        bag = tmp_path / "nold"
        cfg = SynthConfig(frames=2, width=64, height=36)
        write_bag(bag, cfg, "sqlite3", progress=False)
        meta = (bag / "metadata.yaml").read_text().replace("rsvo.line_delay", "other.key")
        (bag / "metadata.yaml").write_text(meta)
        args[0] = str(bag)
    elif case == "line_delay_text":
        bag = tmp_path / "badld"
        write_bag(bag, SynthConfig(frames=2, width=64, height=36), "sqlite3", progress=False)
        meta = (bag / "metadata.yaml").read_text()
        meta = meta.replace(next(ln for ln in meta.splitlines() if "rsvo.line_delay" in ln),
                            "    rsvo.line_delay: fast")
        (bag / "metadata.yaml").write_text(meta)
        args[0] = str(bag)
    elif case == "truncated":
        bag = tmp_path / "trunc"
        write_bag(bag, SynthConfig(frames=3, width=64, height=36), "mcap", progress=False)
        data = next(bag.glob("*.mcap"))
        data.write_bytes(data.read_bytes()[:200])
        args[0] = str(bag)
    code = replay_main(args)
    err = capsys.readouterr().err.strip()
    assert code == 1
    assert message in err and len(err.splitlines()) == 1


def test_compressed_image_bags_replay_as_the_raw_ones(tmp_path, capsys):
    """image_transport's compressed topic: PNG gives the raw bag's trajectory exactly, JPEG
    one close to it; found without --image-topic when it is the bag's only camera; a frame
    that does not decode is one counted skip."""
    cfg = SynthConfig(frames=12, motion="vehicle", severity=1.0, width=320, height=180, seed=1)
    runs = {}
    for kind in ("raw", "png", "jpeg"):
        bag = tmp_path / kind
        write_bag(bag, cfg, "sqlite3", progress=False,
                  compressed=None if kind == "raw" else kind)
        assert (bagio.IMAGE_TOPIC + "/compressed" in _topics(bag)) == (kind != "raw")
        out = tmp_path / f"out_{kind}"
        assert replay_main([str(bag), "--output", str(out), "--no-progress"]) == 0
        err = capsys.readouterr().err
        assert ("using its only image topic /camera/image_raw/compressed" in err) == \
            (kind != "raw")
        runs[kind] = (json.loads((out / "summary.json").read_text()),
                      (out / "trajectory.tum").read_text())
    assert runs["png"][1] == runs["raw"][1]  # lossless: the same frames, the same poses
    assert runs["png"][0]["image_topic"] == "/camera/image_raw/compressed"
    ate = {k: v[0]["accuracy"]["ate_m"]["rmse"] for k, v in runs.items()}
    assert runs["jpeg"][0]["frames_posed"] == 12
    assert ate["jpeg"] < 2.0 * ate["raw"] + 0.01, ate

    # one undecodable frame in the middle of a compressed bag
    bad = tmp_path / "bad_jpeg"
    renderer = SequenceRenderer(cfg)
    ts = bagio.typestore()
    with bagio.open_writer(bad, "sqlite3") as writer:
        writer.set_custom_data(bagio.LINE_DELAY_KEY, str(cfg.tau))
        ci = writer.add_connection("/cam/compressed", bagio.COMPRESSED_IMAGE_TYPE, typestore=ts)
        cc = writer.add_connection(bagio.CAMERA_INFO_TOPIC, bagio.CAMERA_INFO_TYPE, typestore=ts)
        for k, fr in enumerate(renderer):
            stamp = round(fr.stamp * 1e9)
            msg = bagio.compressed_image_msg(stamp, fr.image, "jpeg")
            if k == 5:
                msg.data = msg.data[:100]  # a cut-off JPEG
            writer.write(cc, stamp, bagio.serialize(
                bagio.camera_info_msg(stamp, renderer.K, cfg.width, cfg.height)))
            writer.write(ci, stamp, bagio.serialize(msg))
    out = tmp_path / "out_bad"
    assert replay_main([str(bad), "--output", str(out), "--image-topic", "/cam/compressed",
                        "--no-progress"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["frames_in"] == 12 and s["frames_posed"] == 11
    assert s["skipped_reasons"] == {"cannot decode the compressed image": 1}
    # a topic that is not an image says which ones are
    code = replay_main([str(bad), "--output", str(tmp_path / "o2"), "--image-topic",
                        bagio.CAMERA_INFO_TOPIC, "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert code == 1 and len(err.splitlines()) == 1
    assert "is sensor_msgs/msg/CameraInfo, not" in err and "/cam/compressed" in err


def test_a_ros1_bag_replays_as_its_rosbag2_original(vehicle_bag, tmp_path, capsys):
    """A ROS 1 .bag (rosbags-convert of the rosbag2, CameraInfo's K and D in capitals):
    the same trajectory and ground truth; it records no line delay, so the RS model asks for
    one in one line."""
    from rosbags.convert import convert
    from rosbags.typesys import Stores, get_typestore

    ros1 = tmp_path / "vehicle.bag"
    convert([vehicle_bag], ros1, "sqlite3", 0, None, "none", None,
            get_typestore(Stores.ROS1_NOETIC), [], [], [], [])  # fmt: skip
    with bagio.BagReader(ros1) as reader:
        assert reader.ros1
        info = next(c for c in reader.connections if c.topic == bagio.CAMERA_INFO_TOPIC)
        _c, _t, raw = next(iter(reader.messages(connections=[info])))
        assert hasattr(reader.deserialize(raw, info.msgtype), "K")  # ROS 1's spelling
    line_delay = bagio.custom_data(vehicle_bag)[bagio.LINE_DELAY_KEY]
    outs = {}
    for name, bag in (("ros2", vehicle_bag), ("ros1", ros1)):
        outs[name] = tmp_path / name
        assert replay_main([str(bag), "--output", str(outs[name]), "--line-delay", line_delay,
                            "--no-progress"]) == 0
    assert (outs["ros1"] / "trajectory.tum").read_text() == \
        (outs["ros2"] / "trajectory.tum").read_text()
    acc = [json.loads((outs[k] / "summary.json").read_text())["accuracy"] for k in outs]
    assert acc[0]["matched_poses"] == acc[1]["matched_poses"] == 8  # the ground truth was read
    capsys.readouterr()
    assert replay_main([str(ros1), "--output", str(tmp_path / "o"), "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert "does not record rsvo.line_delay" in err and len(err.splitlines()) == 1


@pytest.mark.parametrize("gt_type", ["geometry_msgs/msg/PoseStamped",
                                     "geometry_msgs/msg/TransformStamped"])
def test_a_motion_capture_ground_truth_is_resampled_at_the_frames(tmp_path, gt_type):
    """Ground truth at its own rate (200 Hz, stamps between the frames', as from motion
    capture), as PoseStamped or TransformStamped: interpolated at the frames, the accuracy is
    the one with the ground truth at the frames' stamps."""
    cfg = SynthConfig(frames=20, motion="vehicle", severity=1.0, width=320, height=180, seed=1)
    ref_bag = tmp_path / "ref"
    write_bag(ref_bag, cfg, "sqlite3", progress=False)
    renderer = SequenceRenderer(cfg)
    ts = bagio.typestore()
    bag = tmp_path / "mocap"
    with bagio.open_writer(bag, "sqlite3") as writer:
        writer.set_custom_data(bagio.LINE_DELAY_KEY, str(cfg.tau))
        ci = writer.add_connection(bagio.IMAGE_TOPIC, bagio.IMAGE_TYPE, typestore=ts)
        cc = writer.add_connection(bagio.CAMERA_INFO_TOPIC, bagio.CAMERA_INFO_TYPE, typestore=ts)
        cg = writer.add_connection("/mocap", gt_type, typestore=ts)
        for fr in renderer:
            stamp = round(fr.stamp * 1e9)
            writer.write(cc, stamp, bagio.serialize(
                bagio.camera_info_msg(stamp, renderer.K, cfg.width, cfg.height)))
            writer.write(ci, stamp, bagio.serialize(bagio.image_msg(stamp, fr.image)))
        t_mocap = np.arange(-0.01, cfg.frames / 30.0 + 0.01, 0.005) + 0.0013
        R, p = renderer.trajectory.pose(t_mocap)
        for t, Rk, pk in zip(t_mocap, R, p, strict=True):
            stamp = round(t * 1e9)
            head = bagio.header(stamp, "world")
            q = bagio.pose_msg(Rk, pk)
            if gt_type.endswith("PoseStamped"):
                msg = ts.types[gt_type](header=head, pose=q)
            else:
                tr = ts.types["geometry_msgs/msg/Vector3"](x=q.position.x, y=q.position.y,
                                                           z=q.position.z)
                msg = ts.types[gt_type](header=head, child_frame_id="camera", transform=ts.types[
                    "geometry_msgs/msg/Transform"](translation=tr, rotation=q.orientation))
            writer.write(cg, stamp, bagio.serialize(msg))
    summaries = {}
    for name, b, extra in (("ref", ref_bag, []), ("mocap", bag, ["--ground-truth-topic",
                                                                  "/mocap"])):
        out = tmp_path / f"out_{name}"
        assert replay_main([str(b), "--output", str(out), "--no-progress", *extra]) == 0
        summaries[name] = json.loads((out / "summary.json").read_text())
    gt = summaries["mocap"]["ground_truth"]
    assert gt["type"] == gt_type and gt["resampled"] and gt["frames_covered"] == 20
    assert summaries["ref"]["ground_truth"]["resampled"] is False
    a, b = (summaries[k]["accuracy"] for k in ("ref", "mocap"))
    assert a["matched_poses"] == b["matched_poses"] == 20
    assert b["ate_m"]["rmse"] == pytest.approx(a["ate_m"]["rmse"], rel=0.02, abs=2e-4)
    assert b["rpe_rot_deg"]["mean"] == pytest.approx(a["rpe_rot_deg"]["mean"], rel=0.05, abs=2e-3)


def _rewrite_bag(src: Path, dst: Path, rewrite) -> None:
    """Copy ``src`` (and its line delay) into the rosbag2 ``dst``, each message through
    ``rewrite(conn, raw, reader)``: the ``(topic, msgtype, raw)`` to write for it (none:
    dropped)."""
    ts = bagio.typestore()
    with bagio.BagReader(src) as reader, bagio.open_writer(dst, "sqlite3") as writer:
        writer.set_custom_data(bagio.LINE_DELAY_KEY,
                               bagio.custom_data(src)[bagio.LINE_DELAY_KEY])
        conns = {}
        for c, t, raw in reader.messages(connections=reader.connections):
            for topic, msgtype, data in rewrite(c, raw, reader):
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
                writer.write(conns[topic], t, data)


def test_a_calibration_file_stands_in_for_the_camera_info_topic(vehicle_bag, tmp_path,
                                                                 capsys):  # fmt: skip
    """--camera-file (a Kalibr camchain here): a bag without camera info replays as the bag
    with it; a bad file is a one-line error."""
    K = SequenceRenderer(SynthConfig(width=320, height=180)).K
    calib = tmp_path / "camchain.yaml"
    fu_fv_pu_pv = [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])]
    calib.write_text("cam0:\n  camera_model: pinhole\n  distortion_model: none\n"
                     f"  distortion_coeffs: []\n  intrinsics: {fu_fv_pu_pv}\n"
                     "  resolution: [320, 180]\n")
    bare = tmp_path / "no_info"
    _rewrite_bag(vehicle_bag, bare, lambda c, raw, _r: [] if c.topic == bagio.CAMERA_INFO_TOPIC
                 else [(c.topic, c.msgtype, raw)])  # fmt: skip
    assert bagio.CAMERA_INFO_TOPIC not in _topics(bare)
    assert replay_main([str(bare), "--output", str(tmp_path / "o0"), "--no-progress"]) == 1
    assert "give --camera-info-topic or --camera-file" in capsys.readouterr().err
    outs = {}
    for name, bag, extra in (("topic", vehicle_bag, []),
                             ("file", bare, ["--camera-file", str(calib)])):
        outs[name] = tmp_path / name
        assert replay_main([str(bag), "--output", str(outs[name]), "--no-progress",
                            *extra]) == 0
    assert (outs["file"] / "trajectory.tum").read_text() == \
        (outs["topic"] / "trajectory.tum").read_text()
    assert json.loads((outs["file"] / "summary.json").read_text())["camera_file"] == str(calib)
    capsys.readouterr()
    assert replay_main([str(bare), "--output", str(tmp_path / "o1"), "--camera-file",
                        str(calib), "--camera-entry", "cam1", "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert "no camera 'cam1'" in err and len(err.splitlines()) == 1


def test_rectified_images_take_the_projection_and_no_lens(vehicle_bag, tmp_path):
    """--rectified (image_rect with the raw camera's CameraInfo): P's intrinsics and no
    undistortion. The bag's undistorted images with a lens in their CameraInfo replay as the
    lens-free original with the flag, and differently without it."""
    def with_a_lens(c, raw, reader):
        if c.topic == bagio.CAMERA_INFO_TOPIC:
            msg = reader.deserialize(raw, c.msgtype)
            K = np.array(msg.k).reshape(3, 3)
            msg.d = np.array([-0.3, 0.1, 0.001, 0.002, 0.0])  # the raw camera's lens
            msg.k = (K * [[1.1, 1, 1.1], [1, 1.1, 1.1], [1, 1, 1]]).ravel()  # its K
            raw = bagio.serialize(msg)
        return [(c.topic, c.msgtype, raw)]

    rect = tmp_path / "rect"
    _rewrite_bag(vehicle_bag, rect, with_a_lens)
    runs = {}
    for name, bag, extra in (("original", vehicle_bag, []), ("rect", rect, ["--rectified"]),
                             ("raw", rect, [])):
        out = tmp_path / name
        assert replay_main([str(bag), "--output", str(out), "--no-progress", *extra]) == 0
        runs[name] = (out / "trajectory.tum").read_text()
    assert runs["rect"] == runs["original"]
    assert runs["raw"] != runs["original"]  # K and the lens were applied to rectified images


def test_an_uncalibrated_cameras_bag_replays_with_an_assumed_focal_length(vehicle_bag, tmp_path,
                                                                          capsys):  # fmt: skip
    """A camera driver without a calibration file publishes K all zero: every image skipped,
    the reason naming --uncalibrated-focal-factor; with it, a pinhole of that many image
    widths. The synthetic camera's own factor (0.78125: 250 px at 320 px) gives the
    calibrated replay's accuracy; a guess 28 % off (1.0) still poses every frame."""
    def uncalibrated(c, raw, reader):
        if c.topic == bagio.CAMERA_INFO_TOPIC:
            msg = reader.deserialize(raw, c.msgtype)
            msg.k, msg.d = np.zeros(9), np.zeros(0)
            raw = bagio.serialize(msg)
        return [(c.topic, c.msgtype, raw)]

    bag = tmp_path / "uncalibrated"
    _rewrite_bag(vehicle_bag, bag, uncalibrated)
    runs = {}
    for name, b, extra in (("original", vehicle_bag, []), ("refused", bag, []),
                           ("right", bag, ["--uncalibrated-focal-factor", "0.78125"]),
                           ("guess", bag, ["--uncalibrated-focal-factor", "1.0"])):
        out = tmp_path / name
        replay_main([str(b), "--output", str(out), "--no-progress", *extra])
        runs[name] = json.loads((out / "summary.json").read_text())
    refused = runs["refused"]
    assert refused["frames_posed"] == 0
    assert any("uncalibrated" in k and "uncalibrated-focal-factor" in k
               for k in refused["skipped_reasons"]), refused["skipped_reasons"]
    assert "assuming a pinhole camera of focal length 250.0 px" in capsys.readouterr().out
    ate = {k: r["accuracy"]["ate_m"]["rmse"] for k, r in runs.items() if k != "refused"}
    for name in ("right", "guess"):
        r = runs[name]
        assert r["intrinsics"] == "assumed" and r["frames_posed"] == r["frames_in"] == 8
        assert np.isfinite(ate[name])
    assert runs["original"]["intrinsics"] == "camera info"
    assert ate["right"] == pytest.approx(ate["original"], rel=0.1), ate
    assert replay_main([str(bag), "--output", str(tmp_path / "x"), "--no-progress",
                        "--uncalibrated-focal-factor", "-1"]) == 2
    # rsvo_calibrate takes the same flag (the bag is too short for an estimate either way)
    from rsvo_ros.tools.calibrate import main as calibrate_main

    capsys.readouterr()
    yaml_out = str(tmp_path / "ld.yaml")
    assert calibrate_main([str(bag), "--output", yaml_out, "--no-progress"]) == 1
    assert "rsvo_calibrate: --uncalibrated-focal-factor" in capsys.readouterr().err
    assert calibrate_main([str(bag), "--output", yaml_out, "--no-progress",
                           "--uncalibrated-focal-factor", "0.78125"]) == 1
    err = capsys.readouterr().err
    assert "no estimate" in err and "uncalibrated" not in err
    assert calibrate_main([str(bag), "--output", yaml_out, "--no-progress",
                           "--uncalibrated-focal-factor", "nan"]) == 2


def _poison_the_window(monkeypatch, from_stamp_ns: int, focal: float) -> None:
    """From ``from_stamp_ns`` on, the window backend of the camera with focal length
    ``focal`` (not the warm-up's) raises on every frame, as a state gone bad would, until the
    pipeline makes a new one (a reset)."""
    from rsvo_ros.odometry.window import WindowOdometry

    poisoned = []
    track = WindowOdometry.track

    def failing(self, stamp_ns, obs, hint=None, memory_from_hint=None):
        if self.K[0, 0] == focal and stamp_ns >= from_stamp_ns and not poisoned:
            poisoned.append(self)
        if poisoned and self is poisoned[0]:
            raise RuntimeError("state gone bad")
        return track(self, stamp_ns, obs, hint, memory_from_hint)

    monkeypatch.setattr(WindowOdometry, "track", failing)


def test_a_fault_that_stays_resets_the_odometry_after_three_frames(
        vehicle_bag, tmp_path, monkeypatch, capsys):
    """A fault of the package that the pipeline's state carries on (every frame from the
    third raises): before, every later frame was skipped; now three in a row reset the
    odometry, and the frames after it are posed in a new trajectory."""
    _poison_the_window(monkeypatch, round(2e9 / 30), 250.0)
    out = tmp_path / "faults"
    assert replay_main([str(vehicle_bag), "--output", str(out), "--no-progress"]) == 0
    s = json.loads((out / "summary.json").read_text())
    errors = sum(n for k, n in s["skipped_reasons"].items() if k.startswith("processing error"))
    assert errors == 3 and s["fault_resets"] == 1
    assert [t["frames"] for t in s["trajectories"]] == [2, 3]
    assert "state gone bad" in capsys.readouterr().err  # the first traceback


def test_a_binned_cameras_bag_replays_as_its_plain_original(vehicle_bag, tmp_path, capsys):
    """REP 104: a camera info of the full-resolution calibration with binning 2 x 2 and a
    region of interest describes the bag's images (they were all skipped as 'image size
    differs from camera info')."""
    def binned(c, raw, reader):
        if c.topic == bagio.CAMERA_INFO_TOPIC:
            msg = reader.deserialize(raw, c.msgtype)
            K = np.array(msg.k).reshape(3, 3)
            msg.k = (K * [[2, 1, 2], [1, 2, 2], [1, 1, 1]] + [[0, 0, 40], [0, 0, 20], [0, 0, 0]]
                     ).ravel()  # full resolution, the region 40, 20 px from its corner
            msg.roi.x_offset, msg.roi.y_offset = 40, 20
            msg.roi.width, msg.roi.height = 2 * msg.width, 2 * msg.height
            msg.width, msg.height = 2 * msg.width + 100, 2 * msg.height + 50
            msg.binning_x = msg.binning_y = 2
            raw = bagio.serialize(msg)
        return [(c.topic, c.msgtype, raw)]

    bag = tmp_path / "binned"
    _rewrite_bag(vehicle_bag, bag, binned)
    runs = {}
    for name, b in (("original", vehicle_bag), ("binned", bag)):
        out = tmp_path / name
        assert replay_main([str(b), "--output", str(out), "--no-progress"]) == 0
        runs[name] = (out / "trajectory.tum").read_text()
    assert runs["binned"] == runs["original"]
    assert "binning 2 rows" in capsys.readouterr().out


def test_the_image_topics_own_camera_info_is_found_beside_it(vehicle_bag, tmp_path, capsys):
    """Two cameras (/cam0, /cam1), no /camera/camera_info: --image-topic /cam1/image_raw (or
    its compressed topic) takes /cam1/camera_info, not the other camera's."""
    def two_cameras(c, raw, reader):
        if c.topic == bagio.IMAGE_TOPIC:
            return [(f"/{cam}/image_raw", c.msgtype, raw) for cam in ("cam0", "cam1")]
        if c.topic != bagio.CAMERA_INFO_TOPIC:
            return []
        msg = reader.deserialize(raw, c.msgtype)
        msg.k = np.asarray(msg.k) * [1.3, 1, 1, 1, 1.3, 1, 1, 1, 1]  # another camera
        return [("/cam1/camera_info", c.msgtype, raw),
                ("/cam0/camera_info", c.msgtype, bagio.serialize(msg))]

    two = tmp_path / "two_cams"
    _rewrite_bag(vehicle_bag, two, two_cameras)
    runs = {}
    for name, bag, extra in (("ref", vehicle_bag, []),
                             ("cam1", two, ["--image-topic", "/cam1/image_raw"]),
                             ("cam0", two, ["--image-topic", "/cam0/image_raw"])):
        o = tmp_path / name
        assert replay_main([str(bag), "--output", str(o), "--no-progress", *extra]) == 0
        runs[name] = (o / "trajectory.tum").read_text()
        if name != "ref":
            assert f"using /{name}/camera_info (beside the image topic)" in \
                capsys.readouterr().err
    assert runs["cam1"] == runs["ref"] and runs["cam0"] != runs["ref"]
    capsys.readouterr()
    assert replay_main([str(two), "--output", str(tmp_path / "o"), "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()  # two cameras: which image topic is not guessed
    assert "image topics: /cam0/image_raw, /cam1/image_raw" in err


def test_the_debug_video_holds_every_processed_frame_with_its_tracks(vehicle_bag, tmp_path,
                                                                     capsys):  # fmt: skip
    import cv2

    video = tmp_path / "tracks.mp4"
    out = tmp_path / "o"
    assert replay_main([str(vehicle_bag), "--output", str(out), "--debug-video", str(video),
                        "--no-progress"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["debug_video"] == {"path": str(video), "frames": 8}
    cap = cv2.VideoCapture(str(video))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame)
    assert len(frames) == 8 and frames[0].shape == (180, 320, 3)
    assert abs(cap.get(cv2.CAP_PROP_FPS) - 30.0) < 0.5  # the bag's rate
    green = [int(((f[..., 1] > 150) & (f[..., 0] < 80) & (f[..., 2] < 80)).sum()) for f in frames]
    assert green[0] < 20 and min(green[1:]) > 100, green  # the first frame has no pair yet
    assert replay_main([str(vehicle_bag), "--output", str(tmp_path / "o2"), "--debug-video",
                        str(tmp_path / "nope" / "v.mp4"), "--no-progress"]) == 2
    assert "folder" in capsys.readouterr().err


def test_console_script(vehicle_bag, tmp_path):
    proc = subprocess.run([sys.executable, "-m", "rsvo_ros.tools.replay", str(vehicle_bag),
                           "--output", str(tmp_path / "o"), "--model", "gs"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "rsvo_replay" in proc.stderr  # the progress bar


@pytest.fixture(scope="module")
def walk_bag(tmp_path_factory) -> Path:
    bag = tmp_path_factory.mktemp("walk") / "walk"
    write_bag(bag, SynthConfig(frames=120, motion="walk", severity=1.0, seed=3,
                               line_delay=5e-5), progress=False)
    return bag


def test_replay_reports_the_scale_drift(walk_bag, tmp_path):
    """The whole run's Sim(3) scale against that of its first 60 frames (monocular scale
    drift; no run-away on 120 frames of walking)."""
    assert replay_main([str(walk_bag), "--output", str(tmp_path / "rep"), "--no-progress"]) == 0
    acc = json.loads((tmp_path / "rep" / "summary.json").read_text())["accuracy"]
    drift = acc["scale_drift"]
    assert drift["first_frames"] == 60
    assert np.isclose(drift["ratio"], acc["sim3_scale"] / drift["sim3_scale_first"])
    assert 0.7 < drift["ratio"] < 1.4
    rate = acc["scale_rate"]
    assert rate["windows"] > 20 and abs(rate["percent_per_s"]) < 30


def test_scale_rate_measures_a_shrinking_trajectory_and_skips_stops():
    t = np.arange(150) / 30.0
    gt = np.column_stack([8.0 * t, np.sin(t), np.zeros_like(t)])
    # positions whose local scale falls by 3 % per second: p(t) = integral of exp(b t) v dt
    b = np.log(0.97)
    est = np.column_stack([8.0 * np.expm1(b * t) / b, np.zeros_like(t), np.zeros_like(t)])
    est[:, 1] = np.cumsum(np.r_[0.0, np.diff(np.sin(t)) * np.exp(b * t[1:])])
    rate = scale_rate(t, gt, 2.0 * est)  # any overall scale
    assert rate is not None and np.isclose(rate["percent_per_s"], -3.0, atol=0.1)
    assert np.isclose(scale_rate(t, gt, gt)["percent_per_s"], 0.0, atol=1e-9)
    # a camera standing still has no displacement to compare: no windows, no figure
    still = np.zeros_like(gt)
    assert scale_rate(t, still, still + 0.001) is None
    assert scale_rate(t[:10], gt[:10], gt[:10]) is None  # shorter than three windows


def test_rsvo_calibrate_writes_a_parameter_file_the_node_can_load(walk_bag, tmp_path, capsys):
    import yaml

    from rsvo_ros.tools.calibrate import main as calibrate_main

    bag = walk_bag
    out = tmp_path / "calib.yaml"
    assert calibrate_main([str(bag), "--output", str(out), "--no-progress",
                           "--no-refine"]) == 0
    printed = capsys.readouterr().out
    assert "us/row" in printed and "frame intervals" in printed and "records 50.00" in printed
    assert "second pass" not in printed
    params = yaml.safe_load(out.read_text())["rsvo_node"]["ros__parameters"]
    assert params["line_delay_mode"] == "fixed"
    # 67.4 us/row for 50 (55.4 before the first map waited for translation parallax, which
    # starts this walk's map later): the estimate's spread on a 120-frame walk
    first = params["line_delay"]
    assert 0.7 * 5e-5 < first < 1.4 * 5e-5
    # by default refined in a second pass over the bag: that value goes into the file
    refined_out = tmp_path / "refined.yaml"
    assert calibrate_main([str(bag), "--output", str(refined_out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "refined in a second pass" in printed and f"first {first * 1e6:.2f} us/row" in printed
    text = refined_out.read_text()
    refined = yaml.safe_load(text)["rsvo_node"]["ros__parameters"]["line_delay"]
    assert "refined" in text.splitlines()[0] and refined != first
    assert abs(refined - 5e-5) < 0.2 * 5e-5
    # too short to see anything: a clear failure, no file
    short = tmp_path / "short"
    write_bag(short, SynthConfig(frames=12, motion="walk", seed=3), progress=False)
    assert calibrate_main([str(short), "--output", str(tmp_path / "no.yaml"),
                           "--no-progress"]) == 1
    assert "no estimate" in capsys.readouterr().err and not (tmp_path / "no.yaml").exists()


def test_two_passes_replay_with_the_first_pass_estimate(walk_bag, tmp_path, capsys):
    """--line-delay auto --two-pass: the online pass in OUTPUT/first_pass, then the bag again
    with its estimate fixed; without an estimate the online pass is the result."""
    out = tmp_path / "two"
    assert replay_main([str(walk_bag), "--output", str(out), "--line-delay", "auto",
                        "--two-pass", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "two passes: the figures above are the second pass's" in printed
    first = json.loads((out / "first_pass" / "summary.json").read_text())
    second = json.loads((out / "summary.json").read_text())
    estimate = first["line_delay_auto"]
    assert estimate["status"] in ("estimated", "converged")
    assert second["line_delay_s"] == estimate["line_delay_s"]
    assert second["line_delay_auto"] == estimate  # the estimate it was replayed with
    tp = second["two_pass"]
    assert tp["second_pass"] and tp["first_pass_ate_m"] == first["accuracy"]["ate_m"]["rmse"]
    assert (out / "trajectory.tum").exists() and (out / "first_pass" / "trajectory.tum").exists()
    # the second pass has no estimate of its own: every frame at the fixed line delay
    assert all(f["status"] in ("first", "posed", "held") for f in second["frames"])
    assert second["frames_posed"] == first["frames_posed"] == 120
    # a bag too short to estimate from: one pass, its outputs where a replay puts them
    short = tmp_path / "short"
    write_bag(short, SynthConfig(frames=12, motion="walk", seed=3), progress=False)
    assert replay_main([str(short), "--output", str(tmp_path / "one"), "--line-delay", "auto",
                        "--two-pass", "--no-progress"]) == 0
    assert "no second pass" in capsys.readouterr().out
    one = json.loads((tmp_path / "one" / "summary.json").read_text())
    assert not one["two_pass"]["second_pass"] and "collecting" in one["two_pass"]["reason"]
    assert (tmp_path / "one" / "trajectory.tum").exists()
    assert not (tmp_path / "one" / "first_pass").exists()
    # one pass says how many frames ran before the first estimate, and what to do about it
    assert replay_main([str(walk_bag), "--output", str(tmp_path / "online"), "--line-delay",
                        "auto", "--no-progress"]) == 0
    online = json.loads((tmp_path / "online" / "summary.json").read_text())
    firsts = [h["frames"] for h in online["line_delay_auto"]["history"]
              if h["line_delay_s"] is not None]
    # ... which processed the frames before its first estimate again with it: trajectory.tum
    # and the accuracy have their new poses, accuracy_as_published what was published
    rerun = online["line_delay_auto"]["reruns"][0]
    assert rerun["frames"] == firsts[0] - 1
    assert online["line_delay_auto"]["frames_revised"] == sum(
        r["frames"] for r in online["line_delay_auto"]["reruns"])
    assert rerun["line_delay_s"] == online["line_delay_auto"]["history"][0]["line_delay_s"]
    said = f"the frames before the first estimate were processed again with it ({rerun['frames']}"
    assert said + " frames with" in capsys.readouterr().out
    assert online["accuracy_as_published"]["ate_m"]["rmse"] != online["accuracy"]["ate_m"][
        "rmse"]
    tum = np.loadtxt(tmp_path / "online" / "trajectory.tum")
    assert len(tum) == len(np.unique(tum[:, 0])) == online["frames_posed"]
    # as the node runs: on from the first estimate, the frames before it as they ran
    assert replay_main([str(walk_bag), "--output", str(tmp_path / "node"), "--line-delay",
                        "auto", "--no-line-delay-rerun", "--no-progress"]) == 0
    node = json.loads((tmp_path / "node" / "summary.json").read_text())
    assert node["line_delay_auto"]["reruns"] == [] and "accuracy_as_published" not in node
    assert node["accuracy"] == first["accuracy"]  # the first of two passes runs as the node
    assert first["line_delay_auto"]["reruns"] == []
    assert f"the {firsts[0]} frames before the first estimate ran with the starting" \
        in capsys.readouterr().out
    # two passes need auto
    assert replay_main([str(short), "--output", str(tmp_path / "x"), "--two-pass"]) == 2
    assert "--two-pass needs --line-delay auto" in capsys.readouterr().err


def test_replay_refines_the_estimate_after_its_first_frames(walk_bag, tmp_path, capsys):
    """--line-delay-refine-frames N: after N frames the estimate is refined in a second pass
    over them (the pipeline's line_delay_auto_refine_frames), used to the end and reported;
    0 keeps the calibrator's; the flag needs auto and at least 30 frames."""
    assert replay_main([str(walk_bag), "--output", str(tmp_path / "ref"), "--line-delay",
                        "auto", "--no-line-delay-rerun", "--line-delay-refine-frames", "90",
                        "--no-progress"]) == 0
    s = json.loads((tmp_path / "ref" / "summary.json").read_text())
    auto, ref = s["line_delay_auto"], s["line_delay_auto"]["refinement"]
    assert ref["status"] == "refined" and auto["status"] == "refined", ref
    assert s["line_delay_s"] == auto["line_delay_s"] == ref["line_delay_s"]
    before = [h for h in auto["history"] if h["status"] != "refined"][-1]
    assert ref["first_line_delay_s"] == before["line_delay_s"] != ref["line_delay_s"]
    assert auto["history"][-1]["status"] == "refined"
    out = capsys.readouterr().out
    assert f"refined after 90 frames from {ref['first_line_delay_s'] * 1e6:.2f} us/row" in out
    # two passes: the second runs with the refined estimate
    assert replay_main([str(walk_bag), "--output", str(tmp_path / "two"), "--line-delay",
                        "auto", "--two-pass", "--line-delay-refine-frames", "90",
                        "--no-progress"]) == 0
    two = json.loads((tmp_path / "two" / "summary.json").read_text())
    assert two["two_pass"]["second_pass"], two["two_pass"]
    assert two["line_delay_auto"]["status"] == "refined"
    assert two["line_delay_s"] == two["line_delay_auto"]["line_delay_s"] == ref["line_delay_s"]
    assert replay_main([str(walk_bag), "--output", str(tmp_path / "x"), "--line-delay", "auto",
                        "--line-delay-refine-frames", "10"]) == 2
    assert "at least 30" in capsys.readouterr().err
    assert replay_main([str(walk_bag), "--output", str(tmp_path / "x"),
                        "--line-delay-refine-frames", "60"]) == 2
    assert "--line-delay-refine-frames needs --line-delay auto" in capsys.readouterr().err


def test_a_processing_error_skips_that_frame_and_the_rest_is_processed(vehicle_bag, tmp_path,
                                                                       capsys, monkeypatch):
    """A fault of the package on one frame (here made to happen) is counted as that frame's,
    with its traceback, as the node does; it is not the bag's (it was reported as "bag read
    stopped", and the frames after it were lost)."""
    from rsvo_ros.odometry.pipeline import OdometryPipeline

    process = OdometryPipeline.process
    calls = []

    def faulty(self, stamp_ns, gray):
        calls.append(stamp_ns)
        if len(calls) == 3:
            raise RuntimeError("made to fail")
        return process(self, stamp_ns, gray)

    monkeypatch.setattr(OdometryPipeline, "process", faulty)
    out = tmp_path / "fault"
    assert replay_main([str(vehicle_bag), "--output", str(out), "--no-progress"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["skipped_reasons"] == {"processing error: RuntimeError: made to fail": 1}
    assert s["frames_in"] == 8 and s["frames_posed"] == 7
    assert "Traceback" in capsys.readouterr().err


def test_max_frames_stops_early_and_is_checked(vehicle_bag, tmp_path, capsys):
    out = tmp_path / "five"
    assert replay_main([str(vehicle_bag), "--output", str(out), "--max-frames", "5",
                        "--no-progress"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["frames_in"] == 5 and s["frames_posed"] == 5
    assert replay_main([str(vehicle_bag), "--output", str(tmp_path / "zero"), "--max-frames",
                        "0", "--no-progress"]) == 2
    assert "--max-frames" in capsys.readouterr().err


def test_angular_acceleration_flag_reaches_the_window_and_is_checked(vehicle_bag, tmp_path,
                                                                      capsys):
    out = tmp_path / "acc"
    assert replay_main([str(vehicle_bag), "--output", str(out), "--angular-acceleration", "0",
                        "--no-progress"]) == 0  # the paper's constant velocity within a frame
    s = json.loads((out / "summary.json").read_text())
    assert s["angular_acceleration_std"] == 0.0
    assert s["frames_posed"] == s["frames_in"] == 8  # the whole (8-frame) bag
    assert replay_main([str(vehicle_bag), "--output", str(tmp_path / "default"),
                        "--max-frames", "3", "--no-progress"]) == 0
    default = json.loads((tmp_path / "default" / "summary.json").read_text())
    assert default["angular_acceleration_std"] == 50.0
    assert replay_main([str(vehicle_bag), "--output", str(tmp_path / "bad"),
                        "--angular-acceleration", "-1", "--no-progress"]) == 2
    assert "--angular-acceleration" in capsys.readouterr().err


def _summary_fields(bag, tmp_path, runs: dict, key: str, frames: int) -> dict:
    """Replay ``bag`` once per ``runs`` entry (name -> extra flags, first ``frames`` frames);
    each run's ``summary.json`` value of ``key``."""
    used = {}
    for name, extra in runs.items():
        assert replay_main([str(bag), "--output", str(tmp_path / name), "--max-frames",
                            str(frames), "--no-progress", *extra]) == 0
        used[name] = json.loads((tmp_path / name / "summary.json").read_text())[key]
    return used


def _rejected(bag, tmp_path, capsys, flag: str, values) -> None:
    """Each bad value of ``flag`` stops rsvo_replay with exit 2 and a message naming it."""
    for bad in values:
        assert replay_main([str(bag), "--output", str(tmp_path / f"bad{bad}"), flag, bad,
                            "--no-progress"]) == 2
        assert flag in capsys.readouterr().err


def test_klt_refine_window_flag_reaches_the_tracker_and_is_checked(vehicle_bag, tmp_path,
                                                                    capsys):
    runs = {"default": [], "off": ["--klt-refine-window", "0"],
            "pairwise": ["--backend", "pairwise"], "seven": ["--klt-refine-window", "7"]}
    used = _summary_fields(vehicle_bag, tmp_path, runs, "klt_refine_window_px", 4)
    assert used == {"default": 11, "off": 0, "pairwise": 0, "seven": 7}
    traj = {n: (tmp_path / n / "trajectory.tum").read_text() for n in ("default", "off")}
    assert traj["default"] != traj["off"]  # the refinement moved the tracks
    _rejected(vehicle_bag, tmp_path, capsys, "--klt-refine-window", ("2", "99", "-3"))


def test_klt_window_flag_reaches_the_tracker_and_is_checked(vehicle_bag, tmp_path, capsys):
    runs = {"default": [], "narrow": ["--klt-window", "17"]}
    used = _summary_fields(vehicle_bag, tmp_path, runs, "klt_window_px", 4)
    assert used == {"default": DEFAULT_WINDOW_PX, "narrow": 17}
    traj = {n: (tmp_path / n / "trajectory.tum").read_text() for n in runs}
    assert traj["default"] != traj["narrow"]  # the window moved the tracks
    _rejected(vehicle_bag, tmp_path, capsys, "--klt-window", ("4", "52", "-1"))


def test_decimation_flag_reaches_the_tracker_and_is_checked(vehicle_bag, tmp_path, capsys):
    runs = {"default": [], "half": ["--decimation", "2"]}
    used = _summary_fields(vehicle_bag, tmp_path, runs, "tracking_decimation", 4)
    assert used == {"default": 1, "half": 2}
    traj = {n: (tmp_path / n / "trajectory.tum").read_text() for n in runs}
    assert traj["default"] != traj["half"]  # tracked in other pixels
    assert len(traj["half"].splitlines()) == len(traj["default"].splitlines())
    _rejected(vehicle_bag, tmp_path, capsys, "--decimation", ("0", "5", "-1"))


def test_readout_direction_flag_reaches_the_pipeline_and_is_checked(vehicle_bag, tmp_path,
                                                                   capsys):
    runs = {"default": [], "up": ["--readout-direction", "up"],
            "right": ["--readout-direction", "right"]}
    used = _summary_fields(vehicle_bag, tmp_path, runs, "readout_direction", 7)
    assert used == {"default": "down", "up": "up", "right": "right"}
    traj = {n: (tmp_path / n / "trajectory.tum").read_text() for n in runs}
    assert traj["default"] != traj["up"] != traj["right"]  # the rows' times changed
    with pytest.raises(SystemExit) as exc:  # argparse's choices
        replay_main([str(vehicle_bag), "--output", str(tmp_path / "bad"), "--readout-direction",
                     "sideways"])
    assert exc.value.code == 2 and "--readout-direction" in capsys.readouterr().err


def test_uncertain_rotation_flag_reaches_the_chain_and_is_checked(vehicle_bag, tmp_path, capsys):
    runs = {"default": [], "never": ["--uncertain-rotation", "0"],
            "pairwise": ["--backend", "pairwise"], "two": ["--uncertain-rotation", "2"]}
    used = _summary_fields(vehicle_bag, tmp_path, runs, "uncertain_rotation_deg", 3)
    assert used == {"default": BOOTSTRAP_UNCERTAIN_ROTATION_DEG, "never": 0.0,
                    "pairwise": UNCERTAIN_PAIR_ROTATION_DEG, "two": 2.0}
    _rejected(vehicle_bag, tmp_path, capsys, "--uncertain-rotation", ("-0.5", "nan"))


def test_window_option_flag_sets_a_field_records_it_and_is_checked(vehicle_bag, tmp_path,
                                                                   capsys):
    out = tmp_path / "opt"
    assert replay_main([str(vehicle_bag), "--output", str(out), "--window-option",
                        "init_max_rotation_std_deg=0", "--window-option", "min_landmarks=25",
                        "--no-progress"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["window_options_changed"] == {"init_max_rotation_std_deg": 0.0,
                                           "min_landmarks": 25}
    assert s["frames_posed"] == s["frames_in"] == 8
    default = tmp_path / "default"
    assert replay_main([str(vehicle_bag), "--output", str(default), "--no-progress"]) == 0
    assert json.loads((default / "summary.json").read_text())["window_options_changed"] == {}
    for bad, message in (("nope=1", "not a numeric WindowOptions field"),
                         ("min_landmarks=inf", "the value must be finite"),
                         ("min_landmarks=2.5", "takes a whole number")):
        with pytest.raises(SystemExit):
            replay_main([str(vehicle_bag), "--output", str(tmp_path / "bad"),
                         "--window-option", bad])
        assert message in capsys.readouterr().err


def test_replay_keeps_the_callers_tracker_options(vehicle_bag, tmp_path, monkeypatch):
    """``replay()`` with PipelineOptions: the command line's tracker settings (max features,
    refinement window) go over the given tracker options, whose other fields are kept (they
    were all replaced by defaults)."""
    from rsvo_ros.odometry.pipeline import PipelineOptions
    from rsvo_ros.odometry.tracker import TrackerOptions
    from rsvo_ros.tools import replay as replay_mod

    seen = []
    original = replay_mod.OdometryPipeline

    def spy(K, lens, line_delay, options):
        seen.append(options.tracker)
        return original(K, lens, line_delay, options)

    monkeypatch.setattr(replay_mod, "OdometryPipeline", spy)
    options = PipelineOptions(tracker=TrackerOptions(grid=(4, 3), fb_threshold_px=0.5))
    replay_mod.replay(replay_mod.ReplayConfig(vehicle_bag, tmp_path / "opts", max_frames=3,
                                              max_features=300, overwrite=True,
                                              progress=False, options=options))  # fmt: skip
    assert seen and seen[0].grid == (4, 3) and seen[0].fb_threshold_px == 0.5
    assert seen[0].max_features == 300


def test_brightness_changes_are_compensated_and_counted(tmp_path, capsys):
    # an auto exposure varying the brightness from frame to frame (--gain-variation): the
    # tracker maps each changed image into the previous one's grey levels; the summary counts
    # those frames, --no-photometric-compensation tracks the images as they are
    bag = tmp_path / "gain"
    write_bag(bag, SynthConfig(frames=10, motion="walk", width=320, height=180, seed=3,
                               gain_variation=0.3), progress=False)
    runs = {"on": [], "off": ["--no-photometric-compensation"]}
    counted = _summary_fields(bag, tmp_path, runs, "frames_brightness_compensated", 10)
    assert counted["on"] >= 5 and counted["off"] == 0, counted
    out = capsys.readouterr().out
    assert out.count("the brightness changed on") == 1  # said by the run that mapped frames
    assert f"the brightness changed on {counted['on']} frame(s)" in out
    summary = {n: json.loads((tmp_path / n / "summary.json").read_text()) for n in runs}
    assert summary["on"]["photometric_compensation"] is True
    assert summary["off"]["photometric_compensation"] is False


def test_rsvo_calibrate_keeps_the_first_estimate_when_the_second_pass_fails(tmp_path, capsys,
                                                                           monkeypatch):
    import yaml

    from rsvo_ros.tools import calibrate
    from rsvo_ros.tools.replay import ReplayError

    first = {"status": "estimated", "line_delay_s": 4.2e-5, "std_s": 1e-6, "readout_s": 0.0151,
             "readout_fraction": 0.45, "std_fraction": 0.01, "windows": 9, "frames": 120,
             "reason": "", "bag_line_delay_s": None}
    calls = []

    def fake_replay(cfg):
        calls.append(cfg.options.line_delay_refine)
        if cfg.options.line_delay_refine:
            raise ReplayError("the bag's image topic has no messages")
        return {"line_delay_auto": dict(first), "frames_in": 120}

    monkeypatch.setattr(calibrate, "replay", fake_replay)
    out = tmp_path / "calib.yaml"
    assert calibrate.main([str(tmp_path / "bag"), "--output", str(out), "--no-progress"]) == 0
    assert calls == [False, True]
    printed = capsys.readouterr().out
    assert "kept the first estimate" in printed and "the second pass failed" in printed
    params = yaml.safe_load(out.read_text())["rsvo_node"]["ros__parameters"]
    assert params["line_delay"] == 4.2e-5


def _tum_poses(path: Path) -> np.ndarray:
    return np.array([[float(x) for x in ln.split()] for ln in path.read_text().splitlines()
                     if ln.strip() and not ln.startswith("#")])


def test_a_mapping_lag_replays_the_same_on_the_mapping_thread_and_inline(walk_bag, tmp_path,
                                                                          capsys):
    """--mapping-lag S picks up each keyframe's BA at the first frame S after it: on the
    mapping thread (--async-mapping, as the node) and inline held back, the same trajectory
    to the bit, and not the inline replay's (the frames meanwhile track against the map as it
    was). A lag out of range is a usage error."""
    runs = {"inline": [], "lag": ["--mapping-lag", "0.05"],
            "lag_async": ["--mapping-lag", "0.05", "--async-mapping"]}
    tum, summary = {}, {}
    for name, extra in runs.items():
        out = tmp_path / name
        assert replay_main([str(walk_bag), "--output", str(out), "--no-progress",
                            *extra]) == 0
        tum[name] = _tum_poses(out / "trajectory.tum")
        summary[name] = json.loads((out / "summary.json").read_text())
    assert summary["lag"]["mapping_lag_s"] == summary["lag_async"]["mapping_lag_s"] == 0.05
    assert summary["inline"]["mapping_lag_s"] == 0.0 and summary["lag_async"]["async_mapping"]
    assert len(tum["lag"]) == len(tum["inline"]) >= 110
    np.testing.assert_array_equal(tum["lag"], tum["lag_async"])
    assert np.abs(tum["lag"] - tum["inline"]).max() > 1e-6
    for bad in ("-0.1", "3", "nan"):
        assert replay_main([str(walk_bag), "--output", str(tmp_path / "x"),
                            "--mapping-lag", bad]) == 2
        assert "--mapping-lag must be in [0, 2] s" in capsys.readouterr().err
    assert replay_main([str(walk_bag), "--output", str(tmp_path / "x"), "--backend",
                        "pairwise", "--mapping-lag", "0.05"]) == 2
    assert "--mapping-lag needs --backend window" in capsys.readouterr().err
