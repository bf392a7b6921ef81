"""rsvo_synth: exact RS rendering, bag round trips, the command line."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import cv2
import numpy as np
import pytest
from rosbags.rosbag2 import Reader

from rsvo_ros.core.geometry import so3_exp, so3_log
from rsvo_ros.ros import bagio, convert
from rsvo_ros.sim.synth import (
    MOVER_CLEARANCE_M,
    TEXELS_PER_M,
    TEXTURE_SIZE,
    CorridorScene,
    SequenceRenderer,
    SynthConfig,
    project_points,
    render_sequence,
)
from rsvo_ros.tools.synth_bag import jittered_stamps_ns, write_bag
from rsvo_ros.tools.synth_bag import main as synth_main

DOT_TOL_PX = 0.5  # issue: dots land within 0.5 px of their exact RS projection
MAX_BLOB_AREA_PX = 30


DOT_RADIUS_TEXELS = 5.0


def _dot_texture(rng, count=160):
    """Mid-gray tile with white discs at wall heights 0.3-2.7 m (clear of floor and ceiling);
    returns the texture and the dot centres in texels."""
    tex = np.full((TEXTURE_SIZE, TEXTURE_SIZE), 90.0, np.float32)
    lo, hi = 0.3 * TEXELS_PER_M, 2.7 * TEXELS_PER_M
    centres = np.column_stack([rng.uniform(20, TEXTURE_SIZE - 20, count),
                               rng.uniform(lo, hi, count)])
    for cx, cy in centres:
        cv2.circle(tex, (int(round(cx * 16)), int(round(cy * 16))),
                   int(DOT_RADIUS_TEXELS * 16), 255.0, -1, lineType=cv2.LINE_AA, shift=4)
    return tex, centres


def _blob_centroids(img, max_area=MAX_BLOB_AREA_PX):
    """Intensity centroids of small bright blobs (large, near, oblique discs are skipped:
    their image centroid is not the projection of their centre)."""
    mask = (img > 170).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    out = []
    w = np.clip(img.astype(float) - 90.0, 0, None)
    for i in range(1, n):
        x, y, bw, bh, area = stats[i]
        if area < 4 or area > max_area or x == 0 or y == 0 or x + bw >= img.shape[1] \
                or y + bh >= img.shape[0]:
            continue
        ys, xs = np.nonzero(labels == i)
        ww = w[ys, xs]
        out.append([np.sum(xs * ww) / ww.sum(), np.sum(ys * ww) / ww.sum()])
    return np.array(out).reshape(-1, 2)


def _hidden_by_inner_wall(scene, row_pose, rows, X):
    """Whether the segment from each row's camera to X crosses the inner wall first."""
    R, p = row_pose(rows)
    A, B = scene.wall_axes(0)
    cx, cz = scene.centre
    d = X - p
    ox, oz = (p[:, 0] - cx) / A, (p[:, 2] - cz) / B
    dx, dz = d[:, 0] / A, d[:, 2] / B
    qa, qb, qc = dx * dx + dz * dz, ox * dx + oz * dz, ox * ox + oz * oz - 1.0
    disc = qb * qb - qa * qc
    lam = (-qb - np.sqrt(np.maximum(disc, 0))) / qa
    return (disc > 0) & (lam > 1e-6) & (lam < 1 - 1e-6)


@pytest.mark.parametrize("motion, extra", [("paper", {"level": 6}),
                                           ("handheld", {"severity": 3.0}),
                                           ("vehicle", {"severity": 3.0}),
                                           ("handheld", {"severity": 3.0, "exposure": 0.008})])
def test_rendered_points_land_on_their_exact_rs_projection(motion, extra):
    """Dots on the outer wall, fully visible, land on the fixed-point RS projection of their
    centres (the paper motion at level 6 moves rows by tens of pixels); with motion blur the
    smeared dots' centroids still do: the exposure is centred on each row's time."""
    rng = np.random.default_rng(4)
    tex, centres = _dot_texture(rng)
    gray = np.full_like(tex, 90.0)
    scene = CorridorScene([gray, tex, gray, gray])
    cfg = SynthConfig(frames=3, motion=motion, width=640, height=360, **extra)
    renderer = SequenceRenderer(cfg, scene)
    frame = renderer.render(2)
    assert np.degrees(np.linalg.norm(frame.w)) > 20.0  # strong RS motion
    tile = TEXTURE_SIZE / TEXELS_PER_M
    s = (centres[:, 0][None, :] / TEXELS_PER_M + tile * np.arange(-12, 13)[:, None]).ravel()
    t = np.tile(centres[:, 1] / TEXELS_PER_M, 25)
    X = scene.surface_points(1, s, t)
    proj = project_points(X, frame.row_pose, renderer.K, cfg.height)
    ok = np.isfinite(proj).all(axis=1)
    ok &= (proj[:, 0] > 12) & (proj[:, 0] < cfg.width - 12)
    ok &= (proj[:, 1] > 12) & (proj[:, 1] < cfg.height - 12)
    # fully visible: the centre and eight rim points are not behind the inner wall
    r = 1.5 * DOT_RADIUS_TEXELS / TEXELS_PER_M
    for ang in np.linspace(0, 2 * np.pi, 8, endpoint=False):
        Xr = scene.surface_points(1, s + r * np.cos(ang), t + r * np.sin(ang))
        rows = np.nan_to_num(proj[:, 1], nan=0.0)
        ok &= ~_hidden_by_inner_wall(scene, frame.row_pose, rows, Xr)
    ok &= ~_hidden_by_inner_wall(scene, frame.row_pose, np.nan_to_num(proj[:, 1]), X)
    expected = proj[ok]
    blobs = _blob_centroids(frame.image)
    # isolated projections only (no second dot within 10 px)
    dd = np.linalg.norm(expected[:, None] - expected[None], axis=2) + np.eye(len(expected)) * 1e9
    expected = expected[dd.min(axis=1) > 10.0]
    d = np.linalg.norm(expected[:, None, :] - blobs[None, :, :], axis=2)
    nearest = d.min(axis=1)
    found = nearest < 3.0  # small enough to be measured (large near dots are skipped)
    assert found.sum() >= 10, found.sum()
    assert np.median(nearest[found]) < 0.5 * DOT_TOL_PX
    assert np.max(nearest[found]) < DOT_TOL_PX, np.sort(nearest[found])[-5:]


def test_rolling_shutter_moves_the_rows():
    """The same frame without line delay differs: the distortion is real."""
    a = render_sequence(SynthConfig(frames=2, motion="paper", level=6, width=160, height=90))
    b = render_sequence(SynthConfig(frames=2, motion="paper", level=6, width=160, height=90,
                                    line_delay=0.0))
    assert np.array_equal(a[0].R_world_cam, b[0].R_world_cam)
    assert np.mean(np.abs(a[1].image.astype(int) - b[1].image.astype(int))) > 5


def test_frames_are_textured_everywhere():
    frame = render_sequence(SynthConfig(frames=1, width=320, height=180))[0]
    corners = cv2.goodFeaturesToTrack(frame.image, 500, 0.01, 8)
    assert corners is not None and len(corners) > 150
    hist, _, _ = np.histogram2d(corners[:, 0, 0], corners[:, 0, 1], bins=(4, 3),
                                range=[[0, 320], [0, 180]])
    assert hist.min() > 0  # features in every cell of a 4x3 grid


def test_exposure_blurs_along_the_motion_and_noise_has_its_std():
    """--exposure: a shaken frame loses sharpness (and a longer exposure more), while the
    frame's ground truth is unchanged; --noise: the difference to the noiseless frame has the
    asked std and no bias, is drawn from the seed (the same bag every time) and differs from
    frame to frame."""
    base = dict(frames=2, motion="handheld", severity=3.0, width=320, height=180, seed=3)
    sharp, short, long = (render_sequence(SynthConfig(**base, exposure=e))[1]
                          for e in (0.0, 0.004, 0.016))

    def sharpness(img):
        return float(cv2.Laplacian(img.astype(np.float64), cv2.CV_64F).var())

    assert sharpness(long.image) < sharpness(short.image) < 0.97 * sharpness(sharp.image)
    assert abs(float(long.image.mean()) - float(sharp.image.mean())) < 1.0
    assert np.array_equal(long.R_world_cam, sharp.R_world_cam)
    assert np.array_equal(long.w, sharp.w)

    clean = render_sequence(SynthConfig(**base))
    noisy = render_sequence(SynthConfig(**base, noise=4.0))
    again = render_sequence(SynthConfig(**base, noise=4.0))
    d = [n.image.astype(float) - c.image.astype(float) for n, c in zip(noisy, clean, strict=True)]
    inside = [(c.image > 20) & (c.image < 235) for c in clean]  # away from clipping
    for dk, mk in zip(d, inside, strict=True):
        assert abs(dk[mk].std() - 4.0) < 0.2 and abs(dk[mk].mean()) < 0.1
    assert all(np.array_equal(a.image, b.image) for a, b in zip(noisy, again, strict=True))
    assert not np.array_equal(d[0], d[1])


def test_gain_variation_scales_each_frames_brightness():
    """--gain-variation: each frame is the constant-brightness frame times its own gain
    (clipped to 0-255), the gains vary smoothly from frame to frame by the asked log RMS,
    and the frame's ground truth is unchanged."""
    base = dict(frames=60, motion="walk", width=96, height=54, seed=5)
    clean = SequenceRenderer(SynthConfig(**base))
    varied = SequenceRenderer(SynthConfig(**base, gain_variation=0.2))
    gains = np.array([varied.gain(k) for k in range(base["frames"])])
    assert np.all(gains > 0) and clean.gain(7) == 1.0
    assert 0.08 < np.std(np.log(gains)) < 0.4
    assert np.max(np.abs(np.diff(np.log(gains)))) < 0.1  # smooth: an auto exposure's ramp
    for k in (0, 30):
        a, b = clean.render(k), varied.render(k)
        unclipped = (a.image > 10) & (a.image < 200)
        ratio = b.image[unclipped].astype(float) / a.image[unclipped]
        assert np.median(ratio) == pytest.approx(gains[k], rel=0.02)
        assert np.array_equal(a.R_world_cam, b.R_world_cam)


@pytest.mark.parametrize("bad, match", [({"exposure": 0.04}, "exposure"),
                                        ({"exposure": -0.001}, "exposure"),
                                        ({"noise": -1.0}, "noise"),
                                        ({"noise": float("nan")}, "noise"),
                                        ({"gain_variation": -0.1}, "gain variation"),
                                        ({"gain_variation": 2.0}, "gain variation"),
                                        ({"exposure": 0.01, "exposure_samples": 1},
                                         "exposure_samples")])
def test_sensor_settings_are_validated(bad, match):
    with pytest.raises(ValueError, match=match):
        SynthConfig(**bad)


def test_handheld_ground_truth_velocity_matches_the_trajectory():
    """The (w, v) ground truth is the row-0 derivative: X_row0 = Exp(r tau w) X_r + r tau v."""
    cfg = SynthConfig(frames=2, motion="handheld", severity=2.0, width=1280, height=720)
    r = SequenceRenderer(cfg)
    stamp, R0, p0, w, v, row_pose = r.frame_pose(1)
    R1, p1 = row_pose(np.array([2.0]))
    dt = 2 * cfg.tau
    assert np.allclose(R0.T @ (p1[0] - p0), dt * v, rtol=0, atol=1e-2 * np.linalg.norm(dt * v))
    assert np.allclose(so3_log(R0.T @ R1[0]), dt * w, rtol=0, atol=1e-2 * np.linalg.norm(dt * w))


def test_readout_turn_rate_is_the_mean_over_the_readout():
    """The paper's frames turn at a constant rate within the readout: the mean is their w.
    Under hand-held shake at 8-15 Hz a 36 ms readout's mean is far from the row-0 rate."""
    paper = SequenceRenderer(SynthConfig(frames=3, motion="paper", level=6))
    for k in range(3):
        assert np.allclose(paper.readout_turn_rate(k), paper.frame_pose(k)[3], atol=1e-9)
    walk = SequenceRenderer(SynthConfig(frames=60, motion="walk", severity=2.0))
    rel = [np.linalg.norm(walk.readout_turn_rate(k) - walk.frame_pose(k)[3])
           / np.linalg.norm(walk.frame_pose(k)[3]) for k in range(60)]
    assert np.median(rel) > 0.3
    # turning by the mean rate from row 0 lands exactly on the last row's rotation
    cfg = walk.config
    _, R0, _, _, _, row_pose = walk.frame_pose(7)
    readout = (cfg.height - 1) * cfg.tau
    R_last = row_pose(np.array([cfg.height - 1.0]))[0][0]
    assert np.allclose(R0 @ so3_exp(readout * walk.readout_turn_rate(7)), R_last, atol=1e-9)


def test_another_frame_rate_samples_the_same_motion():
    """At 60 Hz every second frame is the 30 Hz frame of the same instant (same pose, same
    velocities, same readout); at 15 Hz the default readout stays the paper's 36 ms, at 60 Hz
    it is one frame interval."""
    base = dict(motion="walk", severity=1.0, width=96, height=54, seed=3, line_delay=1e-4)
    fast = SequenceRenderer(SynthConfig(**base, frames=14, frame_rate=60.0))
    plain = SequenceRenderer(SynthConfig(**base, frames=7))
    for k in range(7):
        a, b = plain.frame_pose(k), fast.frame_pose(2 * k)
        assert a[0] == pytest.approx(b[0], abs=1e-12)
        for x, y in zip(a[1:5], b[1:5], strict=True):
            assert np.allclose(x, y, atol=1e-12)
    assert np.array_equal(plain.render(3).image, fast.render(6).image)
    assert SynthConfig(height=360, frame_rate=15.0).tau * 360 == pytest.approx(0.036)
    assert SynthConfig(height=360, frame_rate=60.0).tau * 360 == pytest.approx(1 / 60)
    assert SynthConfig(height=360).tau * 360 == pytest.approx(0.036)  # the 30 Hz default
    for bad, match in (({"frame_rate": 0.5}, "frame rate"),
                       ({"frame_rate": float("nan")}, "frame rate"),
                       ({"frame_rate": 10.0, "motion": "paper"}, "paper motion")):
        with pytest.raises(ValueError, match=match):
            SynthConfig(**bad)
    # the exposure is checked against the chosen rate's frame interval
    with pytest.raises(ValueError, match="exposure must be in"):
        SynthConfig(frame_rate=60.0, exposure=0.02)


@pytest.mark.parametrize("line_delay", [0.0, 1e-4])
def test_movers_are_drawn_where_each_row_sees_them(line_delay):
    """A mover changes the image only where it is: in each row, centred on where its centre
    line projects from that row's pose at that row's time (with a rolling shutter the panel
    is sheared by its own motion as well as the camera's). The camera and its ground truth are
    the bag's without movers."""
    base = dict(frames=40, motion="walk", severity=1.0, width=320, height=180, seed=5,
                line_delay=line_delay)
    plain = SequenceRenderer(SynthConfig(**base))
    moving = SequenceRenderer(SynthConfig(**base, movers=1))
    (mover,) = moving.movers
    assert np.linalg.norm(mover.velocity) >= 1.0  # crossing at walking speed
    # as fast as a passing car (8 m/s), so that its own motion during the readout shows
    mover = dataclasses.replace(mover, velocity=mover.velocity * 8.0
                                / np.linalg.norm(mover.velocity))  # fmt: skip
    moving.movers = [mover]
    k = int(round(mover.t0 * moving.config.rate_hz))  # it is in front of the camera then
    a, b = plain.render(k), moving.render(k)
    assert np.array_equal(a.pose(), b.pose()) and np.array_equal(a.w, b.w)
    changed = np.abs(a.image.astype(int) - b.image.astype(int)) > 0
    rows = np.flatnonzero(changed.sum(axis=1) >= 6)
    assert len(rows) > 40, "the mover is not in view"
    K = moving.K
    errors = []
    for r in rows[5:-5:4]:
        R, p = b.row_pose(np.array([float(r)]))
        centre = mover.centres(np.array([b.stamp + r * moving.config.tau]))[0]
        line = centre + np.linspace(-mover.half_height, mover.half_height, 2001)[:, None] \
            * np.array([0.0, 1.0, 0.0])  # fmt: skip
        Xc = (line - p[0]) @ R[0]
        uv = (Xc @ K.T)[:, :2] / Xc[:, 2:3]
        x_line = uv[np.argmin(np.abs(uv[:, 1] - r)), 0]
        cols = np.flatnonzero(changed[r])
        errors.append(0.5 * (cols.min() + cols.max()) - x_line)
    assert np.max(np.abs(errors)) < 1.5, errors
    with pytest.raises(ValueError, match="movers"):
        SynthConfig(movers=-1)
    with pytest.raises(ValueError, match="paper motion"):
        SynthConfig(motion="paper", movers=1)


def test_movers_keep_clear_of_the_camera():
    """People are placed 3-6 m ahead of the camera; a car reaches them in under a second.
    Their paths keep MOVER_CLEARANCE_M from the camera's over the whole sequence (a car no
    longer drives through a person whose panel then fills the view), and a person already
    clear is where the draw put them (a walk's bag is the same bag as before the rule)."""
    for motion in ("vehicle", "handheld"):
        for seed in (820, 822):
            cfg = SynthConfig(frames=90, motion=motion, severity=1.0, seed=seed, movers=4)
            r = SequenceRenderer(cfg)
            t = np.linspace(0.0, cfg.frames / cfg.rate_hz, 901)
            p_cam = r.trajectory.pose(t)[1]
            for mover in r.movers:
                gap = np.linalg.norm((mover.centres(t) - p_cam)[:, [0, 2]], axis=1)
                assert gap.min() >= MOVER_CLEARANCE_M[motion] - 1e-9, (motion, seed, gap.min())
                # still in front of the camera at its own time, as drawn
                R, p = r.trajectory.pose(np.array([mover.t0]))
                ahead = (mover.centres(np.array([mover.t0]))[0] - p[0]) @ R[0][:, 2]
                assert 2.5 < ahead < 6.5, (motion, seed, ahead)
    # the draws of a walk whose people were clear are unchanged: 3-6 m ahead, within 0.5 m
    # of the camera's heading at t0 (the shifted vehicles' people are up to metres aside)
    r = SequenceRenderer(SynthConfig(frames=90, motion="walk", severity=1.0, seed=821, movers=2))
    for mover in r.movers:
        R, p = r.trajectory.pose(np.array([mover.t0]))
        aside = (mover.centres(np.array([mover.t0]))[0] - p[0]) @ R[0][:, 0]
        assert abs(aside) <= 0.55
    shifted = SequenceRenderer(SynthConfig(frames=90, motion="vehicle", severity=1.0, seed=822,
                                           movers=2))  # fmt: skip
    asides = []
    for mover in shifted.movers:
        R, p = shifted.trajectory.pose(np.array([mover.t0]))
        asides.append(abs((mover.centres(np.array([mover.t0]))[0] - p[0]) @ R[0][:, 0]))
    assert max(asides) > 1.0


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_bag_round_trip(tmp_path, storage):
    cfg = SynthConfig(frames=4, motion="vehicle", width=96, height=54, seed=2)
    path = tmp_path / f"bag_{storage}"
    write_bag(path, cfg, storage, progress=False)
    frames = render_sequence(cfg)
    meta = bagio.custom_data(path)
    assert float(meta[bagio.LINE_DELAY_KEY]) == pytest.approx(cfg.tau, rel=1e-12)
    assert meta["rsvo.motion"] == "vehicle"
    with Reader(path) as reader:
        topics = {c.topic: c for c in reader.connections}
        assert topics[bagio.IMAGE_TOPIC].msgtype == bagio.IMAGE_TYPE
        assert topics[bagio.CAMERA_INFO_TOPIC].msgtype == bagio.CAMERA_INFO_TYPE
        assert topics[bagio.GROUND_TRUTH_TOPIC].msgtype == bagio.ODOMETRY_TYPE
        seen = {t: [] for t in topics}
        for conn, t_ns, raw in reader.messages():
            seen[conn.topic].append((t_ns, bagio.deserialize(raw, conn.msgtype)))
    assert all(len(v) == cfg.frames for v in seen.values())
    for k, ((t_img, img), (t_info, info), (t_gt, gt)) in enumerate(zip(
            seen[bagio.IMAGE_TOPIC], seen[bagio.CAMERA_INFO_TOPIC],
            seen[bagio.GROUND_TRUTH_TOPIC], strict=True)):
        stamp_ns = round(frames[k].stamp * 1e9)
        assert t_img == t_info == t_gt == stamp_ns
        for msg in (img, info, gt):
            assert convert.stamp_ns(msg.header) == stamp_ns
        assert img.encoding == "mono8" and img.header.frame_id == bagio.CAMERA_FRAME
        assert (img.width, img.height, img.step) == (96, 54, 96)
        assert np.array_equal(img.data.reshape(54, 96), frames[k].image)
        assert info.distortion_model == "plumb_bob"
        assert np.allclose(info.k.reshape(3, 3), SequenceRenderer(cfg).K)
        assert (gt.header.frame_id, gt.child_frame_id) == ("world", bagio.CAMERA_FRAME)
        R, p = bagio.pose_of(gt.pose.pose)
        assert np.allclose(R, frames[k].R_world_cam, atol=1e-9)
        assert np.allclose(p, frames[k].p_world_cam)
        tw = gt.twist.twist
        assert np.allclose([tw.angular.x, tw.angular.y, tw.angular.z], frames[k].w)
        assert np.allclose([tw.linear.x, tw.linear.y, tw.linear.z], frames[k].v)


def test_a_bag_with_a_drivers_stamp_jitter(tmp_path, capsys):
    """``--stamp-jitter S``: every message of frame k is stamped k / rate plus a uniform delay
    under S (a driver stamping on arrival), the same for the same seed, the images and ground
    truth still the nominal instant's; the bag says so. A jitter of one frame interval or more
    (frames out of order) or below 0 is refused."""
    cfg = SynthConfig(frames=6, motion="walk", width=96, height=54, seed=4)
    path = tmp_path / "jittered"
    assert synth_main([str(path), "--frames", "6", "--motion", "walk", "--resolution", "96x54",
                       "--seed", "4", "--stamp-jitter", "0.003", "--no-progress"]) == 0
    frames = render_sequence(cfg)
    nominal = [round(f.stamp * 1e9) for f in frames]
    assert bagio.custom_data(path)["rsvo.stamp_jitter"] == "0.003"
    with Reader(path) as reader:
        seen = {}
        for conn, t_ns, raw in reader.messages():
            msg = bagio.deserialize(raw, conn.msgtype)
            seen.setdefault(conn.topic, []).append((t_ns, msg))
    stamps = [t for t, _ in seen[bagio.IMAGE_TOPIC]]
    late = np.array(stamps) - np.array(nominal)
    assert (late >= 0).all() and (late < 3_000_000).all() and late.std() > 300_000
    for topic in (bagio.CAMERA_INFO_TOPIC, bagio.GROUND_TRUTH_TOPIC):
        assert [t for t, _ in seen[topic]] == stamps
    for k, (_, img) in enumerate(seen[bagio.IMAGE_TOPIC]):
        assert np.array_equal(img.data.reshape(54, 96), frames[k].image)
    _, gt = seen[bagio.GROUND_TRUTH_TOPIC][3]
    assert np.allclose(bagio.pose_of(gt.pose.pose)[1], frames[3].p_world_cam)
    assert jittered_stamps_ns(cfg, 0.003) == stamps  # the same again
    assert jittered_stamps_ns(cfg, 0.0) == nominal
    for bad in ("0.034", "-0.001"):
        assert synth_main([str(tmp_path / f"bad{bad}"), "--frames", "2", "--motion", "walk",
                           "--stamp-jitter", bad, "--no-progress"]) == 2
        assert "the stamp jitter must be at least 0 s and under one frame interval" in \
            capsys.readouterr().err


def test_cli_refuses_to_overwrite_and_validates(tmp_path, capsys):
    out = tmp_path / "b"
    assert synth_main([str(out), "--frames", "2", "--resolution", "64x36", "--no-progress"]) == 0
    assert "wrote 2 frames" in capsys.readouterr().out
    assert synth_main([str(out), "--frames", "2", "--no-progress"]) == 2
    assert "exists" in capsys.readouterr().err
    assert synth_main([str(out), "--frames", "2", "--resolution", "64x36", "--overwrite",
                       "--no-progress", "--storage", "mcap"]) == 0
    assert synth_main([str(tmp_path / "c"), "--frames", "0", "--no-progress"]) == 2
    assert "frames" in capsys.readouterr().err
    assert synth_main([str(tmp_path / "c"), "--exposure", "0.05", "--no-progress"]) == 2
    assert "exposure must be in [0, 0.0333333) s" in capsys.readouterr().err
    blurred = tmp_path / "blurred"
    assert synth_main([str(blurred), "--frames", "2", "--resolution", "64x36", "--exposure",
                       "0.01", "--noise", "2", "--gain-variation", "0.2", "--no-progress"]) == 0
    meta = bagio.custom_data(blurred)
    assert (meta["rsvo.exposure"], meta["rsvo.noise"]) == ("0.01", "2")
    assert meta["rsvo.gain_variation"] == "0.2" and meta["rsvo.frame_rate"] == "30"
    slow = tmp_path / "slow"
    assert synth_main([str(slow), "--frames", "3", "--resolution", "64x36", "--rate", "15",
                       "--no-progress"]) == 0
    with Reader(slow) as reader:
        stamps = [t for c, t, _ in reader.messages() if c.topic == bagio.IMAGE_TOPIC]
    assert np.diff(stamps).tolist() == [66_666_667, 66_666_666]
    assert bagio.custom_data(slow)["rsvo.frame_rate"] == "15"
    assert bagio.custom_data(slow)["rsvo.movers"] == "0"
    people = tmp_path / "people"
    assert synth_main([str(people), "--frames", "2", "--resolution", "64x36", "--movers", "2",
                       "--motion", "walk", "--no-progress"]) == 0
    assert bagio.custom_data(people)["rsvo.movers"] == "2"
    assert synth_main([str(tmp_path / "p2"), "--movers", "1", "--motion", "paper",
                       "--no-progress"]) == 2
    assert "paper motion has none" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        synth_main([str(tmp_path / "d"), "--resolution", "big"])


def test_console_script_runs(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "rsvo_ros.tools.synth_bag", str(tmp_path / "e"),
                           "--frames", "2", "--resolution", "64x36", "--motion", "paper",
                           "--level", "3"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "e" / "metadata.yaml").exists()
