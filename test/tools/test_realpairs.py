"""rsvo_bench --real and --realistic: real RS pairs with GS twins, realistic synthetic pairs."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from conftest import REPO_ROOT

from rsvo_ros.core.geometry import rotation_angle_deg, so3_exp
from rsvo_ros.estimation import estimate_relative_pose
from rsvo_ros.sim.realistic import realistic_pair
from rsvo_ros.sim.synth import project_points
from rsvo_ros.tools import realpairs
from rsvo_ros.tools.bench import main

REAL = REPO_ROOT / "data" / "realdata" / "bsrsc"
READOUT_FROM_TWINS = 0.42  # BS-RSC: RS->GS-twin displacement fits this readout (README)


@pytest.fixture(scope="module")
def real_report(tmp_path_factory):
    out = tmp_path_factory.mktemp("real")
    assert main(["--real", str(REAL), "--output", str(out), "--no-progress"]) == 0
    return json.loads((out / "real.json").read_text()), out


def test_the_real_pairs_ship_with_their_licence():
    assert (REAL / "LICENSE").read_text().startswith("MIT License")
    assert len(realpairs.load_pairs(REAL)) == 4


def test_real_pairs_report_every_method_and_a_picture(real_report):
    report, out = real_report
    s = report["summary"]
    assert set(s) == set(realpairs.METHODS)
    assert all(v["pairs"] == 4 for v in s.values())
    # every method poses every pair, except the paper's 8-point MVO baseline, which may fail on
    # these forward-motion pairs (since the refined tracks, 2026-11-25: pair_1, 4 inliers); a
    # failure is reported with its reason, never as a pose
    assert all(v["failed"] == 0 for m, v in s.items() if m != "ours mvo")
    assert s["ours mvo"]["failed"] <= 1
    for row in report["results"]:
        assert row["ok"] or (row["reason"] and row["unroll_px_median"] is None)
    # the GS twins' reference agrees with OpenCV's best GS pipeline on the RS tracks
    assert s["OpenCV USAC_MAGSAC (GS)"]["rot_err_deg_mean"] < 0.2
    # our GS model is that pipeline
    assert np.isclose(s["ours gs"]["rot_err_deg_mean"], s["OpenCV USAC_MAGSAC (GS)"]
                      ["rot_err_deg_mean"], atol=1e-6)  # fmt: skip
    assert (out / "real_pairs.png").stat().st_size > 100_000
    assert "| ours rs, stream |" in report["table"]


def test_rs_model_on_real_pairs_is_as_good_as_the_gs_pipeline(real_report):
    report = real_report[0]
    s = report["summary"]
    gs = s["OpenCV USAC_MAGSAC (GS)"]
    stream = s["ours rs, stream"]  # the product's mode: a video stream
    assert stream["rot_err_deg_mean"] <= 1.1 * gs["rot_err_deg_mean"]
    assert stream["dir_err_deg_median"] <= gs["dir_err_deg_median"] + 0.5
    # two-view mode keeps the GS pose on pairs 0-2 (two views of smooth real motion carry no
    # velocities: none reported, no harm done). On pair_3 the held-out test finds a real RS
    # gain (with the tracks re-tracked from the images' shift: 0.070 px^2 per point, 5
    # standard errors, 55 % of the points) that two views cannot tell from the pose: its RS
    # fit is 0.8 deg off on every seed (with KLT's own tracks: 0.10 deg on even seeds, 2.2 on
    # odd ones; README, "Real pairs")
    rows = {(r["pair"], r["method"]): r for r in report["results"]}
    for pair in ("pair_0", "pair_1", "pair_2"):
        two = rows[(pair, "ours rs, two-view")]
        assert two["rot_err_deg"] <= rows[(pair, "OpenCV USAC_MAGSAC (GS)")]["rot_err_deg"] + 0.01
        assert two["unroll_px_median"] <= two["nothing_px_median"] + 1e-9
    assert rows[("pair_3", "ours rs, two-view")]["rot_err_deg"] < 1.5


@pytest.fixture(scope="module")
def real_tracks() -> dict:
    return {pair.name: realpairs.prepare(pair) for pair in realpairs.load_pairs(REAL)}


def _rotation_errors(tracks, method: str, seeds) -> list[float]:
    return [realpairs.evaluate_pair(tracks, seed=seed, methods=(method,))[0].rot_err_deg
            for seed in seeds]


def test_stream_mode_equals_the_gs_pipeline_on_every_real_pair_and_seed(real_tracks):
    """The product's mode (a video stream) keeps the GS pose on all four pairs whatever the
    seed. (Two-view mode does not: on pair_3 it takes an RS fit, 0.8 deg off; README, "Real
    pairs".)"""
    for name, tracks in real_tracks.items():
        gs = _rotation_errors(tracks, "OpenCV USAC_MAGSAC (GS)", [0])[0]
        for err in _rotation_errors(tracks, "ours rs, stream", range(4)):
            assert err <= gs + 0.05, name


@pytest.mark.parametrize("window_px", [13, 17, 19])
def test_a_tolerant_start_near_the_local_scale_is_checked_by_the_best_gs_fit(monkeypatch,
                                                                             window_px):
    """pair_3 tracked with a 13-, 17- or 19-px KLT window: the tolerant GS start leaves a
    robust scale of 1.6-2.4 px, the best GS fit (MAGSAC) 0.72-0.74. The search took the first
    for strong RS distortion and went global, to RS fits 5.2-5.4 deg off in stream mode;
    checked by the best GS fit (estimator.LOCAL_CHECK_FACTOR) it stays local and keeps the
    GS pose. Without the check the failure comes back."""
    from functools import partial

    from rsvo_ros.odometry.tracker import TrackerOptions
    from rsvo_ros.twoview import estimator

    monkeypatch.setattr(realpairs, "TrackerOptions",
                        partial(TrackerOptions, window_px=window_px))
    tracks = realpairs.prepare(realpairs.load_pairs(REAL)[3])
    gs = _rotation_errors(tracks, "OpenCV USAC_MAGSAC (GS)", [0])[0]
    assert max(_rotation_errors(tracks, "ours rs, stream", range(2))) <= gs + 0.05
    monkeypatch.setattr(estimator, "LOCAL_CHECK_FACTOR", 1.0)
    assert min(_rotation_errors(tracks, "ours rs, stream", range(2))) > gs + 2.0


def test_stream_velocities_unroll_real_frames_with_the_right_readout():
    pair = realpairs.load_pairs(REAL)[1]
    tracks = realpairs.prepare(pair)
    res = {r.method: r for r in realpairs.evaluate_pair(tracks, READOUT_FROM_TWINS)}
    stream = res["ours rs, stream"]
    assert np.median(stream.unroll_px) < 0.5 * np.median(stream.nothing_px)


def test_bad_real_directories_fail_with_a_clear_message(tmp_path, capsys):
    assert main(["--real", str(tmp_path / "nowhere"), "--output", str(tmp_path)]) == 2
    assert "not a directory" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["--real", str(tmp_path / "empty"), "--output", str(tmp_path)]) == 2
    assert "no pair folders" in capsys.readouterr().err
    bad = tmp_path / "bad" / "p0"
    bad.mkdir(parents=True)
    for name in realpairs.PAIR_FILES:
        (bad / name).write_bytes(b"not a png")
    assert main(["--real", str(tmp_path / "bad"), "--output", str(tmp_path)]) == 2
    assert "cannot read" in capsys.readouterr().err


def test_unroll_moves_rs_pixels_to_the_middle_row_time():
    """With the true velocities and depths, unrolling lands on the GS-twin positions of a
    realistic pair (no noise on the twins; the pixel noise stays)."""
    p = realistic_pair(3)
    K, tau = p.K, p.line_delay
    height = 2 * K[1, 2] + 1
    keep = ~p.outliers
    est = estimate_relative_pose(p.pts_prev[keep], p.pts_curr[keep], K, tau,
                                 rows_prev=p.rows_prev[keep], rows_curr=p.rows_curr[keep],
                                 frame_interval=p.frame_interval)
    assert est.ok
    moved = realpairs.unroll(p.pts_prev[keep], est.depths_prev, est.w_prev, est.v_prev, K, tau,
                             (height - 1) / 2, p.rows_prev[keep])
    nothing = np.linalg.norm(p.pts_prev[keep] - p.twin_prev[keep], axis=1)
    left = np.linalg.norm(moved - p.twin_prev[keep], axis=1)
    assert np.nanmedian(left) < 0.15 * np.median(nothing)
    zero = realpairs.unroll(p.pts_prev[keep], est.depths_prev, np.zeros(3), np.zeros(3), K, tau,
                            (height - 1) / 2, p.rows_prev[keep])
    assert np.allclose(zero[np.isfinite(zero).all(1)],
                       p.pts_prev[keep][np.isfinite(zero).all(1)])  # fmt: skip


def test_realistic_pairs_are_reproducible_and_consistent():
    a, b = realistic_pair(7), realistic_pair(7)
    assert np.array_equal(a.pts_prev, b.pts_prev) and np.array_equal(a.twin_curr, b.twin_curr)
    assert 100 < len(a.pts_prev) <= 500 and 0 < a.outliers.mean() < 0.5
    # without a readout the RS pixels are their GS twins (up to the noise)
    g = realistic_pair(7, readout=0.0)
    err = np.linalg.norm(g.pts_prev - g.twin_prev, axis=1)[~g.outliers]
    assert np.median(err) < 0.6


def test_smooth_pairs_keep_the_gs_fit_and_strong_rs_keeps_the_rs_fit(paper_scene):
    """The model selection: on smooth realistic pairs the RS model reports the GS pose (zero
    velocities from two views; the constant velocity of the motion in a stream); on the
    paper's level 4 it keeps its velocities and beats the GS fit."""
    p = realistic_pair(1)
    kw = dict(rows_prev=p.rows_prev, rows_curr=p.rows_curr)
    two = estimate_relative_pose(p.pts_prev, p.pts_curr, p.K, p.line_delay, **kw)
    gs = estimate_relative_pose(p.pts_prev, p.pts_curr, p.K, 0.0, model="gs", **kw)
    assert two.ok and not np.any(two.w_prev) and not np.any(two.v_curr)
    assert rotation_angle_deg(two.R @ gs.R.T) < 1e-6
    stream = estimate_relative_pose(p.pts_prev, p.pts_curr, p.K, p.line_delay,
                                    frame_interval=p.frame_interval, **kw)
    w_cv = np.linalg.norm(stream.w_prev)
    assert stream.ok and np.isclose(w_cv, np.linalg.norm(stream.w_curr))
    assert np.isclose(w_cv, np.radians(rotation_angle_deg(gs.R)) / p.frame_interval, rtol=0.05)
    rng = np.random.default_rng(4)
    pair = paper_scene.frame_pair(rng, 4)
    noisy = [pts + rng.normal(0, 0.5, pts.shape) for pts in (pair.pts_prev, pair.pts_curr)]
    rs = estimate_relative_pose(*noisy, pair.K, pair.line_delay)
    gs = estimate_relative_pose(*noisy, pair.K, pair.line_delay, model="gs")
    assert np.linalg.norm(rs.w_prev) > 0.1
    assert rotation_angle_deg(pair.R @ rs.R.T) < 0.5 * rotation_angle_deg(pair.R @ gs.R.T)


def test_quick_realistic_bench(tmp_path, capsys):
    assert main(["--realistic", "--trials", "2", "--output", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    assert "tuning seeds 0-1" in text and "held-out seeds 1000-1001" in text
    data = json.loads((tmp_path / "realistic.json").read_text())
    assert set(data["groups"]) == {"tuning", "held-out"}


def test_realpairs_reads_color_images(tmp_path):
    """The loader turns the PNGs to gray and keeps the pair's name."""
    src = REAL / "pair_0"
    dst = tmp_path / "one" / "mine"
    dst.mkdir(parents=True)
    for name in realpairs.PAIR_FILES:
        img = cv2.imread(str(src / name))
        cv2.imwrite(str(dst / name), cv2.resize(img, (512, 384)))
    pairs = realpairs.load_pairs(tmp_path / "one")
    assert [p.name for p in pairs] == ["mine"] and pairs[0].shape == (384, 512)


def _constant_velocity_tracks(readout: float, frame_interval: float = 1 / 30,
                              n: int = 400) -> realpairs.PairTracks:  # fmt: skip
    """Noise-free RS tracks of a camera turning and moving at one constant velocity through
    both frames, exposed with ``readout`` frame intervals."""
    rng = np.random.default_rng(3)
    width, height = 640, 480
    K = realpairs.intrinsics_guess(width, height)
    w, v = np.array([0.9, -1.2, 0.5]), np.array([1.0, 0.2, 3.0])  # rad/s, m/s
    tau = readout * frame_interval / height
    X = rng.uniform([-4, -3, 2], [4, 3, 8], (n, 3))

    def row_pose(k):
        def pose(rows):
            t = k * frame_interval + np.asarray(rows, float) * tau
            return so3_exp(t[:, None] * w), t[:, None] * v

        return pose

    p0, p1 = (project_points(X, row_pose(k), K, height) for k in (0, 1))
    ok = np.isfinite(p0).all(1) & np.isfinite(p1).all(1)
    pts = (p0[ok], p1[ok])
    return realpairs.PairTracks("constant velocity", K, pts, pts, np.eye(3), np.zeros(3), 1.0, 0)


def test_readout_from_two_frames_finds_an_exact_constant_velocity_readout():
    for truth in (0.3, 0.9):
        est = realpairs.estimate_readout([_constant_velocity_tracks(truth)], bootstrap=0)
        assert est.readout == pytest.approx(truth, abs=0.1)
        assert est.status == "not observable" and "1 pair" in est.reason  # one pair: no spread


def test_readout_auto_on_real_pairs_reports_the_estimate_and_keeps_the_assumed(tmp_path,
                                                                                capsys):
    assert main(["--real", str(REAL), "--readout", "auto", "--output", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "real.json").read_text())
    auto = report["readout_auto"]
    assert report["readout_frame_intervals"] == realpairs.DEFAULT_READOUT
    assert set(auto["per_pair"]) == {f"pair_{i}" for i in range(4)}
    costs = np.array([c for _, c in auto["curve"]])
    assert len(costs) == len(realpairs.LineDelayOptions().readout_grid)
    # the README's finding: the pooled cost of two smooth real frames is nearly flat in the
    # readout and the pairs disagree, so the estimate is not trusted
    assert costs.max() < 1.05 * costs.min()
    assert auto["status"] == "not observable" and "disagree" in auto["reason"]
    assert np.isfinite([auto["unroll_px_median_assumed"], auto["nothing_px_median"]]).all()
    assert "readout from the RS tracks alone" in capsys.readouterr().out
    with pytest.raises(SystemExit) as bad:
        main(["--real", str(REAL), "--readout", "soon", "--output", str(tmp_path)])
    assert bad.value.code == 2 and "expected 'auto' or a number" in capsys.readouterr().err
