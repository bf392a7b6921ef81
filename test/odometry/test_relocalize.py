"""Re-finding the map: ORB descriptors at tracked corners, the landmark memory, a frame posed
against it (PnP, then more matches by projection), and the window backend re-finding its map
after a walker's stop-and-look."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from rsvo_ros.core.geometry import so3_exp, so3_log
from rsvo_ros.odometry.pipeline import OdometryPipeline, PipelineOptions
from rsvo_ros.odometry.relocalize import (
    LandmarkMemory,
    _pairs_within,
    describe,
    guided_matches,
    match_memory,
)
from rsvo_ros.odometry.window import REFOUND_REASON
from rsvo_ros.sim.synth import SequenceRenderer, SynthConfig
from rsvo_ros.tools.replay import accuracy

F, W, H = 500.0, 640, 360
K = np.array([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]])
DEPTH = 4.0  # a textured wall this far in front of the first camera


def _texture(rng) -> np.ndarray:
    """A wall's texture (uint8), larger than the views of it."""
    img = rng.integers(0, 256, (3 * H, 3 * W), dtype=np.uint8)
    return cv2.GaussianBlur(img, (0, 0), 2.0)


def _view(texture: np.ndarray, R_wc: np.ndarray, p_wc: np.ndarray) -> np.ndarray:
    """The wall z = DEPTH (texture pixel (u, v) at x = (u - 1.5 W) DEPTH / F, ...) seen by a
    camera at ``p_wc`` turned by ``R_wc``: a plane's homography."""
    # wall point (a, b) in texture pixels -> world X = (a - 1.5W, b - 1.5H, F) DEPTH / F
    T_tex = np.array([[DEPTH / F, 0, -1.5 * W * DEPTH / F], [0, DEPTH / F, -1.5 * H * DEPTH / F],
                      [0, 0, DEPTH]])  # fmt: skip
    # camera: K R^T (X - p); X = T_tex [a, b, 1]
    M = K @ R_wc.T @ (T_tex - np.outer(p_wc, [0, 0, 1]))
    return cv2.warpPerspective(texture, M, (W, H), flags=cv2.INTER_LINEAR)


def _wall_points(px: np.ndarray, R_wc: np.ndarray, p_wc: np.ndarray) -> np.ndarray:
    """World points on the wall seen at pixels ``px`` by the camera."""
    rays = np.column_stack([(px - K[:2, 2]) / F, np.ones(len(px))]) @ R_wc.T
    lam = (DEPTH - p_wc[2]) / rays[:, 2]
    return p_wc + lam[:, None] * rays


def _corners(img: np.ndarray, n: int = 400) -> np.ndarray:
    return cv2.goodFeaturesToTrack(img, n, 0.01, 8).reshape(-1, 2)


def test_descriptors_of_the_same_corners_agree_across_a_small_motion(rng):
    tex = _texture(rng)
    a = _view(tex, np.eye(3), np.zeros(3))
    b = _view(tex, so3_exp([0.0, 0.02, 0.0]), np.array([0.1, 0.0, 0.0]))
    pts = _corners(a)
    d1, v1 = describe(a, pts)
    assert d1.shape == (len(pts), 32) and d1.dtype == np.uint8
    assert np.array_equal(describe(a, pts)[0], d1)  # deterministic
    # points near the border get none
    edge = np.array([[3.0, 3.0], [W / 2, H / 2]])
    assert describe(a, edge)[1].tolist() == [False, True]
    # the same wall points in the second view: close descriptors; other points: far
    X = _wall_points(pts, np.eye(3), np.zeros(3))
    Xc = (X - [0.1, 0.0, 0.0]) @ so3_exp([0.0, 0.02, 0.0])
    pts_b = Xc[:, :2] / Xc[:, 2:] * F + K[:2, 2]
    d2, v2 = describe(b, pts_b)
    ok = v1 & v2
    same = np.unpackbits(d1[ok] ^ d2[ok], axis=1).sum(1)
    other = np.unpackbits(d1[ok] ^ np.roll(d2[ok], 7, axis=0), axis=1).sum(1)
    assert np.median(same) < 40 < np.median(other)


def test_the_memory_overwrites_and_keeps_the_newest():
    mem = LandmarkMemory(capacity=5)
    d = np.zeros((3, 32), np.uint8)
    mem.update(np.array([1, 2, 3]), np.zeros((3, 3)), d)
    mem.update(np.array([3, 4, 5]), np.ones((3, 3)), d + 1)
    ids, X, desc = mem.snapshot()
    assert sorted(ids.tolist()) == [1, 2, 3, 4, 5]
    assert X[ids == 3][0].tolist() == [1.0, 1.0, 1.0] and desc[ids == 3][0, 0] == 1
    assert mem.known(np.array([5, 6, 1])).tolist() == [True, False, True]
    mem.update(np.array([6, 7]), np.full((2, 3), 2.0), d[:2])
    ids, _, _ = mem.snapshot()
    assert sorted(ids.tolist()) == [3, 4, 5, 6, 7]  # 1 and 2 were written first: dropped
    mem.update(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 32), np.uint8))
    assert len(mem) == 5
    mem.clear()
    assert len(mem) == 0


def test_a_frame_that_looked_away_is_posed_against_the_memory(rng):
    """The first view's corners (world points on the wall, descriptors) are remembered; a
    later view from 30 cm aside and turned by 6 deg, with its own corners (other track ids,
    none shared by KLT), is posed by matching them: within a centimetre and a tenth of a
    degree; by projection the matches grow."""
    tex = _texture(rng)
    R1, p1 = np.eye(3), np.zeros(3)
    R2, p2 = so3_exp([0.02, -0.1, 0.01]), np.array([0.3, -0.05, 0.1])
    a, b = _view(tex, R1, p1), _view(tex, R2, p2)
    pts_a = _corners(a)
    d_a, v_a = describe(a, pts_a)
    mem = LandmarkMemory()
    mem.update(np.arange(len(pts_a))[v_a], _wall_points(pts_a, R1, p1)[v_a], d_a[v_a])
    pts_b = _corners(b)
    x_b = (pts_b - K[:2, 2]) / F
    d_b, v_b = describe(b, pts_b)
    found = match_memory(mem.snapshot(), x_b, d_b, v_b, F, ratio=0.8, max_hamming=64,
                         ransac_px=2.0, min_inliers=30)  # fmt: skip
    assert found is not None
    assert np.linalg.norm(found.p - p2) < 0.01
    assert np.degrees(np.linalg.norm(so3_log(R2.T @ found.R))) < 0.1
    more = guided_matches(found, mem.snapshot(), x_b, d_b, v_b, F, 8.0, 64)
    assert len(more.obs_idx) > len(found.obs_idx)
    assert len(set(more.obs_idx.tolist())) == len(more.obs_idx)  # one memory point each
    # every match is right: its world point projects onto its corner
    Xc = (more.X - p2) @ R2
    err = np.linalg.norm(Xc[:, :2] / Xc[:, 2:] - x_b[more.obs_idx], axis=1) * F
    assert np.percentile(err, 95) < 2.0
    # a view of another wall finds nothing
    other = _view(_texture(np.random.default_rng(99)), R2, p2)
    d_o, v_o = describe(other, _corners(other))
    assert match_memory(mem.snapshot(), (_corners(other) - K[:2, 2]) / F, d_o, v_o, F, 0.8,
                        64, 2.0, 30) is None  # fmt: skip


def test_the_guided_search_finds_the_pairs_a_dense_distance_matrix_finds(rng):
    """The search by projection's radius query (a k-d tree) gives the pairs, and their order,
    that the full (observations x memory) distance matrix gives, to the bit: on random points,
    with pairs exactly at the radius (not near: the test is strict) and non-finite
    points on either side among them."""
    f, radius = 700.0, 8.0
    for trial in range(60):
        a = rng.uniform(-0.6, 0.6, (int(rng.integers(0, 400)), 2))
        b = rng.uniform(-0.8, 0.8, (int(rng.integers(0, 3000)), 2))
        k = min(len(a), len(b))
        b[:k] = a[:k] + [radius / f, 0.0]  # on the circle (up to rounding either side)
        b[k: k + 2 * (trial % 2)] = np.inf
        a[: 2 * (trial % 3 == 1)] = np.nan
        with np.errstate(invalid="ignore"):
            d2 = ((a[:, None, :] - b[None, :, :]) ** 2).sum(axis=2) * f**2
        want_i, want_j = np.nonzero(d2 < radius**2)
        got_i, got_j = _pairs_within(a, b, radius, f)
        assert np.array_equal(got_i, want_i) and np.array_equal(got_j, want_j), trial
    # some pairs are found at all (the check is not vacuous)
    a = rng.uniform(-0.1, 0.1, (50, 2))
    assert len(_pairs_within(a, a + 1.0 / f, radius, f)[0]) >= 50


def _walk(refind: bool, frames: int = 300, seed: int = 100,
          **window: float) -> tuple[dict, list[bool], dict[int, np.ndarray]]:  # fmt: skip
    """Replay a rendered walk through the pipeline (``window``: WindowOptions to change): its
    accuracy, each frame's ``refound`` flag (checked against the frame's reason) and the
    poses."""
    cfg = SynthConfig(frames=frames, motion="walk", severity=0.7, seed=seed)
    renderer = SequenceRenderer(cfg)
    options = PipelineOptions()
    # KLT alone, as these walks were measured: the tracker's re-tracking from the images'
    # shift (on by default since the thirty-third session) carries some tracks through the
    # look-around and changes where the map is lost and re-found (seed 979: re-found at frames
    # 172 and 180 instead of 166 and 180; seed 1016: five pair recoveries instead of three,
    # ATE 0.076 m against 0.036); the paths these tests pin are the loss's
    options.tracker.shift_retry = False
    if not refind:
        options.window.reloc_min_inliers = 0
    for name, value in window.items():
        setattr(options.window, name, value)
    pipeline = OdometryPipeline(renderer.K, None, cfg.tau, options)
    gt, est, refound = {}, {}, []
    for frame in renderer:
        stamp = round(frame.stamp * 1e9)
        res = pipeline.process(stamp, frame.image)
        gt[stamp], est[stamp] = frame.pose(), res.T_world_cam
        assert res.refound == res.reason.startswith(REFOUND_REASON), res.reason
        # every posed frame's inlier ratio is a share of what its estimate used, and says
        # which tracks (the pair recoveries' had neither: 266-376 "inlier ratio" and all red)
        if res.status == "posed":
            assert 0.0 <= res.inlier_ratio <= 1.0, (res.reason, res.inlier_ratio)
            assert res.inliers is not None and res.inliers.any(), res.reason
        refound.append(res.refound)
    pipeline.close()
    acc = accuracy(gt, est)
    first = dict(sorted(est.items())[:60])
    acc["scale_ratio"] = acc["sim3_scale"] / accuracy(gt, first)["sim3_scale"]  # as replay's
    return acc, refound, est


@pytest.mark.slow
def test_the_map_is_found_again_after_a_stop_and_look():
    """A 300-frame walk whose walker stops for 1.5 s and looks 40 deg left and right (the
    replay table's held-out seed 100): the map is lost in the look and the pair estimator's
    recovery from a few millimetres of baseline changes its scale. Re-found by descriptors,
    the walk keeps its scale (measured: the whole run's Sim(3) scale 0.96 of its first 60
    frames' and ATE 0.09 m, against 0.65 and 0.42 m without)."""
    acc, refound, _ = _walk(refind=True)
    assert any(refound)
    assert abs(acc["scale_ratio"] - 1.0) < 0.1
    acc_off, refound_off, _ = _walk(refind=False)
    assert not any(refound_off)
    assert abs(acc_off["scale_ratio"] - 1.0) > 0.2
    assert acc["ate_m"]["rmse"] < 0.5 * acc_off["ate_m"]["rmse"]


@pytest.mark.slow
def test_a_refound_frame_is_published_in_the_lost_maps_odometry_frame():
    """Seed 979 of the 300-frame walks: the map is lost in the stop-and-look, re-found, lost
    again and restarted from the pairwise chain (whose odometry frame keeps the published pose
    continuous), and two frames later the memory re-finds the old map. The re-found pose is in
    the old map's world, so it is published with that map's odometry frame: with the restarted
    map's, that frame jumped 107 map units (3.4 m) and the ATE was 0.58 m, the scale 0.63 of the
    first 60 frames' (measured: 0.056 m and 1.02 with the old map's frame)."""
    acc, flags, est = _walk(refind=True, seed=979)
    refound = [i for i, r in enumerate(flags) if r]
    assert len(refound) >= 2
    p = np.array([T[:3, 3] for _, T in sorted(est.items())])
    steps = np.linalg.norm(np.diff(p, axis=0), axis=1)
    assert max(steps[i - 1] for i in refound) < 10 * np.median(steps)
    assert abs(acc["scale_ratio"] - 1.0) < 0.1


@pytest.mark.slow
@pytest.mark.parametrize("guard", [True, False])
def test_a_pair_recovery_does_not_take_a_scale_far_beyond_the_usual_step(guard):
    """Seed 1016 of the 300-frame walks: the walker stops and looks around, the map is lost,
    and the pair estimator recovers frame 158 from a few millimetres of baseline. The depths of
    the nine landmarks it shares with the map gave a scale of 31 usual steps; the rebuilt map
    carried it until the map was re-found 22 frames later (ATE 1.21 m, steps of 15-440 map
    units against about 1). A scale beyond ``recovery_max_steps`` usual steps is not believed
    (measured: ATE 0.036 m). Without the guard the test sees the run-away."""
    window = {} if guard else {"recovery_max_steps": np.inf}
    acc, _, est = _walk(refind=True, seed=1016, **window)
    p = np.array([T[:3, 3] for _, T in sorted(est.items())])
    steps = np.linalg.norm(np.diff(p, axis=0), axis=1)
    ran_away = steps.max() > 10 * np.median(steps) or acc["ate_m"]["rmse"] > 0.2
    assert ran_away != guard
