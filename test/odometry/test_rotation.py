"""A turning rolling-shutter camera: rotation, turn rate and translation parallax of a frame pair
(odometry/rotation.py), and the pairwise chain that takes them where the baseline is too short
for the pair estimator."""

from __future__ import annotations

import dataclasses

import numpy as np
from conftest import ground_truth_pose, rs_views

from rsvo_ros.core.geometry import so3_exp, so3_log
from rsvo_ros.odometry import pairwise
from rsvo_ros.odometry.frame import FrameState
from rsvo_ros.odometry.pairwise import row0_turn_rate
from rsvo_ros.odometry.pipeline import OdometryPipeline, PipelineOptions
from rsvo_ros.odometry.rotation import direction_given_rotation, fit_rotation
from rsvo_ros.odometry.tracker import TrackedPair
from rsvo_ros.sim.synth import SequenceRenderer, SynthConfig
from rsvo_ros.tools.replay import accuracy

FOCAL = 500.0
TAU = 1e-4  # s per row: a 36 ms readout over 360 rows


def _views(rng, state: FrameState, X: np.ndarray, noise_px: float = 0.0):
    """RS observations (normalized, row times) of world points by a frame, with noise."""
    x, s = rs_views(state, X, FOCAL, TAU)
    return x + rng.normal(0, noise_px / FOCAL, x.shape), s


def _scene(rng, n: int = 300) -> np.ndarray:
    return np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-2, 2, n), rng.uniform(2, 8, n)])


def test_a_turning_rs_camera_is_fitted_and_a_moving_one_leaves_parallax(rng):
    """A camera turning at 2.6 rad/s (a walker looking around: 5 deg a frame, 5 deg across
    the readout) whose turn rate a shake changes by 1.2 rad/s from one frame to the next: the
    fit gives the rotation and turn rate and leaves only the noise; a global-shutter rotation
    leaves a pixel and more of wobble. The same turn while the camera moves 6 cm leaves the
    translation parallax the chain keeps the pair estimator for."""
    X = _scene(rng)
    w, w2 = np.array([0.3, 2.6, 0.2]), np.array([1.1, 1.8, -0.4])
    first = FrameState(0, np.eye(3), np.zeros(3), w, np.zeros(3))
    R_true = so3_exp((w + w2) / 60.0)
    xa, sa = _views(rng, first, X, 0.3)
    for move, expect_parallax in ((0.0, False), (0.06, True)):
        second = FrameState(1, R_true, np.array([0.0, 0.0, move]), w2, np.zeros(3))
        xb, sb = _views(rng, second, X, 0.3)
        fit = fit_rotation(first, xa, sa, xb, sb, np.eye(3), np.zeros(3), FOCAL)
        assert fit.ok
        if expect_parallax:
            assert fit.parallax_px > 1.5, fit.parallax_px
            continue
        assert fit.parallax_px < 0.5, fit.parallax_px  # noise 0.3 px per axis
        assert np.degrees(np.linalg.norm(so3_log(R_true.T @ fit.R))) < 0.03
        assert np.linalg.norm(fit.w - w2) < 0.1 * np.linalg.norm(w2)
        gs = fit_rotation(first, xa, sa * 0, xb, sb * 0, np.eye(3), np.zeros(3), FOCAL)
        assert gs.parallax_px > 2 * fit.parallax_px, (gs.parallax_px, fit.parallax_px)


def test_a_turn_rate_that_changes_within_the_readout_is_fitted_with_its_change(rng):
    """A strong shake (a 10 Hz turn of 1 rad/s changes the rate by up to 60 rad/s^2): over a
    36 ms readout a constant turn rate leaves pixels of wobble, the pair would not count as a
    turning camera; with the rate's change fitted only the noise is left, the rotation is
    right and the change is the frames' difference."""
    X = _scene(rng)
    first = FrameState(0, np.eye(3), np.zeros(3), np.array([0.3, 1.5, 0.2]), np.zeros(3))
    w2, a2 = np.array([0.5, 1.2, -0.3]), np.array([40.0, -60.0, 20.0])
    R_true = so3_exp(np.array([0.4, 1.35, -0.05]) / 30.0)
    second = FrameState(1, R_true, np.zeros(3), w2, np.zeros(3), a2)
    xa, sa = _views(rng, first, X, 0.3)
    xb, sb = _views(rng, second, X, 0.3)
    constant = fit_rotation(first, xa, sa, xb, sb, np.eye(3), np.zeros(3), FOCAL)
    changing = fit_rotation(first, xa, sa, xb, sb, constant.R, constant.w, FOCAL,
                            acceleration=True)  # fmt: skip
    assert constant.ok and changing.ok
    assert constant.parallax_px > 1.0, constant.parallax_px
    assert changing.parallax_px < 0.6, changing.parallax_px  # noise 0.3 px per axis
    assert np.degrees(np.linalg.norm(so3_log(R_true.T @ changing.R))) < 0.05
    assert np.linalg.norm(changing.a - a2) < 0.2 * np.linalg.norm(a2), changing.a
    assert np.linalg.norm(fit_rotation(first, xa, sa, xb, sb, np.eye(3), np.zeros(3), FOCAL,
                                       acceleration=True).a - a2) < 0.2 * np.linalg.norm(a2)


def test_the_baseline_direction_follows_from_a_known_rotation(rng):
    """Given the fitted rotation, the rays of each track and the baseline are coplanar: a
    walker's 3 cm step (forward, or forward with some sway and bob) comes out within 20 deg
    (the pair estimator on such walk pairs: 70-95 deg off). A step straight sideways is mostly
    taken up by the rotation fit (0.3 deg of it here) and its direction is not recovered."""
    X = _scene(rng)
    w = np.array([0.5, -1.0, 0.1])
    first = FrameState(0, np.eye(3), np.zeros(3), w, np.zeros(3))
    xa, sa = _views(rng, first, X, 0.3)
    for step in ([0.0, 0.0, 0.03], [0.01, 0.005, 0.03], [-0.008, 0.004, 0.025]):
        c = np.array(step)
        second = FrameState(1, so3_exp(w / 30.0), c, w, np.zeros(3))
        xb, sb = _views(rng, second, X, 0.3)
        fit = fit_rotation(first, xa, sa, xb, sb, np.eye(3), w, FOCAL)
        got, front = direction_given_rotation(w, xa, sa, fit, xb, sb, 1.5, FOCAL)
        assert front > 0.5
        angle = np.degrees(np.arccos(np.clip(got @ c / np.linalg.norm(c), -1, 1)))
        assert angle < 20.0, (step, angle)


def test_a_driving_step_takes_its_direction_from_every_track():
    """A 20 cm forward step past points 1-4 m away (14 px of translation parallax, a shaken
    vehicle's first pairs): the turning camera's fitted turn rate takes up part of it, so the
    pairwise chain takes the direction at the rotation's own rate. There every track's residual
    under the rotation is its parallax: left out as outliers (the default, for pairs of
    1-3 px), the informative tracks go and the direction is 4-8 deg off; with every track it is
    within 5 deg, about half the error."""
    errors = {None: [], np.inf: []}
    for seed in range(4):
        rng = np.random.default_rng(seed)
        X = 0.5 * _scene(rng)
        w = np.array([0.05, 0.6, 0.02])
        first = FrameState(0, np.eye(3), np.zeros(3), w, np.zeros(3))
        xa, sa = _views(rng, first, X, 0.3)
        c = np.array([0.02, -0.01, 0.2])
        xb, sb = _views(rng, FrameState(1, so3_exp(w / 30.0), c, w, np.zeros(3)), X, 0.3)
        fit = fit_rotation(first, xa, sa, xb, sb, np.eye(3), w, FOCAL)
        assert fit.parallax_px > 10.0, fit.parallax_px
        w_cv = so3_log(fit.R) * 30.0
        at_rate = dataclasses.replace(fit, w=w_cv, a=np.zeros(3))
        for keep in errors:
            got, front = direction_given_rotation(w_cv, xa, sa, at_rate, xb, sb, 1.5, FOCAL,
                                                  max_residual_px=keep)  # fmt: skip
            assert front > 0.5
            errors[keep].append(np.degrees(np.arccos(np.clip(got @ c / np.linalg.norm(c), -1,
                                                             1))))  # fmt: skip
    assert max(errors[np.inf]) < 5.0, errors
    assert np.mean(errors[None]) > 1.5 * np.mean(errors[np.inf]), errors


def _pairwise_walk(severity: float, monkeypatch) -> tuple[int, np.ndarray, float, int]:
    """The RS pairwise backend over a rendered 30-frame walk (640x360, seed 0): the number of
    pairs posed as a turning camera, each frame's rotation error against the previous frame
    (deg, row 0 as published), the ATE (m) and how often the pair estimator ran."""
    calls = []
    estimate = pairwise.estimate_relative_pose
    monkeypatch.setattr(pairwise, "estimate_relative_pose",
                        lambda *a, **k: calls.append(1) or estimate(*a, **k))
    cfg = SynthConfig(frames=30, motion="walk", severity=severity, width=640, height=360,
                      seed=0)  # fmt: skip
    renderer = SequenceRenderer(cfg)
    pipe = OdometryPipeline(renderer.K, None, cfg.tau, PipelineOptions(backend="pairwise"))
    est, gt, turned = {}, {}, 0
    for f in renderer:
        s = round(f.stamp * 1e9)
        r = pipe.process(s, f.image)
        assert np.isfinite(r.T_world_cam).all()
        turned += "turning camera" in r.reason
        est[s], gt[s] = r.T_world_cam, ground_truth_pose(f)
    stamps = sorted(est)
    err = np.array([np.degrees(np.linalg.norm(so3_log(
        (gt[a][:3, :3].T @ gt[b][:3, :3]).T @ (est[a][:3, :3].T @ est[b][:3, :3]))))
        for a, b in zip(stamps, stamps[1:], strict=False)])  # fmt: skip
    return turned, err, accuracy(gt, est)["ate_m"]["rmse"], len(calls)


def test_the_pairwise_chain_takes_the_turning_camera_on_a_walk(monkeypatch):
    """A rendered walk (3 cm a frame, strong shake): most pairs are posed as a turning camera,
    saying so, and the chain's per-frame rotation error is far below the pair estimator's
    (1.6 deg RMS before on this walk's first 26 frames). At row 0: 0.70 deg with the row-0
    rotation interpolated between middle rows, 0.51 with the row-0 turn rate at share 1/2, 0.23
    at 0.3. After the first turning camera's pair the next ones are fitted as one first, and
    the pair estimator is not run for them: 1 estimate for 29 pairs (29 before; 0.22 deg)."""
    turned, err, ate, estimates = _pairwise_walk(1.0, monkeypatch)
    assert turned >= 20
    assert np.sqrt(np.mean(np.square(err))) < 0.4, err
    assert ate < 0.1
    assert estimates <= 3, estimates


def test_the_chain_takes_the_turning_camera_through_the_strongest_shake(monkeypatch):
    """The severity-2 walk: a constant turn rate per frame left a third of its pairs over the
    parallax limit, and the pair estimator posed them 5-7 deg off; with the rate's change
    fitted where the constant rate is not enough, nearly every pair is a turning camera (29 of
    29; 20 before) and no frame is more than 2 deg off (RMS 0.39 deg, max 1.25 deg; before
    2.10 and 6.9 deg). Without the pair estimator after the first pair: the same (0.39 deg RMS,
    1.25 deg max)."""
    turned, err, _, estimates = _pairwise_walk(2.0, monkeypatch)
    assert turned >= 25, turned
    assert err.max() < 2.0 and np.sqrt(np.mean(err**2)) < 0.8, err
    assert estimates <= 5, estimates


def test_the_row0_turn_rate_follows_a_shake_between_middle_rows(rng):
    """A rendered walk's own trajectory (strong shake, 36 ms readout at 30 Hz): from exact
    middle-row poses and each frame's mean turn rate over its readout, both rates off by the
    same unknown amount (two views see only their difference), the row-0 rotations come out
    within 0.3 deg per frame; interpolating between the middle rows misses the shake."""
    cfg = SynthConfig(frames=60, motion="walk", severity=1.0, width=640, height=360, seed=0)
    traj = SequenceRenderer(cfg).trajectory
    dt, s = 1.0 / cfg.rate_hz, 180 * cfg.tau  # the middle row's time after row 0

    def rotation_at(t: float) -> np.ndarray:
        return traj.pose(np.array([t]))[0][0]

    def readout_rate(k: int) -> np.ndarray:
        return so3_log(rotation_at(k * dt).T @ rotation_at(k * dt + 2 * s)) / (2 * s)

    new, interpolated = {}, {}
    for k in range(1, 60):
        # middle-row cameras, world from camera
        R_prev, R_curr = rotation_at((k - 1) * dt + s), rotation_at(k * dt + s)
        common = rng.normal(0, 1.0, 3)  # rad/s, the part of the rates two views do not see
        w = row0_turn_rate(R_curr.T @ R_prev, dt, readout_rate(k - 1) + common,
                           readout_rate(k) + common)  # fmt: skip
        new[k] = R_curr @ so3_exp(-s * w)
        interpolated[k] = R_prev @ so3_exp((1 - s / dt) * so3_log(R_prev.T @ R_curr))

    def rms_deg(est: dict) -> float:
        err = [np.linalg.norm(so3_log((est[k - 1].T @ est[k]).T
                                      @ (rotation_at((k - 1) * dt).T @ rotation_at(k * dt))))
               for k in range(2, 60)]  # fmt: skip
        return float(np.degrees(np.sqrt(np.mean(np.square(err)))))

    assert rms_deg(new) < 0.3, rms_deg(new)
    assert rms_deg(interpolated) > 2 * rms_deg(new), (rms_deg(interpolated), rms_deg(new))


def test_the_gs_chain_does_not_use_the_line_delay():
    """The GS models' turning camera is a global shutter's: on a walk rendered with a global
    shutter, whose pairs are mostly posed as a turning camera, the GS pairwise chain gives the
    same poses whatever line delay the camera is said to have (a first version fitted the GS
    chain's pairs with RS rows)."""
    cfg = SynthConfig(frames=12, motion="walk", severity=1.0, width=640, height=360, seed=0,
                      line_delay=0.0)  # fmt: skip
    renderer = SequenceRenderer(cfg)
    frames = list(renderer)
    poses = {}
    for tau in (0.0, 1e-4):
        pipe = OdometryPipeline(renderer.K, None, tau,
                                PipelineOptions(model="gs", backend="pairwise"))  # fmt: skip
        poses[tau] = [pipe.process(round(f.stamp * 1e9), f.image) for f in frames]
    assert sum("turning camera" in r.reason for r in poses[0.0]) >= 5
    for a, b in zip(poses[0.0], poses[1e-4], strict=True):
        np.testing.assert_allclose(a.T_world_cam, b.T_world_cam, atol=1e-9)


def test_a_short_readout_keeps_the_walk_going_forward():
    """A walk with a 7 ms readout (20 us per row): the fitted turn rates can take up part of
    each step's expansion, and the direction from them alone pointed 100-130 deg off (the
    replay 0.196 m off instead of 0.034 m); the chain takes the direction, of those from the
    fitted and the constant turn rate, that puts more tracks in front of both cameras."""
    cfg = SynthConfig(frames=30, motion="walk", severity=1.0, width=640, height=360, seed=0,
                      line_delay=20e-6)  # fmt: skip
    renderer = SequenceRenderer(cfg)
    pipe = OdometryPipeline(renderer.K, None, cfg.tau, PipelineOptions(backend="pairwise"))
    est, gt = {}, {}
    for f in renderer:
        s = round(f.stamp * 1e9)
        est[s], gt[s] = pipe.process(s, f.image).T_world_cam, ground_truth_pose(f)
    stamps = sorted(est)
    R0 = gt[stamps[0]][:3, :3] @ est[stamps[0]][:3, :3].T
    step_est = R0 @ (est[stamps[-1]][:3, 3] - est[stamps[0]][:3, 3])
    step_gt = gt[stamps[-1]][:3, 3] - gt[stamps[0]][:3, 3]
    cos = step_est @ step_gt / np.linalg.norm(step_est) / np.linalg.norm(step_gt)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))) < 20.0


def test_a_pair_with_a_baseline_after_a_turn_goes_to_the_pair_estimator(monkeypatch):
    """The turning camera is tried first only after a turning camera's pair, and a pair that
    it does not explain (a step of 30 cm after two turns) is posed by the pair
    estimator as before, with its depths and scale: nothing is forced to be a rotation."""
    calls = []
    estimate = pairwise.estimate_relative_pose
    monkeypatch.setattr(pairwise, "estimate_relative_pose",
                        lambda *a, **k: calls.append(1) or estimate(*a, **k))
    rng = np.random.default_rng(3)
    K = np.array([[500.0, 0, 320], [0, 500, 180], [0, 0, 1]])
    X = np.column_stack([rng.uniform(-3, 3, 300), rng.uniform(-2, 2, 300),
                         rng.uniform(4, 10, 300)])  # fmt: skip
    ids = np.arange(300)
    # cameras (world from camera): two turns of 1.5 deg while walking 3 cm forward (a step to
    # the side would alias with the turn), then a 30 cm step
    poses = [(np.eye(3), np.zeros(3))]
    for k in (1, 2):
        poses.append((so3_exp(np.radians([0.3, 1.5 * k, 0.2 * k])), np.array([0, 0, 0.03 * k])))
    poses.append((poses[-1][0], np.array([0.3, 0.02, 0.05])))

    def project(R, p):
        q = (X - p) @ R
        return (q[:, :2] / q[:, 2:]) * 500 + K[:2, 2]

    chain = pairwise.PairwiseChain(K, None, 0.0, "rs", "fast", pairwise.RansacOptions(),
                                   pairwise.LMOptions(), 1.0, True, 4.0, 0)  # fmt: skip
    steps, rotations = [], []
    for (Ra, pa), (Rb, pb) in zip(poses, poses[1:], strict=False):
        uv_a = project(Ra, pa) + rng.normal(0, 0.2, (300, 2))
        uv_b = project(Rb, pb) + rng.normal(0, 0.2, (300, 2))
        steps.append(chain.step(TrackedPair(uv_a, uv_b, ids), 1 / 30, len(steps)))
        rotations.append(chain.T_world_cam[:3, :3].copy())
    assert [s.status for s in steps] == ["posed"] * 3
    assert "turning camera" in steps[0].reason and "turning camera" in steps[1].reason
    assert "turning camera" not in steps[2].reason
    assert len(calls) == 2  # the first pair and the step; not the second turn
    assert np.isfinite(steps[2].relative.depths_curr).sum() > 200
    # the second turn, without the pair estimator
    assert np.degrees(np.linalg.norm(so3_log(rotations[1].T @ poses[2][0]))) < 0.1
