"""Rolling-shutter reprojection: residuals and Jacobians for tracking and the window BA (numba).

A frame's state is its camera at the reference row (the principal point's row) in the world,
``R`` (world <- camera) and ``p`` (position), its instantaneous motion ``w`` (rad/s) and
``v`` (map units/s) in that camera's frame, and its angular acceleration ``a`` (rad/s^2). The
camera that exposed row ``r`` is the reference one moved by ``s = (r - row_ref) * tau`` seconds
of that motion (CONTRACTS.md's convention, re-expressed at the reference row, plus a turn rate
that changes during the readout):

    R(s) = R Exp(s w + s^2/2 a),   p(s) = p + R (s v).

With ``a = 0`` this is the paper's constant velocity. Hand-held shake of 8-15 Hz turns the
camera at a rate that changes within one readout; constant velocity leaves 1.7-3.2 px RMS of a
walk's within-readout rotation unexplained at 100 us/row, the acceleration 0.3-0.6 px (README).
In the kernels the rotation is ``Exp(s w_s)`` with ``w_s = w + s/2 a``, so the derivative by
``a`` is ``s/2`` times the one by ``w``.

A world point ``X`` seen in row ``r`` is at ``X_c = Exp(-s w_s) (R^T (X - p) - s v)`` in that
row's camera and projects to ``(X_c0 / X_c2, X_c1 / X_c2)`` (normalized coordinates); residuals
are in pixels (times the focal length). Increments: ``R <- R Exp(dtheta)``, ``p <- p + dp``,
``w <- w + dw``, ``v <- v + dv``, ``a <- a + da``; a frame's 15 parameters are
``[dtheta, dp, dw, dv, da]``.

Landmarks of the window are inverse depths ``rho`` along the bearing ``b_a = (x_a, y_a, 1)`` of
their first observation, in the camera of the anchor keyframe's row ``s_a``:
``X = p_a(s_a) + R_a(s_a) b_a / rho``.

Pure numba/numpy, no ROS. ``test/odometry/test_rs_projection.py`` checks every Jacobian against
finite differences.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from rsvo_ros.core.small3 import JIT
from rsvo_ros.core.small3 import add as _add
from rsvo_ros.core.small3 import cross as _cross
from rsvo_ros.core.small3 import exp_jr as _exp_jr
from rsvo_ros.core.small3 import mm as _mm
from rsvo_ros.core.small3 import mtv as _mtv
from rsvo_ros.core.small3 import mv as _mv
from rsvo_ros.core.small3 import rot_update as _rot_update
from rsvo_ros.core.small3 import rows as _rows
from rsvo_ros.core.small3 import scale as _scale

FRAME_PARAMS = 15
MIN_DEPTH = 1e-6  # a point this close to (or behind) the camera plane gives no residual
RHO_MIN, RHO_MAX = 1e-4, 1e3  # inverse depths are kept inside these bounds
LAMBDA_MAX = 1e10
# the window LM's default stop: an accepted step that lowers the cost by no more than this
# fraction (MapOptions.ba_rel_tol sets the window BA's own)
WINDOW_LM_REL_TOL = 1e-8


# --------------------------------------------------------------------------- small algebra


@nb.njit(**JIT, inline="always")
def _skew_mul(a, M):
    """``[a]x M`` for a 3x3 ``M`` given as tuple of rows: columns ``a x M[:, j]``."""
    c0 = _cross(a, (M[0][0], M[1][0], M[2][0]))
    c1 = _cross(a, (M[0][1], M[1][1], M[2][1]))
    c2 = _cross(a, (M[0][2], M[1][2], M[2][2]))
    return ((c0[0], c1[0], c2[0]), (c0[1], c1[1], c2[1]), (c0[2], c1[2], c2[2]))


@nb.njit(**JIT, inline="always")
def _turn_rate(w, a, s):
    """``w + s/2 a``: the constant rate that turns the camera from the reference row to row
    time ``s``."""
    h = 0.5 * s
    return (w[0] + h * a[0], w[1] + h * a[1], w[2] + h * a[2])


@nb.njit(**JIT, inline="always")
def _row_pose(R, p, w, v, a, s):
    """(R(s), p(s)) as tuples."""
    Es, _ = _exp_jr(_scale(s, _turn_rate(w, a, s)))
    return _mm(R, Es), _add(p, _mv(R, _scale(s, v)))


# --------------------------------------------------------------------------- one observation


@nb.njit(**JIT, inline="always")
def _in_row_camera(R, p, w, v, a, s, X):
    """World point ``X`` in the camera of row time ``s``: ``q = R^T (X - p)``,
    ``Y = q - s v``, ``E = Exp(-s w_s)`` and its right Jacobian, ``Xc = E Y``."""
    d = (X[0] - p[0], X[1] - p[1], X[2] - p[2])
    q = _mtv(R, d)
    Y = (q[0] - s * v[0], q[1] - s * v[1], q[2] - s * v[2])
    E, Jr = _exp_jr(_scale(-s, _turn_rate(w, a, s)))
    return q, Y, E, Jr, _mv(E, Y)


@nb.njit(**JIT, inline="always")
def _residual(R, p, w, v, a, s, X, x_obs, focal):
    """:func:`_observe`'s residual alone (the same bits; no derivatives)."""
    Xc = _in_row_camera(R, p, w, v, a, s, X)[4]
    if Xc[2] < MIN_DEPTH:
        return 0.0, 0.0, False
    iz = 1.0 / Xc[2]
    ux, uy = Xc[0] * iz, Xc[1] * iz
    return focal * (ux - x_obs[0]), focal * (uy - x_obs[1]), True


@nb.njit(**JIT)
def _observe(R, p, w, v, a, s, X, x_obs, focal, Jf, JX):
    """Residual (2,) in px of world point ``X`` seen at normalized ``x_obs`` in the row ``s`` of
    a frame; fills ``Jf`` (2, 15) with its derivative by the frame's parameters and ``JX``
    (2, 3) by ``X``. Returns (ex, ey, ok): ok False behind the camera."""
    q, Y, E, Jr, Xc = _in_row_camera(R, p, w, v, a, s, X)
    if Xc[2] < MIN_DEPTH:
        return 0.0, 0.0, False
    iz = 1.0 / Xc[2]
    ux, uy = Xc[0] * iz, Xc[1] * iz
    ex, ey = focal * (ux - x_obs[0]), focal * (uy - x_obs[1])
    # A = focal dpi/dXc (2x3)
    A0 = (focal * iz, 0.0, -focal * ux * iz)
    A1 = (0.0, focal * iz, -focal * uy * iz)
    AE0 = _mtv(E, A0)  # row 0 of A E
    AE1 = _mtv(E, A1)
    # dXc/dtheta = E [q]x ; a row of it: a^T [q]x = (a x q)^T
    t0, t1 = _cross(AE0, q), _cross(AE1, q)
    # dXc/dp = -E R^T : row (A E) (-R^T) = -(R (A E)^T)^T
    P0, P1 = _mv(R, AE0), _mv(R, AE1)
    # dXc/dw = s E [Y]x J_r(phi) : a row of it s (AE_r x Y)^T J_r
    c0, c1 = _cross(AE0, Y), _cross(AE1, Y)
    W0, W1 = _scale(s, _mtv(Jr, c0)), _scale(s, _mtv(Jr, c1))
    for j in range(3):
        Jf[0, j], Jf[1, j] = t0[j], t1[j]
        Jf[0, 3 + j], Jf[1, 3 + j] = -P0[j], -P1[j]
        Jf[0, 6 + j], Jf[1, 6 + j] = W0[j], W1[j]
        Jf[0, 9 + j], Jf[1, 9 + j] = -s * AE0[j], -s * AE1[j]
        Jf[0, 12 + j], Jf[1, 12 + j] = 0.5 * s * W0[j], 0.5 * s * W1[j]
        JX[0, j], JX[1, j] = P0[j], P1[j]  # dXc/dX = E R^T
    return ex, ey, True


@nb.njit(**JIT, inline="always")
def _anchor_point(Ra, pa, wa, va, aa, sa, xa, rho):
    """World point ``X`` of an anchored inverse-depth landmark, with the anchor row's
    bearing ``b``, its rotation ``Exp(s_a w_s)`` and right Jacobian, and ``m = s_a v + E b``."""
    b = (xa[0] / rho, xa[1] / rho, 1.0 / rho)
    Ea, Jra = _exp_jr(_scale(sa, _turn_rate(wa, aa, sa)))
    Eb = _mv(Ea, b)
    m = _add(_scale(sa, va), Eb)
    return _add(pa, _mv(Ra, m)), b, Ea, Jra, m


@nb.njit(**JIT)
def _landmark(Ra, pa, wa, va, aa, sa, xa, rho, JA, Jrho):
    """World point of an anchored inverse-depth landmark and its derivatives: ``JA`` (3, 15)
    by the anchor frame's parameters, ``Jrho`` (3,) by ``rho``."""
    X, b, Ea, Jra, m = _anchor_point(Ra, pa, wa, va, aa, sa, xa, rho)
    # dX/dtheta_a = -R_a [m]x ; dX/dp_a = I ; dX/dw_a = -s_a R_a E_a [b]x J_r ; dX/dv_a = s_a R_a
    Rm = _skew_mul(m, ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)))  # [m]x
    RaM = _mm(Ra, Rm)
    RaE = _mm(Ra, Ea)
    bJ = _mm(_skew_mul(b, ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))), Jra)
    RaEbJ = _mm(RaE, bJ)
    for i in range(3):
        for j in range(3):
            JA[i, j] = -RaM[i][j]
            JA[i, 3 + j] = 1.0 if i == j else 0.0
            JA[i, 6 + j] = -sa * RaEbJ[i][j]
            JA[i, 9 + j] = sa * Ra[i][j]
            JA[i, 12 + j] = -0.5 * sa * sa * RaEbJ[i][j]
    ie = -1.0 / rho
    Xa = _mv(RaE, (xa[0], xa[1], 1.0))
    for i in range(3):
        Jrho[i] = Xa[i] * ie / rho  # d(b)/drho = -b / rho
    return X


# --------------------------------------------------------------------------- tracking


@nb.njit(**JIT)
def _track_cost(R, p, w, v, a, X, x_obs, s, focal, robust, prior_mu, prior_p2, acc_p2):
    Rr = _rows(R)
    pp, ww, vv = (p[0], p[1], p[2]), (w[0], w[1], w[2]), (v[0], v[1], v[2])
    aa = (a[0], a[1], a[2])
    Jf = np.empty((2, FRAME_PARAMS))
    JX = np.empty((2, 3))
    c = 0.0
    for i in range(X.shape[0]):
        ex, ey, ok = _observe(Rr, pp, ww, vv, aa, s[i], (X[i, 0], X[i, 1], X[i, 2]),
                              (x_obs[i, 0], x_obs[i, 1]), focal, Jf, JX)  # fmt: skip
        e2 = ex * ex + ey * ey if ok else 100.0 * robust * robust
        c += robust * robust * np.log1p(e2 / (robust * robust))
    for j in range(3):
        c += prior_p2[j] * (w[j] - prior_mu[j]) ** 2
        c += prior_p2[3 + j] * (v[j] - prior_mu[3 + j]) ** 2
        c += prior_p2[6 + j] * (p[j] - prior_mu[6 + j]) ** 2
        c += acc_p2 * a[j] ** 2
    return c


@nb.njit(**JIT)
def track_frame(R, p, w, v, a, X, x_obs, s, focal, robust, prior_mu, prior_p2, acc_p2,
                iterations):  # fmt: skip
    """Motion-only RS pose of one frame against fixed world points (Levenberg-Marquardt,
    Cauchy loss of scale ``robust`` px; a prior ``sum(prior_p2 (y - prior_mu)^2)`` on
    ``y = [w, v, p]`` (9,) and ``acc_p2 |a|^2`` on the angular acceleration; ``acc_p2 <= 0``
    holds ``a``).
    ``X`` (n, 3), ``x_obs`` (n, 2) normalized, ``s`` (n,) row times. Returns R, p, w, v, a,
    residuals (n, 2) px, cost and the Gauss-Newton Hessian (15, 15)."""
    if prior_mu.shape[0] != 9 or prior_p2.shape[0] != 9:
        raise ValueError("track_frame: prior_mu and prior_p2 must have 9 entries (w, v, p)")
    R, p, w, v, a = R.copy(), p.copy(), w.copy(), v.copy(), a.copy()
    n = X.shape[0]
    Jf = np.empty((2, FRAME_PARAMS))
    JX = np.empty((2, 3))
    H = np.zeros((FRAME_PARAMS, FRAME_PARAMS))
    g = np.zeros(FRAME_PARAMS)
    lam = 1e-3
    # a held acceleration's rows of the normal equations stay zero: not accumulated
    n_par = FRAME_PARAMS if acc_p2 > 0 else FRAME_PARAMS - 3
    cost = _track_cost(R, p, w, v, a, X, x_obs, s, focal, robust, prior_mu, prior_p2, acc_p2)
    for _ in range(iterations):
        H[:] = 0.0
        g[:] = 0.0
        Rr = _rows(R)
        pp, ww, vv = (p[0], p[1], p[2]), (w[0], w[1], w[2]), (v[0], v[1], v[2])
        aa = (a[0], a[1], a[2])
        for i in range(n):
            ex, ey, ok = _observe(Rr, pp, ww, vv, aa, s[i], (X[i, 0], X[i, 1], X[i, 2]),
                                  (x_obs[i, 0], x_obs[i, 1]), focal, Jf, JX)  # fmt: skip
            if not ok:
                continue
            wt = 1.0 / (1.0 + (ex * ex + ey * ey) / (robust * robust))
            for i1 in range(n_par):
                ja0, ja1 = wt * Jf[0, i1], wt * Jf[1, i1]
                g[i1] += ja0 * ex + ja1 * ey
                for i2 in range(i1, n_par):
                    H[i1, i2] += ja0 * Jf[0, i2] + ja1 * Jf[1, i2]
        for i1 in range(n_par):
            for i2 in range(i1):
                H[i1, i2] = H[i2, i1]
        for j in range(3):
            H[6 + j, 6 + j] += prior_p2[j]
            g[6 + j] += prior_p2[j] * (w[j] - prior_mu[j])
            H[9 + j, 9 + j] += prior_p2[3 + j]
            g[9 + j] += prior_p2[3 + j] * (v[j] - prior_mu[3 + j])
            H[3 + j, 3 + j] += prior_p2[6 + j]
            g[3 + j] += prior_p2[6 + j] * (p[j] - prior_mu[6 + j])
            if acc_p2 > 0:
                H[12 + j, 12 + j] += acc_p2
                g[12 + j] += acc_p2 * a[j]
            else:  # held: the acceleration leaves the system (its rows and columns are 0)
                H[12 + j, 12 + j] = 1.0
        improved = False
        while lam < LAMBDA_MAX:
            A = H.copy()
            for i1 in range(FRAME_PARAMS):
                A[i1, i1] += lam * max(H[i1, i1], 1e-9)
            delta = np.linalg.solve(A, -g)
            R_c = _rot_update(R, delta[0:3])
            p_c, w_c, v_c = p + delta[3:6], w + delta[6:9], v + delta[9:12]
            a_c = a + delta[12:15]
            c_new = _track_cost(R_c, p_c, w_c, v_c, a_c, X, x_obs, s, focal, robust, prior_mu,
                                prior_p2, acc_p2)  # fmt: skip
            if np.isfinite(c_new) and c_new < cost:
                rel = (cost - c_new) / max(cost, 1e-300)
                R, p, w, v, a, cost = R_c, p_c, w_c, v_c, a_c, c_new
                lam = max(lam / 3.0, 1e-9)
                improved = rel > 1e-9
                break
            lam *= 4.0
        if not improved:
            break
    res = np.empty((n, 2))
    Rr = _rows(R)
    pp, ww, vv = (p[0], p[1], p[2]), (w[0], w[1], w[2]), (v[0], v[1], v[2])
    aa = (a[0], a[1], a[2])
    for i in range(n):
        ex, ey, ok = _observe(Rr, pp, ww, vv, aa, s[i], (X[i, 0], X[i, 1], X[i, 2]),
                              (x_obs[i, 0], x_obs[i, 1]), focal, Jf, JX)  # fmt: skip
        res[i, 0] = ex if ok else np.inf
        res[i, 1] = ey if ok else np.inf
    return R, p, w, v, a, res, cost, H


# --------------------------------------------------------------------------- the window


@nb.njit(**JIT)
def _landmark_points_into(R, p, w, v, acc, lm_anchor, lm_x, lm_s, rho, X):
    """Every window landmark's world point into ``X`` (M, 3): once per landmark, for all of
    its observations."""
    for j in range(rho.shape[0]):
        a = lm_anchor[j]
        Xj = _anchor_point(_rows(R[a]), (p[a, 0], p[a, 1], p[a, 2]), (w[a, 0], w[a, 1], w[a, 2]),
                           (v[a, 0], v[a, 1], v[a, 2]), (acc[a, 0], acc[a, 1], acc[a, 2]),
                           lm_s[j], (lm_x[j, 0], lm_x[j, 1]), rho[j])[0]  # fmt: skip
        X[j, 0], X[j, 1], X[j, 2] = Xj


@nb.njit(**JIT)
def _landmark_derivatives_into(R, p, w, v, acc, lm_anchor, lm_x, lm_s, rho, X, JA, Jrho):
    """:func:`_landmark_points_into` with each point's derivatives by its anchor frame's
    parameters ``JA`` (M, 3, 15) and by its inverse depth ``Jrho`` (M, 3)."""
    for j in range(rho.shape[0]):
        a = lm_anchor[j]
        Xj = _landmark(_rows(R[a]), (p[a, 0], p[a, 1], p[a, 2]), (w[a, 0], w[a, 1], w[a, 2]),
                       (v[a, 0], v[a, 1], v[a, 2]), (acc[a, 0], acc[a, 1], acc[a, 2]), lm_s[j],
                       (lm_x[j, 0], lm_x[j, 1]), rho[j], JA[j], Jrho[j])  # fmt: skip
        X[j, 0], X[j, 1], X[j, 2] = Xj


@nb.njit(**JIT)
def _window_cost(R, p, w, v, acc, obs_kf, obs_lm, obs_x, obs_s, lm_anchor, lm_x, lm_s, rho,
                 focal, robust, mu, p2, acc_p2, res):  # fmt: skip
    """Robust cost of the window (and each observation's residual into ``res`` (n, 2))."""
    X = np.empty((rho.shape[0], 3))
    _landmark_points_into(R, p, w, v, acc, lm_anchor, lm_x, lm_s, rho, X)
    c = 0.0
    r2 = robust * robust
    for o in range(obs_kf.shape[0]):
        k, j = obs_kf[o], obs_lm[o]
        ex, ey, ok = _residual(_rows(R[k]), (p[k, 0], p[k, 1], p[k, 2]),
                               (w[k, 0], w[k, 1], w[k, 2]), (v[k, 0], v[k, 1], v[k, 2]),
                               (acc[k, 0], acc[k, 1], acc[k, 2]), obs_s[o],
                               (X[j, 0], X[j, 1], X[j, 2]), (obs_x[o, 0], obs_x[o, 1]),
                               focal)  # fmt: skip
        if not ok:
            ex = ey = 10.0 * robust
        res[o, 0], res[o, 1] = ex, ey
        c += r2 * np.log1p((ex * ex + ey * ey) / r2)
    for k in range(R.shape[0]):
        for j in range(3):
            c += p2[k, j] * (w[k, j] - mu[k, j]) ** 2
            c += p2[k, 3 + j] * (v[k, j] - mu[k, 3 + j]) ** 2
            c += acc_p2 * acc[k, j] ** 2
    return c


@nb.njit(**JIT, inline="always")
def _add_block(Hff, f1, f2, J1, J2, wt, n_par):
    """``Hff[f1, f2] += wt J1^T J2`` over the first ``n_par`` parameters (J1, J2: (2, 15))."""
    for i in range(n_par):
        x0, x1 = J1[0, i], J1[1, i]
        for i2 in range(n_par):
            Hff[f1, f2, i, i2] += wt * (x0 * J2[0, i2] + x1 * J2[1, i2])


@nb.njit(**JIT)
def _gather_blocks(blocks, col, n_par, out):
    """A symmetric matrix over the free columns from its frame-pair blocks ``blocks[f1, f2]``
    (f1 <= f2, the upper triangle: columns are frame-major), both triangles into ``out``."""
    K = blocks.shape[0]
    for f1 in range(K):
        for f2 in range(f1, K):
            for i1 in range(n_par):
                c1 = col[f1, i1]
                if c1 < 0:
                    continue
                for i2 in range(n_par):
                    c2 = col[f2, i2]
                    if c2 >= c1:  # (not the fixed ones, -1, nor a diagonal block's lower part)
                        out[c1, c2] = out[c2, c1] = blocks[f1, f2, i1, i2]


@nb.njit(**JIT)
def _window_system(R, p, w, v, acc, obs_kf, obs_lm, obs_x, obs_s, lm_anchor, lm_x, lm_s, rho,
                   focal, robust, mu, p2, acc_p2, col, n_par, Hcc, gc, Hcp, hpp, gp):  # fmt: skip
    """Normal equations of the window with IRLS weights of the Cauchy loss: the frames'
    block ``Hcc``/``gc`` (columns ``col[k, i]``, -1 for fixed parameters), the frame x
    landmark blocks ``Hcp`` (K, M, 15), the landmarks' ``hpp``/``gp`` (M,); over the first
    ``n_par`` frame parameters (12: every acceleration held)."""
    K, M = R.shape[0], rho.shape[0]
    X = np.empty((M, 3))
    JA = np.empty((M, 3, FRAME_PARAMS))
    Jrho = np.empty((M, 3))
    _landmark_derivatives_into(R, p, w, v, acc, lm_anchor, lm_x, lm_s, rho, X, JA, Jrho)
    Jf = np.empty((2, FRAME_PARAMS))
    JX = np.empty((2, 3))
    Ja = np.empty((2, FRAME_PARAMS))
    jr = np.empty(2)
    # Hcc by frame pairs (f1 <= f2): each observation adds dense blocks, gathered into
    # Hcc's free columns once at the end (the same sums in the same order, so the same bits)
    Hff = np.zeros((K, K, n_par, n_par))
    Hcc[:] = 0.0
    gc[:] = 0.0
    Hcp[:] = 0.0
    hpp[:] = 0.0
    gp[:] = 0.0
    r2 = robust * robust
    for o in range(obs_kf.shape[0]):
        k, j = obs_kf[o], obs_lm[o]
        a = lm_anchor[j]
        ex, ey, ok = _observe(_rows(R[k]), (p[k, 0], p[k, 1], p[k, 2]),
                              (w[k, 0], w[k, 1], w[k, 2]), (v[k, 0], v[k, 1], v[k, 2]),
                              (acc[k, 0], acc[k, 1], acc[k, 2]), obs_s[o],
                              (X[j, 0], X[j, 1], X[j, 2]), (obs_x[o, 0], obs_x[o, 1]), focal,
                              Jf, JX)  # fmt: skip
        if not ok:
            continue
        wt = 1.0 / (1.0 + (ex * ex + ey * ey) / r2)
        for r in range(2):
            for i in range(n_par):
                Ja[r, i] = (JX[r, 0] * JA[j, 0, i] + JX[r, 1] * JA[j, 1, i]
                            + JX[r, 2] * JA[j, 2, i])  # fmt: skip
            jr[r] = JX[r, 0] * Jrho[j, 0] + JX[r, 1] * Jrho[j, 1] + JX[r, 2] * Jrho[j, 2]
        e = (ex, ey)
        hpp[j] += wt * (jr[0] * jr[0] + jr[1] * jr[1])
        gp[j] += wt * (jr[0] * ex + jr[1] * ey)
        for side in range(2):
            f = k if side == 0 else a
            J1 = Jf if side == 0 else Ja
            for i in range(n_par):
                Hcp[f, j, i] += wt * (J1[0, i] * jr[0] + J1[1, i] * jr[1])
                ci = col[f, i]
                if ci >= 0:
                    gc[ci] += wt * (J1[0, i] * e[0] + J1[1, i] * e[1])
        # the frames' products into their blocks, the earlier frame's rows first (in
        # Hcc's upper triangle: columns are frame-major)
        if a == k:  # the anchor's own observation: in the order of the two sides' products
            _add_block(Hff, k, k, Jf, Jf, wt, n_par)
            _add_block(Hff, k, k, Jf, Ja, wt, n_par)
            _add_block(Hff, k, k, Ja, Jf, wt, n_par)
            _add_block(Hff, k, k, Ja, Ja, wt, n_par)
        else:
            _add_block(Hff, k, k, Jf, Jf, wt, n_par)
            _add_block(Hff, a, a, Ja, Ja, wt, n_par)
            if k < a:
                _add_block(Hff, k, a, Jf, Ja, wt, n_par)
            else:
                _add_block(Hff, a, k, Ja, Jf, wt, n_par)
    _gather_blocks(Hff, col, n_par, Hcc)
    for kk in range(K):  # velocity priors
        for i in range(6):
            ci = col[kk, 6 + i]
            if ci < 0:
                continue
            val = w[kk, i] if i < 3 else v[kk, i - 3]
            Hcc[ci, ci] += p2[kk, i]
            gc[ci] += p2[kk, i] * (val - mu[kk, i])
        for i in range(3):  # the angular accelerations' (zero-mean)
            ci = col[kk, 12 + i]
            if ci >= 0:
                Hcc[ci, ci] += acc_p2
                gc[ci] += acc_p2 * acc[kk, i]


@nb.njit(**JIT)
def window_lm(R, p, w, v, acc, obs_kf, obs_lm, obs_x, obs_s, lm_anchor, lm_x, lm_s, rho, focal,
              robust, mu, p2, acc_p2, col, n_cols, iterations,
              rel_tol=WINDOW_LM_REL_TOL):  # fmt: skip
    """Levenberg-Marquardt over the window: the free frame parameters (``col``) and every
    landmark's inverse depth, the landmarks eliminated by the Schur complement (their blocks
    are 1 x 1); it stops after ``iterations``, or once an accepted step lowers the cost by no
    more than the fraction ``rel_tol``. Returns the new R, p, w, v, acc, rho, the residuals
    (n_obs, 2), the final cost and the iterations run."""
    R, p, w, v, acc, rho = R.copy(), p.copy(), w.copy(), v.copy(), acc.copy(), rho.copy()
    K, M = R.shape[0], rho.shape[0]
    # every acceleration held (the default): the loops stop after the 12 other parameters
    n_par = FRAME_PARAMS if np.any(col[:, 12:] >= 0) else FRAME_PARAMS - 3
    Hcc = np.zeros((n_cols, n_cols))
    gc = np.zeros(n_cols)
    Hcp = np.zeros((K, M, FRAME_PARAMS))
    hpp = np.zeros(M)
    gp = np.zeros(M)
    res = np.zeros((obs_kf.shape[0], 2))
    cost = _window_cost(R, p, w, v, acc, obs_kf, obs_lm, obs_x, obs_s, lm_anchor, lm_x, lm_s, rho,
                        focal, robust, mu, p2, acc_p2, res)  # fmt: skip
    # which frames see each landmark (its anchor and its observers)
    seen = np.zeros((M, K), np.bool_)
    for o in range(obs_kf.shape[0]):
        seen[obs_lm[o], obs_kf[o]] = True
    for j in range(M):
        seen[j, lm_anchor[j]] = True
    # per landmark, its free frame parameters (column, frame, parameter) for the Schur sums
    n_free = np.zeros(M, np.int64)
    for j in range(M):
        for k1 in range(K):
            if seen[j, k1]:
                for i1 in range(n_par):
                    if col[k1, i1] >= 0:
                        n_free[j] += 1
    start = np.zeros(M + 1, np.int64)
    for j in range(M):
        start[j + 1] = start[j] + n_free[j]
    free_col = np.empty(start[M], np.int64)
    free_k = np.empty(start[M], np.int64)
    free_i = np.empty(start[M], np.int64)
    for j in range(M):
        m = start[j]
        for k1 in range(K):
            if seen[j, k1]:
                for i1 in range(n_par):
                    if col[k1, i1] >= 0:
                        free_col[m], free_k[m], free_i[m] = col[k1, i1], k1, i1
                        m += 1
    # per landmark, the frames with free parameters that see it (in order), for the Schur
    # sums by frame pairs (dense blocks, gathered into W's free columns once per iteration:
    # the same sums in the same order as over the free columns themselves)
    has_free = np.zeros(K, np.bool_)
    for k1 in range(K):
        for i1 in range(n_par):
            if col[k1, i1] >= 0:
                has_free[k1] = True
    fstart = np.zeros(M + 1, np.int64)
    for j in range(M):
        fstart[j + 1] = fstart[j]
        for k1 in range(K):
            if seen[j, k1] and has_free[k1]:
                fstart[j + 1] += 1
    frames = np.empty(fstart[M], np.int64)
    for j in range(M):
        m = fstart[j]
        for k1 in range(K):
            if seen[j, k1] and has_free[k1]:
                frames[m] = k1
                m += 1
    Wff = np.empty((K, K, n_par, n_par))
    h = np.empty(start[M])
    W = np.empty((n_cols, n_cols))  # sum_j Hcp_j Hcp_j^T / hpp_j (undamped)
    u = np.empty(n_cols)  # sum_j Hcp_j gp_j / hpp_j
    lam = 1e-4
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007
        _window_system(R, p, w, v, acc, obs_kf, obs_lm, obs_x, obs_s, lm_anchor, lm_x, lm_s,
                       rho, focal, robust, mu, p2, acc_p2, col, n_par, Hcc, gc, Hcp, hpp, gp)
        # the landmarks' part of the Schur complement, once per iteration: damping a
        # landmark's block by (1 + lambda) scales its terms by 1 / (1 + lambda)
        Wff[:] = 0.0
        u[:] = 0.0
        for j in range(M):
            inv0 = 1.0 / (hpp[j] + 1e-12)
            for m in range(start[j], start[j + 1]):
                h[m] = Hcp[free_k[m], j, free_i[m]]
                u[free_col[m]] += h[m] * inv0 * gp[j]
            for m in range(fstart[j], fstart[j + 1]):
                f1 = frames[m]
                for m2 in range(m, fstart[j + 1]):
                    f2 = frames[m2]
                    for i1 in range(n_par):
                        h1 = Hcp[f1, j, i1] * inv0
                        for i2 in range(n_par):
                            Wff[f1, f2, i1, i2] += h1 * Hcp[f2, j, i2]
        _gather_blocks(Wff, col, n_par, W)
        accepted = False
        while lam < LAMBDA_MAX:
            scale = 1.0 / (1.0 + lam)
            S = Hcc - scale * W
            b = -gc + scale * u
            for c in range(n_cols):
                S[c, c] += lam * max(Hcc[c, c], 1e-9)
            inv = np.empty(M)
            for j in range(M):
                inv[j] = 1.0 / (hpp[j] * (1.0 + lam) + 1e-12)
            dc = np.linalg.solve(S, b)
            R_c, p_c, w_c, v_c, acc_c = R.copy(), p.copy(), w.copy(), v.copy(), acc.copy()
            for k in range(K):
                d = np.zeros(FRAME_PARAMS)
                for i in range(FRAME_PARAMS):
                    if col[k, i] >= 0:
                        d[i] = dc[col[k, i]]
                R_c[k] = _rot_update(R[k], d[0:3])
                p_c[k] = p[k] + d[3:6]
                w_c[k] = w[k] + d[6:9]
                v_c[k] = v[k] + d[9:12]
                acc_c[k] = acc[k] + d[12:15]
            rho_c = rho.copy()
            for j in range(M):
                gj = gp[j]
                for m in range(start[j], start[j + 1]):
                    gj += h[m] * dc[free_col[m]]
                rho_c[j] = min(max(rho[j] - gj * inv[j], RHO_MIN), RHO_MAX)
            c_new = _window_cost(R_c, p_c, w_c, v_c, acc_c, obs_kf, obs_lm, obs_x, obs_s,
                                 lm_anchor, lm_x, lm_s, rho_c, focal, robust, mu, p2, acc_p2,
                                 res)  # fmt: skip
            if np.isfinite(c_new) and c_new < cost:
                rel = (cost - c_new) / max(cost, 1e-300)
                R, p, w, v, acc, rho, cost = R_c, p_c, w_c, v_c, acc_c, rho_c, c_new
                lam = max(lam / 3.0, 1e-9)
                accepted = rel > rel_tol
                break
            lam *= 4.0
        if not accepted:
            break
    _window_cost(R, p, w, v, acc, obs_kf, obs_lm, obs_x, obs_s, lm_anchor, lm_x, lm_s, rho,
                 focal, robust, mu, p2, acc_p2, res)
    return R, p, w, v, acc, rho, res, cost, it


@nb.njit(**JIT)
def landmark_points(R, p, w, v, acc, lm_anchor, lm_x, lm_s, rho):
    """World points (M, 3) of the window's landmarks."""
    out = np.empty((rho.shape[0], 3))
    _landmark_points_into(R, p, w, v, acc, lm_anchor, lm_x, lm_s, rho, out)
    return out


@nb.njit(**JIT)
def row_camera(R, p, w, v, a, s):
    """(R(s) (3, 3), p(s) (3,)) of a frame's camera at row time ``s``."""
    Rs, ps = _row_pose(_rows(R), (p[0], p[1], p[2]), (w[0], w[1], w[2]), (v[0], v[1], v[2]),
                       (a[0], a[1], a[2]), s)
    out = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            out[i, j] = Rs[i][j]
    return out, np.array([ps[0], ps[1], ps[2]])
