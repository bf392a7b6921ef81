"""RS reprojection kernels of the odometry: Jacobians against finite differences, exact data
giving zero residual, motion-only tracking and the window BA recovering known states."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import TOL

from rsvo_ros.core.geometry import so3_exp
from rsvo_ros.odometry import rs_projection as rp

FOCAL = 500.0


NP = rp.FRAME_PARAMS  # [dtheta, dp, dw, dv, da]


def _frame(rng):
    return (so3_exp(rng.normal(0, 0.3, 3)), rng.normal(0, 1, 3), rng.normal(0, 1.0, 3),
            rng.normal(0, 2.0, 3), rng.normal(0, 40.0, 3))  # fmt: skip


def _perturb(state, k, eps):
    R, p, w, v, a = (np.array(x, float) for x in state)
    d = np.zeros(NP)
    d[k] = eps
    return (R @ so3_exp(d[0:3]), p + d[3:6], w + d[6:9], v + d[9:12], a + d[12:15])


def _obs(state, s, X):
    Jf, JX = np.empty((2, NP)), np.empty((2, 3))
    R, p, w, v, a = state
    ex, ey, ok = rp._observe(rp._rows(R), tuple(p), tuple(w), tuple(v), tuple(a), s, tuple(X),
                             (0.1, -0.05), FOCAL, Jf, JX)  # fmt: skip
    assert ok
    return np.array([ex, ey]), Jf, JX


def test_observation_jacobians_match_finite_differences(rng):
    for _ in range(5):
        state = _frame(rng)
        R, p = state[0], state[1]
        X = p + R @ np.array([rng.normal(0, 1), rng.normal(0, 1), rng.uniform(3, 8)])
        s = rng.uniform(-0.015, 0.015)
        e0, Jf, JX = _obs(state, s, X)
        scale = np.abs(Jf).max() + np.abs(JX).max()
        for k in range(NP):
            h = 1e-6
            num = (_obs(_perturb(state, k, h), s, X)[0] - _obs(_perturb(state, k, -h), s, X)[0])
            assert np.allclose(num / (2 * h), Jf[:, k], atol=TOL["jacobian_rel"] * scale), k
        for k in range(3):
            d = np.zeros(3)
            d[k] = 1e-6
            num = _obs(state, s, X + d)[0] - _obs(state, s, X - d)[0]
            assert np.allclose(num / 2e-6, JX[:, k], atol=TOL["jacobian_rel"] * scale), k


def test_landmark_jacobians_match_finite_differences(rng):
    state = _frame(rng)
    xa, sa, rho = (0.2, -0.1), 0.008, 0.25
    JA, Jrho = np.empty((3, NP)), np.empty(3)

    def point(st, r):
        R, p, w, v, a = st
        return np.array(rp._landmark(rp._rows(R), tuple(p), tuple(w), tuple(v), tuple(a), sa,
                                     xa, r, np.empty((3, NP)), np.empty(3)))  # fmt: skip

    R, p, w, v, a = state
    rp._landmark(rp._rows(R), tuple(p), tuple(w), tuple(v), tuple(a), sa, xa, rho, JA, Jrho)
    assert np.abs(JA[:, 12:]).max() > 0  # the acceleration moves the anchor's row camera
    for k in range(NP):
        num = point(_perturb(state, k, 1e-6), rho) - point(_perturb(state, k, -1e-6), rho)
        assert np.allclose(num / 2e-6, JA[:, k], atol=1e-5 * np.abs(JA).max()), k
    num = (point(state, rho + 1e-7) - point(state, rho - 1e-7)) / 2e-7
    assert np.allclose(num, Jrho, rtol=1e-5)
    # the anchor's own row camera sees the point exactly on its bearing, 1/rho away
    Rs, ps = rp.row_camera(R, p, w, v, a, sa)
    Xc = Rs.T @ (point(state, rho) - ps)
    assert np.allclose(Xc, np.array([xa[0], xa[1], 1.0]) / rho)


def _scene(rng, n=150):
    X = np.column_stack([rng.uniform(-4, 4, n), rng.uniform(-2, 2, n), rng.uniform(4, 12, n)])
    return X


def _project(state, X, tau, row_ref, K_f, iterations=30):
    """Exact RS projection (fixed point on the row) -> normalized coords and row times."""
    R, p, w, v, a = state
    s = np.zeros(len(X))
    for _ in range(iterations):
        x = np.empty((len(X), 2))
        for i in range(len(X)):
            Rs, ps = rp.row_camera(R, p, w, v, a, s[i])
            Xc = Rs.T @ (X[i] - ps)
            x[i] = Xc[:2] / Xc[2]
        s = (x[:, 1] * K_f + row_ref - row_ref) * tau  # rows measured from the reference row
    return x, s


@pytest.mark.parametrize("acc", [(0.0, 0.0, 0.0), (60.0, -30.0, 20.0)])
def test_motion_only_tracking_recovers_pose_velocities_and_acceleration(rng, acc):
    tau = 40e-6
    X = _scene(rng, 300)
    truth = (so3_exp([0.02, -0.05, 0.01]), np.array([0.1, -0.05, 0.3]),
             np.array([0.4, -0.8, 0.2]), np.array([1.5, 0.2, -0.5]), np.array(acc))  # fmt: skip
    x, s = _project(truth, X, tau, 0.0, FOCAL)
    start = (np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3))
    R, p, w, v, a, res, cost, H = rp.track_frame(*start, X, x, s, FOCAL, 1.0, np.zeros(9),
                                                 np.zeros(9), 1e-12, 50)  # fmt: skip
    assert H.shape == (NP, NP)
    assert np.abs(res).max() < 1e-6
    assert np.allclose(R, truth[0], atol=1e-7) and np.allclose(p, truth[1], atol=1e-7)
    assert np.allclose(w, truth[2], atol=1e-4) and np.allclose(v, truth[3], atol=1e-4)
    assert np.allclose(a, truth[4], atol=1e-2)


def test_tracking_position_prior_damps_a_poorly_fixed_position(rng):
    """Few noisy points fix a frame's position poorly; a prior centred on the true position
    (the constant-velocity prediction in the window) brings it closer, a tight one holds it
    at its centre, and a prior of the wrong length is an error, not a read past the array."""
    tau = 40e-6
    X = _scene(rng, 25)
    truth = (so3_exp([0.02, -0.05, 0.01]), np.array([0.1, -0.05, 0.3]),
             np.array([0.4, -0.8, 0.2]), np.array([1.5, 0.2, -0.5]), np.zeros(3))  # fmt: skip
    x, s = _project(truth, X, tau, 0.0, FOCAL)
    start = (truth[0], truth[1] + [0.0, 0.0, 0.05], truth[2], truth[3], np.zeros(3))
    errors = {}
    for name, p_std, centre in (("none", 0.0, truth[1]), ("truth", 0.01, truth[1]),
                                ("tight", 1e-5, truth[1] + [0.02, 0.0, 0.0])):
        off = []
        for trial in range(20):
            noisy = x + np.random.default_rng(trial).normal(0.0, 1.0 / FOCAL, x.shape)
            mu = np.concatenate([truth[2], truth[3], centre])
            p2 = np.concatenate([np.full(6, 1e-6), np.full(3, 1.0 / p_std**2 if p_std else 0.0)])
            _, p, *_ = rp.track_frame(*start, X, noisy, s, FOCAL, 1.0, mu, p2, 0.0, 30)
            off.append(np.linalg.norm(p - centre))
        errors[name] = float(np.sqrt(np.mean(np.square(off))))
    assert errors["truth"] < 0.5 * errors["none"]
    assert errors["tight"] < 1e-3
    with pytest.raises(ValueError, match="9 entries"):
        rp.track_frame(*start, X, x, s, FOCAL, 1.0, np.zeros(6), np.zeros(6), 0.0, 5)


@pytest.mark.parametrize("seed", [0, 1])
def test_window_ba_recovers_states_and_depths_from_a_perturbed_start(seed):
    rng = np.random.default_rng(seed)
    tau = 30e-6
    K = 4
    truth = []
    for k in range(K):
        truth.append((so3_exp([0.0, 0.03 * k, 0.01 * k]), np.array([0.25 * k, 0.02 * k, 0.05 * k]),
                      rng.normal(0, 0.5, 3), rng.normal(0, 1.0, 3) + [1.0, 0, 0], np.zeros(3)))
    X = _scene(rng, 120)
    obs = [_project(st, X, tau, 0.0, FOCAL) for st in truth]
    # anchor every landmark in frame 0, observed by frames 1..3
    lm_x, lm_s = obs[0][0], obs[0][1]
    R0, p0, w0, v0, a0 = truth[0]
    depth = np.array([(rp.row_camera(R0, p0, w0, v0, a0, lm_s[i])[0].T
                       @ (X[i] - rp.row_camera(R0, p0, w0, v0, a0, lm_s[i])[1]))[2]
                      for i in range(len(X))])  # fmt: skip
    obs_kf = np.repeat(np.arange(1, K), len(X))
    obs_lm = np.tile(np.arange(len(X)), K - 1)
    obs_x = np.concatenate([obs[k][0] for k in range(1, K)])
    obs_s = np.concatenate([obs[k][1] for k in range(1, K)])
    R = np.stack([t[0] for t in truth])
    p = np.stack([t[1] for t in truth])
    w = np.stack([t[2] for t in truth])
    v = np.stack([t[3] for t in truth])
    acc = np.zeros((K, 3))
    # gauge: frames 0 and 1 fixed in pose; velocities and the rest free, accelerations held
    col = -np.ones((K, NP), np.int64)
    n = 0
    for k in range(K):
        for i in range(12):
            if k >= 2 or i >= 6:
                col[k, i] = n
                n += 1
    mu, p2 = np.zeros((K, 6)), np.zeros((K, 6))
    rho_true = 1.0 / depth
    # exact data: zero cost at the truth
    res = np.zeros((len(obs_kf), 2))
    c = rp._window_cost(R, p, w, v, acc, obs_kf, obs_lm, obs_x, obs_s,
                        np.zeros(len(X), np.int64), lm_x, lm_s, rho_true, FOCAL, 1.0, mu, p2,
                        0.0, res)  # fmt: skip
    assert c < 1e-12
    # perturbed start converges back
    Rp = R.copy()
    Rp[2:] = Rp[2:] @ so3_exp([0.01, -0.01, 0.005])
    pp = p + [[0, 0, 0], [0, 0, 0], [0.02, -0.01, 0.0], [0.03, 0.0, 0.02]]
    wp, vp = w * 0.8, v * 0.9
    out = rp.window_lm(Rp, pp, wp, vp, acc, obs_kf, obs_lm, obs_x, obs_s,
                       np.zeros(len(X), np.int64), lm_x, lm_s, rho_true * 1.2, FOCAL, 1.0, mu,
                       p2, 0.0, col, n, 100)  # fmt: skip
    R2, p2_, w2, v2, acc2, rho2, res2, cost, it = out
    assert np.all(acc2 == 0.0)  # held
    assert np.abs(res2).max() < 1e-4
    assert np.allclose(p2_, p, atol=1e-4) and np.allclose(rho2, rho_true, rtol=1e-3)
    assert np.allclose(w2[1:], w[1:], atol=0.05)


def _mixed_window(rng, held_acc: bool):
    """A window whose landmarks are anchored in every frame, seen by frames before and after
    their anchor and by the anchor itself, with the first two frames' poses held (and the
    accelerations held or free): every path of the window system's accumulation."""
    tau, K, M = 30e-6, 4, 40
    states = [(so3_exp([0.01 * k, 0.03 * k, 0.01 * k]),
               np.array([0.25 * k, 0.02 * k, 0.05 * k]), rng.normal(0, 0.5, 3),
               rng.normal(0, 1.0, 3) + [1.0, 0, 0], rng.normal(0, 20.0, 3)) for k in range(K)]
    X = _scene(rng, M)
    obs = [_project(st, X, tau, 0.0, FOCAL) for st in states]
    lm_anchor = np.arange(M) % K
    lm_x = np.array([obs[lm_anchor[j]][0][j] for j in range(M)])
    lm_s = np.array([obs[lm_anchor[j]][1][j] for j in range(M)])
    obs_kf, obs_lm = [], []
    for j in range(M):
        for k in range(K):
            if k != lm_anchor[j] or j % 3 == 0:  # a third also seen by their own anchor
                obs_kf.append(k)
                obs_lm.append(j)
    obs_kf, obs_lm = np.array(obs_kf, np.int64), np.array(obs_lm, np.int64)
    # measurements off the exact projections, so the IRLS weights differ
    obs_x = np.array([obs[k][0][j] for k, j in zip(obs_kf, obs_lm, strict=True)]) + rng.normal(
        0, 2.0 / FOCAL, (len(obs_kf), 2))
    obs_s = np.array([obs[k][1][j] for k, j in zip(obs_kf, obs_lm, strict=True)])
    R, p, w, v, acc = (np.stack([st[i] for st in states]) for i in range(5))
    n_par = 12 if held_acc else NP
    col = -np.ones((K, NP), np.int64)
    n = 0
    for k in range(K):
        for i in range(n_par):
            if k >= 2 or 6 <= i < 12:
                col[k, i] = n
                n += 1
    rho = np.array([1.0 / np.linalg.norm(X[j] - states[lm_anchor[j]][1]) for j in range(M)])
    rho *= rng.uniform(0.9, 1.1, M)
    mu, p2 = rng.normal(0, 0.1, (K, 6)), np.full((K, 6), 3.0)
    return (R, p, w, v, acc, obs_kf, obs_lm, obs_x, obs_s, lm_anchor, lm_x, lm_s, rho, FOCAL,
            1.5, mu, p2, 0.0 if held_acc else 1e-4), col, n, n_par  # fmt: skip


def _dense_system(args, col, n, n_par):
    """The window's IRLS normal equations by stacking each observation's full Jacobian (all
    frames' parameters, then every inverse depth): (H, g) over free columns and landmarks,
    and the residuals (n_obs, 2)."""
    (R, p, w, v, acc, obs_kf, obs_lm, obs_x, obs_s, lm_anchor, lm_x, lm_s, rho, focal, robust,
     mu, p2, acc_p2) = args  # fmt: skip
    K, M = R.shape[0], len(rho)
    free = col >= 0
    free[:, n_par:] = False
    H = np.zeros((K * NP + M, K * NP + M))
    g = np.zeros(K * NP + M)
    residuals = np.zeros((len(obs_kf), 2))
    for o in range(len(obs_kf)):
        k, j = obs_kf[o], obs_lm[o]
        a = lm_anchor[j]
        JA, Jrho = np.empty((3, NP)), np.empty(3)
        Xw = rp._landmark(rp._rows(R[a]), tuple(p[a]), tuple(w[a]), tuple(v[a]), tuple(acc[a]),
                          lm_s[j], tuple(lm_x[j]), rho[j], JA, Jrho)  # fmt: skip
        Jf, JX = np.empty((2, NP)), np.empty((2, 3))
        ex, ey, ok = rp._observe(rp._rows(R[k]), tuple(p[k]), tuple(w[k]), tuple(v[k]),
                                 tuple(acc[k]), obs_s[o], Xw, tuple(obs_x[o]), focal, Jf, JX)
        assert ok
        J = np.zeros((2, K * NP + M))
        J[:, k * NP:(k + 1) * NP] += Jf
        J[:, a * NP:(a + 1) * NP] += JX @ JA
        J[:, K * NP + j] = JX @ Jrho
        e = residuals[o] = np.array([ex, ey])
        wt = 1.0 / (1.0 + e @ e / robust**2)
        H += wt * J.T @ J
        g += wt * J.T @ e
    for k in range(K):
        for i in range(6):
            c = k * NP + 6 + i
            H[c, c] += p2[k, i]
            g[c] += p2[k, i] * ((w[k, i] if i < 3 else v[k, i - 3]) - mu[k, i])
        for i in range(3):
            H[k * NP + 12 + i, k * NP + 12 + i] += acc_p2
            g[k * NP + 12 + i] += acc_p2 * acc[k, i]
    order = np.argsort(col[free])  # the free parameters in their columns' order
    idx = np.concatenate([np.flatnonzero(free.ravel())[order], K * NP + np.arange(M)])
    return H[np.ix_(idx, idx)], g[idx], residuals


@pytest.mark.parametrize("held_acc", [True, False])
def test_window_normal_equations_equal_the_stacked_jacobians(held_acc):
    rng = np.random.default_rng(3)
    args, col, n, n_par = _mixed_window(rng, held_acc)
    K, M = args[0].shape[0], len(args[12])
    Hcc, gc = np.zeros((n, n)), np.zeros(n)
    Hcp, hpp, gp = np.zeros((K, M, NP)), np.zeros(M), np.zeros(M)
    rp._window_system(*args, col, n_par, Hcc, gc, Hcp, hpp, gp)
    H, g, residuals = _dense_system(args, col, n, n_par)
    scale = np.abs(H).max()
    assert np.allclose(Hcc, H[:n, :n], rtol=0, atol=1e-12 * scale)
    assert np.allclose(gc, g[:n], rtol=0, atol=1e-12 * np.abs(g).max())
    assert np.allclose(hpp, np.diag(H)[n:], rtol=1e-12)
    assert np.allclose(gp, g[n:], rtol=1e-12, atol=1e-15)
    # each landmark's block couples it with the frames that see it or anchor it only
    for j in range(M):
        Hcp_free = np.zeros(n)
        for k in range(K):
            for i in range(n_par):
                if col[k, i] >= 0:
                    Hcp_free[col[k, i]] = Hcp[k, j, i]
        assert np.allclose(Hcp_free, H[:n, n + j], rtol=0, atol=1e-12 * scale), j
    # the cost's residuals (without derivatives) are the system's
    res = np.zeros((len(args[5]), 2))
    rp._window_cost(*args, res)
    assert np.array_equal(res, residuals)


@pytest.mark.parametrize("held_acc", [True, False])
def test_window_lm_step_is_the_dense_schur_complements(held_acc):
    """One step of the window LM (landmarks eliminated by their Schur complement, summed by
    frame pairs) equals the step of the dense damped system."""
    rng = np.random.default_rng(4)
    args, col, n, n_par = _mixed_window(rng, held_acc)
    (R, p, w, v, acc, obs_kf, obs_lm, obs_x, obs_s, lm_anchor, lm_x, lm_s, rho, focal, robust,
     mu, p2, acc_p2) = args  # fmt: skip
    H, g, _ = _dense_system(args, col, n, n_par)
    lam = 1e-4  # the first step's damping
    A = H + lam * np.diag(np.concatenate([np.maximum(np.diag(H)[:n], 1e-9),
                                          np.diag(H)[n:] + 1e-12 / lam]))  # fmt: skip
    step = np.linalg.solve(A, -g)
    out = rp.window_lm(R, p, w, v, acc, obs_kf, obs_lm, obs_x, obs_s, lm_anchor, lm_x, lm_s, rho,
                       focal, robust, mu, p2, acc_p2, col, n, 1)  # fmt: skip
    R1, p1, w1, v1, acc1, rho1, _, cost, it = out
    assert it == 1
    res = np.zeros((len(obs_kf), 2))
    assert cost < rp._window_cost(*args, res)  # the step was taken
    for k in range(2, R.shape[0]):  # free positions and velocities moved by the dense step
        assert np.allclose(p1[k] - p[k], step[col[k, 3:6]], rtol=1e-6, atol=1e-12)
    for k in range(R.shape[0]):
        assert np.allclose(w1[k] - w[k], step[col[k, 6:9]], rtol=1e-6, atol=1e-12)
    if not held_acc:
        assert np.allclose(acc1[2] - acc[2], step[col[2, 12:15]], rtol=1e-6, atol=1e-10)
    inside = (rho1 > rp.RHO_MIN) & (rho1 < rp.RHO_MAX)
    assert np.allclose((rho1 - rho)[inside], step[n:][inside], rtol=1e-6, atol=1e-12)
