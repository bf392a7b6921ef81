"""estimate_relative_pose: accuracy on exact data, bad input, degenerate data, determinism."""

import numpy as np
import pytest
from conftest import TOL

from rsvo_ros.core.geometry import angle_between_deg, rotation_angle_deg, so3_exp
from rsvo_ros.estimation import RansacOptions, estimate_relative_pose

K = np.array([[1000.0, 0.0, 639.5], [0.0, 1000.0, 359.5], [0.0, 0.0, 1.0]])


def _errors(pair, res):
    return rotation_angle_deg(pair.R @ res.R.T), angle_between_deg(pair.t, res.t)


@pytest.mark.parametrize("model", ["gs", "mvo", "rs"])
def test_global_shutter_data_is_recovered_by_every_model(paper_scene, model):
    pair = paper_scene.frame_pair(np.random.default_rng(1), level=1)  # no RS distortion
    res = estimate_relative_pose(pair.pts_prev, pair.pts_curr, pair.K, pair.line_delay,
                                 model=model, seed=0)
    assert res.ok, res.reason
    rot, tdir = _errors(pair, res)
    assert rot < TOL["gs_data_rot_deg"]
    assert tdir < TOL["gs_data_tdir_deg"]
    assert res.inlier_ratio > 0.95
    assert abs(np.linalg.norm(res.t) - 1.0) < 1e-9
    if model != "rs":
        assert not np.any(np.concatenate([res.w_prev, res.v_prev, res.w_curr, res.v_curr]))


def test_rs_model_beats_gs_on_strong_rolling_shutter(paper_scene):
    """Level 6, noise-free: the RS estimator finds the exact motion where GS cannot."""
    rng = np.random.default_rng(2024)
    rs_err, gs_err, rs_inl = [], [], []
    for _ in range(6):
        pair = paper_scene.frame_pair(rng, level=6)
        rs = estimate_relative_pose(pair.pts_prev, pair.pts_curr, pair.K, pair.line_delay,
                                    model="rs", seed=0)
        gs = estimate_relative_pose(pair.pts_prev, pair.pts_curr, pair.K, pair.line_delay,
                                    model="gs", seed=0)
        rs_err.append(_errors(pair, rs)[0])
        gs_err.append(_errors(pair, gs)[0])
        rs_inl.append(rs.inlier_ratio)
    assert np.median(rs_err) < TOL["noise_free_rot_deg"]
    assert np.median(rs_err) < 0.1 * np.median(gs_err)
    assert np.median(rs_inl) > 0.97


def test_rs_recovers_the_velocities_on_exact_data(paper_scene):
    pair = paper_scene.frame_pair(np.random.default_rng(2024), level=6)
    res = estimate_relative_pose(pair.pts_prev, pair.pts_curr, pair.K, pair.line_delay,
                                 model="rs", seed=0)
    assert res.ok
    scale = np.linalg.norm(pair.t)
    assert np.linalg.norm(res.w_curr - pair.w_curr) < 0.05 * np.linalg.norm(pair.w_curr)
    assert np.linalg.norm(res.v_curr * scale - pair.v_curr) < 0.05 * np.linalg.norm(pair.v_curr)


def test_paper_mode_runs_algorithm_1(paper_scene):
    pair = paper_scene.frame_pair(np.random.default_rng(7), level=3)
    res = estimate_relative_pose(pair.pts_prev, pair.pts_curr, pair.K, pair.line_delay,
                                 model="rs", mode="paper", seed=0,
                                 ransac=RansacOptions(rs_iterations=60))
    assert res.ok, res.reason
    assert res.inlier_ratio > 0.9
    assert _errors(pair, res)[0] < 1.0


def test_same_seed_same_result(paper_scene):
    pair = paper_scene.frame_pair(np.random.default_rng(5), level=4)
    noisy = pair.pts_curr + np.random.default_rng(0).normal(size=pair.pts_curr.shape)
    a = estimate_relative_pose(pair.pts_prev, noisy, pair.K, pair.line_delay, seed=3)
    b = estimate_relative_pose(pair.pts_prev, noisy, pair.K, pair.line_delay, seed=3)
    assert np.array_equal(a.R, b.R) and np.array_equal(a.t, b.t)
    assert np.array_equal(a.inliers, b.inliers)


def test_concurrent_calls_give_the_sequential_results(paper_scene):
    """The node estimates from its tracking and mapping threads at once, and the GS starts of
    the global search are fitted on a thread pool with OpenCV's generator seeded per thread:
    four calls at once (strong distortion: the global search, its starts on the pool) give
    exactly what one after the other gives."""
    from concurrent.futures import ThreadPoolExecutor

    rng = np.random.default_rng(11)
    pairs = [paper_scene.frame_pair(rng, level=5) for _ in range(4)]
    noisy = [p.pts_curr + rng.normal(size=p.pts_curr.shape) for p in pairs]

    def run(k):
        p = pairs[k]
        return estimate_relative_pose(p.pts_prev, noisy[k], p.K, p.line_delay, seed=k)

    sequential = [run(k) for k in range(4)]
    with ThreadPoolExecutor(4) as pool:
        concurrent = list(pool.map(run, range(4)))
    for a, b in zip(sequential, concurrent, strict=True):
        assert a.ok and b.ok
        assert np.array_equal(a.R, b.R) and np.array_equal(a.t, b.t)
        assert np.array_equal(a.w_curr, b.w_curr) and np.array_equal(a.inliers, b.inliers)


def test_gs_starts_dropped_by_a_local_search_are_fitted_when_asked_for(paper_scene):
    """The extra GS starts begin before the estimator knows whether the search is local; a
    local search drops those not begun (``cancel``), and if it then needs them after all,
    ``result`` fits them on the caller: the same starts either way."""
    from rsvo_ros.twoview.options import LMOptions
    from rsvo_ros.twoview.search import GSStarts
    from rsvo_ros.twoview.state import make_correspondences

    pair = paper_scene.frame_pair(np.random.default_rng(3), level=4)
    row_ref = pair.K[1, 2]
    corr = make_correspondences(pair.pts_prev, pair.pts_curr, pair.K, pair.line_delay, row_ref,
                                pair.pts_prev[:, 1], pair.pts_curr[:, 1])
    rows = pair.pts_prev[:, 1] - row_ref

    def starts(cancel):
        gs = GSStarts(corr, rows, RansacOptions(), LMOptions(), 0, 15)
        if cancel:
            gs.cancel()
        return gs.result()

    whole, dropped = starts(False), starts(True)
    assert len(whole) == 4  # one threshold on all points, three row bands
    assert len(dropped) == len(whole)
    for a, b in zip(whole, dropped, strict=True):
        assert np.array_equal(a.R, b.R) and np.array_equal(a.t, b.t)


def test_the_best_gs_fit_begun_early_is_the_same_fit(paper_scene):
    """``GSStarts(best_fit, speculate=True)`` begins the best GS fit on the worker, first;
    ``best`` gives that fit (the one the caller would have made) and the extra starts are the
    same; without ``speculate`` the caller fits it; ``drop_best`` drops it."""
    import threading
    import time

    from rsvo_ros.twoview.essential import estimate_gs_opencv
    from rsvo_ros.twoview.estimator import GS_METHOD
    from rsvo_ros.twoview.options import LMOptions
    from rsvo_ros.twoview.search import GSStarts
    from rsvo_ros.twoview.state import make_correspondences

    pair = paper_scene.frame_pair(np.random.default_rng(1), level=1)
    row_ref = pair.K[1, 2]
    corr = make_correspondences(pair.pts_prev, pair.pts_curr, pair.K, pair.line_delay, row_ref,
                                pair.pts_prev[:, 1], pair.pts_curr[:, 1])
    rows = pair.pts_prev[:, 1] - row_ref
    ransac = RansacOptions()
    threads = []

    def best_fit():
        threads.append(threading.current_thread().name)
        return estimate_gs_opencv(corr, ransac.threshold_px, ransac.confidence,
                                  ransac.null_max_iterations, 0, GS_METHOD)

    here = best_fit()
    for speculate in (True, False):
        threads.clear()
        gs = GSStarts(corr, rows, ransac, LMOptions(), 0, 15, best_fit, speculate)
        if speculate:  # a worker still busy (another test's fits) or not yet awake: wait
            deadline = time.monotonic() + 10.0
            while not (gs._best.running() or gs._best.done()) and time.monotonic() < deadline:
                time.sleep(0.001)
        R, t, mask = gs.best()[:3]
        assert np.array_equal(R, here[0]) and np.array_equal(t, here[1])
        assert np.array_equal(mask, here[2])
        assert threads == (["rsvo_gs_start_0"] if speculate else [threading.current_thread().name])
        assert len(gs.result()) == 4
    dropped = GSStarts(corr, rows, ransac, LMOptions(), 0, 15, best_fit, True)
    dropped.drop_best()
    assert len(dropped.result()) == 4  # the extra starts are not dropped with it
    with pytest.raises(ValueError, match="without a best fit"):
        GSStarts(corr, rows, ransac, LMOptions(), 0, 15).best()


def test_estimates_are_the_same_whether_the_best_fit_began_early(paper_scene):
    """The estimator begins the best GS fit early where the last two estimates needed it (a
    video's pairs); every estimate is the same to the bit either way, and the hint follows
    the pairs: level 1 (no RS distortion) needs it, level 4 (strong) searches globally."""
    import rsvo_ros.twoview.estimator as est

    pairs = [paper_scene.frame_pair(np.random.default_rng(s), level=lv)
             for s, lv in ((0, 1), (1, 1), (0, 4), (1, 4), (3, 1))]
    hint = est._BEST_FIT_HINT.last_two
    try:
        runs = {}
        for early in (True, False):
            runs[early] = []
            for pair in pairs:
                est._BEST_FIT_HINT.last_two = (early, early)
                res = estimate_relative_pose(pair.pts_prev, pair.pts_curr, pair.K,
                                             pair.line_delay, seed=0)
                runs[early].append((res, est._BEST_FIT_HINT.last_two[1]))
    finally:
        est._BEST_FIT_HINT.last_two = hint
    assert [needed for _, needed in runs[True]] == [True, True, False, False, True]
    for (a, needed_a), (b, needed_b) in zip(runs[True], runs[False], strict=True):
        assert a.ok and b.ok and needed_a == needed_b
        for key in ("R", "t", "w_prev", "v_prev", "w_curr", "v_curr", "inliers"):
            assert np.array_equal(getattr(a, key), getattr(b, key)), key
        assert a.iterations == b.iterations and a.cost == b.cost
    fresh = est._BestFitHint()
    assert fresh.expected  # a process starts expecting video
    fresh.note(False)
    assert not fresh.expected
    fresh.note(True)
    assert not fresh.expected  # one estimate alone does not decide
    fresh.note(True)
    assert fresh.expected


def _rotation_only_reference(x_prev, x_curr, focal, draws, voters):
    """The rotation-only fit written out in numpy (Kabsch by SVD, medians): what the compiled
    kernel must give."""

    def kabsch(b_p, b_c):
        U, _, Vt = np.linalg.svd(b_c.T @ b_p)
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
        return U @ D @ Vt

    def residuals(R, rows):
        rp = b_p[rows] @ R.T
        return focal * np.linalg.norm(rp[:, :2] / rp[:, 2:] - x_curr[rows, :2], axis=1)

    b_p = x_prev / np.linalg.norm(x_prev, axis=1, keepdims=True)
    b_c = x_curr / np.linalg.norm(x_curr, axis=1, keepdims=True)
    hyps = [kabsch(b_p[np.argsort(d)[:2]], b_c[np.argsort(d)[:2]]) for d in draws]
    R = hyps[int(np.argmin([np.median(residuals(R, voters)) for R in hyps]))]
    for _ in range(2):
        r = residuals(R, slice(None))
        keep = r <= np.median(r)
        R = kabsch(b_p[keep], b_c[keep])
    return float(np.median(residuals(R, slice(None)))), R


def test_the_compiled_rotation_only_fit_equals_its_numpy_reference():
    """A turning camera with some translation and a fifth of the matches wrong: the kernel's
    rotation and residual are the reference's, and the rotation is about the true one."""
    from rsvo_ros.twoview import kernels

    rng = np.random.default_rng(8)
    X = np.column_stack([rng.uniform(-3, 3, (300, 2)), rng.uniform(4, 15, 300)])
    R_true = so3_exp(np.array([0.01, -0.03, 0.005]))
    t = np.array([0.02, 0.0, 0.01])
    x_prev = X / X[:, 2:]
    Xc = X @ R_true.T + t
    x_curr = Xc / Xc[:, 2:]
    x_curr[:, :2] += rng.normal(0.0, 0.5 / 1000.0, (300, 2))
    wrong = rng.random(300) < 0.2
    x_curr[wrong, :2] += rng.uniform(-0.05, 0.05, (int(wrong.sum()), 2))
    draws = rng.random((16, 300))
    voters = np.linspace(0, 299, 100).astype(np.int64)
    b_p = x_prev / np.linalg.norm(x_prev, axis=1, keepdims=True)
    b_c = x_curr / np.linalg.norm(x_curr, axis=1, keepdims=True)
    med, R = kernels.rotation_only_fit(b_p, b_c, x_curr, 1000.0, draws, voters)
    med_ref, R_ref = _rotation_only_reference(x_prev, x_curr, 1000.0, draws, voters)
    assert abs(med - med_ref) < 1e-9 * max(1.0, med_ref)
    assert np.allclose(R, R_ref, atol=1e-12)
    # the true rotation, up to what the translation's parallax (0.1-0.3 deg) pulls it by
    assert rotation_angle_deg(R @ R_true.T) < 0.3
    assert 0.5 < med < 20.0  # that parallax is left over


def test_statistics_are_reported(paper_scene):
    pair = paper_scene.frame_pair(np.random.default_rng(5), level=2)
    res = estimate_relative_pose(pair.pts_prev, pair.pts_curr, pair.K, pair.line_delay)
    assert res.iterations > 0 and res.time_s > 0 and np.isfinite(res.cost)
    assert res.inliers.shape == (len(pair.pts_prev),) and res.inliers.dtype == bool


# --------------------------------------------------------------------------- bad input


def _points(rng, n=50):
    return rng.uniform([0, 0], [1279, 719], size=(n, 2))


@pytest.mark.parametrize(
    "case, message",
    [
        ("few", "at least 20"),
        ("nan", "non-finite"),
        ("inf", "non-finite"),
        ("shape", "differ in shape"),
        ("columns", "shape (N, 2)"),
        ("singular_K", "singular"),
        ("K_row", "last row"),
        ("identical", "identical"),
        ("model", "model must be one of"),
        ("mode", "mode must be one of"),
        ("line_delay", "line_delay"),
        ("frame_interval", "frame_interval must be finite and > 0"),
        ("predicted", "predicted must be a finite"),
    ],
)
def test_bad_input_raises_a_clear_value_error(rng, case, message):
    p, c, k = _points(rng), _points(rng), K.copy()
    kwargs = {}
    if case == "few":
        p, c = p[:10], c[:10]
    elif case == "nan":
        c[3, 1] = np.nan
    elif case == "inf":
        p[0, 0] = np.inf
    elif case == "shape":
        c = c[:-1]
    elif case == "columns":
        p = np.hstack([p, p[:, :1]])
    elif case == "singular_K":
        k[0, 0] = 0.0
    elif case == "K_row":
        k[2] = [0.0, 0.1, 1.0]
    elif case == "identical":
        p[:] = [100.0, 200.0]
    elif case == "model":
        kwargs["model"] = "fisheye"
    elif case == "mode":
        kwargs["mode"] = "slow"
    elif case == "line_delay":
        kwargs["line_delay"] = -1.0
    elif case == "frame_interval":
        kwargs["frame_interval"] = float("nan")
    elif case == "predicted":
        kwargs["predicted"] = (np.eye(3), np.array([np.nan, 0.0, 1.0]))
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        estimate_relative_pose(p, c, k, **{"line_delay": 50e-6, **kwargs})


@pytest.mark.parametrize("model", ["gs", "mvo", "rs"])
def test_pure_rotation_is_not_a_pose(rng, model):
    """No translation: the direction of t is undefined, so ok=False with a reason."""
    X = np.column_stack([rng.uniform(-4, 4, 200), rng.uniform(-2, 2, 200),
                         rng.uniform(4, 20, 200)])
    R = so3_exp(np.radians([1.0, 3.0, 0.5]))
    pts_prev = X[:, :2] / X[:, 2:] * 1000 + [639.5, 359.5]
    Xc = X @ R.T
    pts_curr = Xc[:, :2] / Xc[:, 2:] * 1000 + [639.5, 359.5]
    res = estimate_relative_pose(pts_prev, pts_curr, K, 0.0, model=model)
    assert not res.ok
    assert "parallax" in res.reason
    assert np.array_equal(res.R, np.eye(3)) and not res.t.any()


@pytest.mark.parametrize("model", ["gs", "rs"])
def test_random_correspondences_give_no_pose(rng, model):
    res = estimate_relative_pose(_points(rng, 200), _points(rng, 200), K, 50e-6, model=model)
    assert not res.ok
    assert res.reason
    assert np.array_equal(res.R, np.eye(3)) and not res.t.any()


def test_frame_interval_centres_the_velocity_prior_on_the_stream_motion():
    """Pairs of a shaking vehicle (synthetic, 0.3 px noise): given the frames' interval, the
    linear velocity comes out near the truth, and the translation direction better, than from
    two views alone (there: 140 % and 5.4 deg median errors; given it: 5 % and 1.8 deg). The
    angular velocity stays as poorly observed as without (its prior is as loose)."""
    from rsvo_ros.sim.synth import SequenceRenderer, SynthConfig, project_points

    cfg = SynthConfig(frames=10, motion="vehicle", severity=2.0, seed=3)
    renderer = SequenceRenderer(cfg)
    interval = 1.0 / cfg.rate_hz
    rng = np.random.default_rng(0)
    err = {None: [], interval: []}
    for k in range(2, 8):
        _, R_a, p_a, _, v_a, rows_a = renderer.frame_pose(k)
        _, R_b, p_b, _, _, rows_b = renderer.frame_pose(k + 1)
        X_cam = rng.uniform([-5.0, -2.0, 2.0], [5.0, 2.0, 12.0], (600, 3))
        X = X_cam @ R_a.T + p_a
        pts = [project_points(X, rows, renderer.K, cfg.height) for rows in (rows_a, rows_b)]
        ok = np.all([np.isfinite(p).all(1) & (p[:, 0] > 0) & (p[:, 0] < cfg.width)
                     for p in pts], axis=0)  # fmt: skip
        p_prev, p_curr = (p[ok][:400] + rng.normal(0, 0.3, (min(ok.sum(), 400), 2)) for p in pts)
        t = R_b.T @ (p_a - p_b)
        for fi in err:
            res = estimate_relative_pose(p_prev, p_curr, renderer.K, cfg.tau, model="rs",
                                         seed=0, frame_interval=fi)  # fmt: skip
            assert res.ok, res.reason
            err[fi].append([angle_between_deg(t, res.t),
                            np.linalg.norm(res.v_prev * np.linalg.norm(t) - v_a)
                            / np.linalg.norm(v_a)])  # fmt: skip
    alone, stream = np.median(err[None], axis=0), np.median(err[interval], axis=0)
    assert stream[0] < 0.5 * alone[0]  # translation direction
    assert stream[1] < 0.5 * alone[1] and stream[1] < 0.2  # linear velocity
