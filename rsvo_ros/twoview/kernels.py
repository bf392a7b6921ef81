"""Compiled (numba) kernels of the RS solver: Levenberg-Marquardt on the Sampson error.

The vectorized numpy model in :mod:`rsvo_ros.twoview.reference` is the readable specification
(and the one the tests check against finite differences); this module evaluates the same
residual and analytic Jacobian one correspondence at a time, accumulating the 17x17 normal
equations as it goes, so that an LM iteration on 500 points costs well under a millisecond and
never builds a (B, N, 17) array. Small vectors are tuples and 3x3 matrices tuples of rows, so the
inner loop allocates nothing.

Convention (as :mod:`rsvo_ros.twoview.reference`): ``X_curr = R X_prev + t`` between the cameras
at the solver's reference row, per correspondence ``E_i = Rc^T [t + R s_p v_p - s_c v_c]x R Rp``
with ``Rp = Exp(s_p w_p)``, ``Rc = Exp(s_c w_c)``; the increment is
``[dtheta(3), dt(2), dvel(12)]`` with ``R <- R Exp(dtheta)``, ``t <- normalize(t + B dt)``.
"""

from __future__ import annotations

import os

# OpenMP threads that spin after lm_batch's parallel loop would take the other core from
# OpenCV (tracking, the GS starts); let them sleep. Read when libgomp starts.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numba as nb  # noqa: E402
import numpy as np

from rsvo_ros.core.small3 import JIT
from rsvo_ros.core.small3 import add as _add
from rsvo_ros.core.small3 import cross as _cross
from rsvo_ros.core.small3 import dot as _dot
from rsvo_ros.core.small3 import exp_jr as _exp_jr
from rsvo_ros.core.small3 import mm as _mm
from rsvo_ros.core.small3 import mtv as _mtv
from rsvo_ros.core.small3 import mv as _mv
from rsvo_ros.core.small3 import rot_update as _rot_update
from rsvo_ros.core.small3 import rows as _rows
from rsvo_ros.core.small3 import scale as _scale

NUM_PARAMS = 17
LAMBDA_MAX = 1e8  # damping at which a hypothesis gives up
# lm_batch spreads hypotheses over the cores; the default workqueue layer must not be entered
# from two threads at once (the node's worker and a test's), OpenMP or TBB may
nb.config.THREADING_LAYER = "threadsafe"


@nb.njit(**JIT)
def _velocities(vel):
    return ((vel[0], vel[1], vel[2]), (vel[3], vel[4], vel[5]), (vel[6], vel[7], vel[8]),
            (vel[9], vel[10], vel[11]))  # fmt: skip


@nb.njit(**JIT)
def _tangent(t):
    """Orthonormal tangent basis ``(b1, b2)`` of the unit sphere at ``t`` (as
    :func:`rsvo_ros.twoview.state.tangent_basis`)."""
    a0, a1, a2 = abs(t[0]), abs(t[1]), abs(t[2])
    if a0 <= a1 and a0 <= a2:  # the axis least aligned with t (np.argmin's first minimum)
        helper = (1.0, 0.0, 0.0)
    elif a1 <= a2:
        helper = (0.0, 1.0, 0.0)
    else:
        helper = (0.0, 0.0, 1.0)
    b1 = _cross(t, helper)
    b1 = _scale(1.0 / np.sqrt(_dot(b1, b1)), b1)
    return b1, _cross(t, b1)


# --------------------------------------------------------------------------- one correspondence


@nb.njit(**JIT, inline="always")
def _rays(R, t, V, xp, xc, sp, sc):
    """The two rays of one correspondence in the current reference camera and the baseline
    between them: ``a = R Rp x_p``, ``b = Rc x_c``, ``T = t + R s_p v_p - s_c v_c`` (with
    ``Rp = Exp(s_p w_p)``, ``Rc = Exp(s_c w_c)``, their right Jacobians, ``q = Rp x_p`` and
    ``tp = s_p v_p``), so that ``lam_c b = lam_p a + T``."""
    wp, vp, wc, vc = V
    Rp, Jrp = _exp_jr(_scale(sp, wp))
    Rc, Jrc = _exp_jr(_scale(sc, wc))
    q = _mv(Rp, xp)
    a = _mv(R, q)
    b = _mv(Rc, xc)
    tp = _scale(sp, vp)
    T = _add(_add(t, _mv(R, tp)), _scale(-sc, vc))
    return Rp, Jrp, Rc, Jrc, q, a, b, tp, T


@nb.njit(**JIT, inline="always")
def _epipolar(R, t, V, xp, xc, sp, sc, cam):
    """Sampson error (px) of one correspondence and the intermediate terms its Jacobian needs.

    The same algebra as :func:`rsvo_ros.twoview.reference.sampson_residuals`, one point at a time.
    ``R`` rows, ``t``, ``V = (w_p, v_p, w_c, v_c)`` and ``cam = (focal, ds_dy)`` are tuples.
    """
    focal, kappa = cam
    wp, vp, wc, vc = V
    Rp, Jrp, Rc, Jrc, q, a, b, tp, T = _rays(R, t, V, xp, xc, sp, sc)
    g = _cross(T, a)
    h = _cross(b, T)
    n = _dot(b, g)
    Ex = _mtv(Rc, g)
    Rth = _mtv(R, h)
    ETx = _mtv(Rp, Rth)
    # E_i moves with the rows: dn/ds_c, dn/ds_p
    m_p = _cross(wp, xp)
    m_c = _cross(wc, xc)
    mp2 = _mv(Rp, m_p)
    da = _mv(R, mp2)
    db = _mv(Rc, m_c)
    Rv = _mv(R, vp)
    ab = _cross(a, b)
    dn_c = _dot(db, g) - _dot(vc, ab)  # b.(a x v_c) = -v_c.(a x b)
    dn_p = _dot(da, h) + _dot(Rv, ab)
    u = (Ex[0], Ex[1] + kappa * dn_c, 0.0)
    z = (ETx[0], ETx[1] + kappa * dn_p, 0.0)
    d2 = u[0] * u[0] + u[1] * u[1] + z[0] * z[0] + z[1] * z[1]
    inv_d = 1.0 / np.sqrt(max(d2, 1e-300))
    e = focal * n * inv_d
    return (e, Rp, Jrp, Rc, Jrc, q, a, b, tp, T, g, h, n, Ex, Rth, ETx, m_p, m_c, mp2, da, db,
            Rv, ab, u, z, inv_d)  # fmt: skip


@nb.njit(**JIT, inline="always")
def _residual(R, t, V, xp, xc, sp, sc, cam):
    """Sampson error (px) of one correspondence."""
    return _epipolar(R, t, V, xp, xc, sp, sc, cam)[0]


@nb.njit(**JIT)
def _point(R, t, Bt, V, xp, xc, sp, sc, cam, J):
    """Sampson error (px) of one correspondence; fills its Jacobian ``J`` (17,).
    ``Bt``: the tangent basis of ``t``."""
    (e, Rp, Jrp, Rc, Jrc, q, a, b, tp, T, g, h, n, Ex, Rth, ETx, m_p, m_c, mp2, da, db, Rv, ab,
     u, z, inv_d) = _epipolar(R, t, V, xp, xc, sp, sc, cam)  # fmt: skip
    focal, kappa = cam
    wp, vp, wc, vc = V
    U = _mv(Rc, u)
    A = _mm(R, Rp)
    Z = _mv(A, z)
    k = focal * n * inv_d**3
    f = focal * inv_d
    alpha = -k * kappa * u[1]
    beta = -k * kappa * z[1]
    c_a = _add(_add(_scale(f, h), _scale(-k, _cross(U, T))),
               _add(_scale(alpha, _add(_cross(db, T), _cross(vc, b))),
                    _scale(beta, _cross(b, Rv))))  # fmt: skip
    c_b = _add(_add(_scale(f, g), _scale(-k, _cross(T, Z))),
               _add(_scale(alpha, _cross(a, vc)),
                    _scale(beta, _add(_cross(T, da), _cross(Rv, a)))))  # fmt: skip
    c_T = _add(_add(_scale(f, ab), _scale(-k, _add(_cross(a, U), _cross(Z, b)))),
               _add(_scale(alpha, _cross(a, db)), _scale(beta, _cross(da, b))))  # fmt: skip
    c_Ex = _scale(-k, u)
    c_ETx = _scale(-k, z)
    c_db = _scale(alpha, g)
    c_da = _scale(beta, h)
    c_Rv = _scale(beta, ab)
    c_vc = _scale(-alpha, ab)  # alpha (b x a)
    RtcT = _mtv(R, c_T)
    Rtc_da = _mtv(R, c_da)
    Rtc_Rv = _mtv(R, c_Rv)
    j = _add(_add(_cross(q, _mtv(R, c_a)), _cross(tp, RtcT)), _cross(_mv(Rp, c_ETx), Rth))
    j = _add(j, _add(_cross(mp2, Rtc_da), _cross(vp, Rtc_Rv)))
    J[0], J[1], J[2] = j
    J[3] = _dot(c_T, Bt[0])
    J[4] = _dot(c_T, Bt[1])
    y_p = _mtv(A, c_a)
    y_da = _mtv(A, c_da)
    j = _scale(sp, _mtv(Jrp, _add(_add(_cross(xp, y_p), _cross(c_ETx, ETx)), _cross(m_p, y_da))))
    J[5], J[6], J[7] = _add(j, _cross(xp, y_da))
    J[8], J[9], J[10] = _add(_scale(sp, RtcT), Rtc_Rv)
    y_c = _mtv(Rc, c_b)
    y_db = _mtv(Rc, c_db)
    j = _scale(sc, _mtv(Jrc, _add(_add(_cross(xc, y_c), _cross(c_Ex, Ex)), _cross(m_c, y_db))))
    J[11], J[12], J[13] = _add(j, _cross(xc, y_db))
    J[14], J[15], J[16] = _add(_scale(-sc, c_T), c_vc)
    return e


@nb.njit(**JIT, inline="always")
def _epipolar_gs(R, t, xp, xc, focal):
    """:func:`_epipolar` of a state without velocities (the GS model at the reference row):
    the same operations on the terms that are not zero there (``Exp(0) = I``, no row motion),
    so the same bits."""
    a = _mv(R, xp)
    g = _cross(t, a)
    h = _cross(xc, t)
    n = _dot(xc, g)
    Rth = _mtv(R, h)
    u = (g[0], g[1], 0.0)
    z = (Rth[0], Rth[1], 0.0)
    d2 = u[0] * u[0] + u[1] * u[1] + z[0] * z[0] + z[1] * z[1]
    inv_d = 1.0 / np.sqrt(max(d2, 1e-300))
    return focal * n * inv_d, a, h, n, Rth, u, z, inv_d


@nb.njit(**JIT)
def _point_gs(R, t, Bt, xp, xc, cam, J):
    """:func:`_point` of a state without velocities, its Jacobian in the rotation and
    translation only (``J[:5]``): the same bits as ``_point`` on zero velocities, in about a
    third of the time (the model selection's null refits)."""
    focal = cam[0]  # the rows' term (cam[1]) multiplies the row motion: zero here
    e, a, h, n, Rth, u, z, inv_d = _epipolar_gs(R, t, xp, xc, focal)
    Z = _mv(R, z)
    k = focal * n * inv_d**3
    f = focal * inv_d
    c_a = _add(_scale(f, h), _scale(-k, _cross(u, t)))
    c_T = _add(_scale(f, _cross(a, xc)), _scale(-k, _add(_cross(a, u), _cross(Z, xc))))
    c_ETx = _scale(-k, z)
    J[0], J[1], J[2] = _add(_cross(xp, _mtv(R, c_a)), _cross(c_ETx, Rth))
    J[3] = _dot(c_T, Bt[0])
    J[4] = _dot(c_T, Bt[1])
    return e


@nb.njit(**JIT)
def residuals_and_jacobian(R, t, vel, x_prev, x_curr, s_prev, s_curr, cam):
    """(N,) Sampson errors and (N, 17) Jacobian of one hypothesis (for tests and callers that
    need them as arrays)."""
    Rr = _rows(R)
    tt = (t[0], t[1], t[2])
    Bt = _tangent(tt)
    V = _velocities(vel)
    N = x_prev.shape[0]
    e = np.empty(N)
    J = np.empty((N, NUM_PARAMS))
    for i in range(N):
        xp = (x_prev[i, 0], x_prev[i, 1], x_prev[i, 2])
        xc = (x_curr[i, 0], x_curr[i, 1], x_curr[i, 2])
        e[i] = _point(Rr, tt, Bt, V, xp, xc, s_prev[i], s_curr[i], cam, J[i])
    return e, J


# --------------------------------------------------------------------------- LM of one hypothesis


@nb.njit(**JIT)
def _loss(e, robust):
    if robust > 0.0:
        return robust * robust * np.log1p((e / robust) ** 2)
    return e * e


@nb.njit(**JIT)
def _normal_equations(R, t, vel, x_prev, x_curr, s_prev, s_curr, cam, idx, robust, p2, mu, H,
                      g, gs):  # fmt: skip
    """Fills ``H = J^T W J + P``, ``g = J^T W e + P (vel - mu)`` (IRLS weights ``W`` of the
    Cauchy loss, prior ``P = diag(p2)`` on the velocities, centred on ``mu``); returns the
    cost. ``gs``: zero velocities that stay zero (steps in the rotation and translation only):
    :func:`_point_gs`, and only the rotation-translation block of ``H`` and ``g`` is filled
    (the rest stays zero)."""
    Rr = _rows(R)
    tt = (t[0], t[1], t[2])
    Bt = _tangent(tt)
    V = _velocities(vel)
    J = np.zeros(NUM_PARAMS)
    H[:] = 0.0
    g[:] = 0.0
    c = 0.0
    k = 5 if gs else NUM_PARAMS
    for m in range(idx.shape[0]):
        i = idx[m]
        xp = (x_prev[i, 0], x_prev[i, 1], x_prev[i, 2])
        xc = (x_curr[i, 0], x_curr[i, 1], x_curr[i, 2])
        if gs:
            e = _point_gs(Rr, tt, Bt, xp, xc, cam, J)
        else:
            e = _point(Rr, tt, Bt, V, xp, xc, s_prev[i], s_curr[i], cam, J)
        c += _loss(e, robust)
        w = 1.0 if robust <= 0.0 else 1.0 / (1.0 + (e / robust) ** 2)
        for r in range(k):
            wj = w * J[r]
            g[r] += wj * e
            for s in range(r, k):
                H[r, s] += wj * J[s]
    for r in range(k):
        for s in range(r):
            H[r, s] = H[s, r]
    for j in range(12):
        c += p2[j] * (vel[j] - mu[j]) ** 2
        H[5 + j, 5 + j] += p2[j]
        g[5 + j] += p2[j] * (vel[j] - mu[j])
    return c


@nb.njit(**JIT)
def _cholesky_solve(A, b):
    """Solve ``A x = b`` for symmetric positive-definite ``A``; ``ok`` False otherwise."""
    n = A.shape[0]
    L = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1):
            s = A[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            if i == j:
                if not s > 0.0:
                    return b * 0.0, False
                L[i, i] = np.sqrt(s)
            else:
                L[i, j] = s / L[j, j]
    y = np.empty(n)
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= L[i, k] * y[k]
        y[i] = s / L[i, i]
    x = np.empty(n)
    for i in range(n - 1, -1, -1):
        s = y[i]
        for k in range(i + 1, n):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]
    return x, True


@nb.njit(**JIT)
def _retract(R, t, vel, delta):
    """:meth:`rsvo_ros.twoview.state.RSBatch.retract` of one state; new arrays."""
    R_new = _rot_update(R, delta)
    tt = (t[0], t[1], t[2])
    b1, b2 = _tangent(tt)
    tn = _add(tt, _add(_scale(delta[3], b1), _scale(delta[4], b2)))
    tn = _scale(1.0 / np.sqrt(_dot(tn, tn)), tn)
    t_new = np.array([tn[0], tn[1], tn[2]])
    vel_new = vel + delta[5:17]
    return R_new, t_new, vel_new


@nb.njit(**JIT)
def _rotation_angle(R):
    c = (R[0, 0] + R[1, 1] + R[2, 2] - 1.0) / 2.0
    return np.arccos(min(1.0, max(-1.0, c)))


@nb.njit(**JIT)
def _within_limits(R, vel, delta, limits, anchor):
    """``limits`` = (max step rotation, max step translation, w_max, v_max, max rotation from
    ``anchor``)."""
    if np.sqrt(delta[0] ** 2 + delta[1] ** 2 + delta[2] ** 2) > limits[0]:
        return False
    if np.sqrt(delta[3] ** 2 + delta[4] ** 2) > limits[1]:
        return False
    for blk in range(4):
        o = 3 * blk
        nrm = np.sqrt(vel[o] ** 2 + vel[o + 1] ** 2 + vel[o + 2] ** 2)
        if nrm > (limits[2] if blk % 2 == 0 else limits[3]):
            return False
    if np.isfinite(limits[4]):
        if _rotation_angle(anchor.T @ R) > limits[4]:
            return False
    return True


@nb.njit(**JIT)
def _is_gs(basis, vel):
    """Whether steps in ``basis`` leave ``vel`` at zero: zero velocities and a basis of the
    first five axes (rotation, translation), as the GS model's refits use."""
    if basis.shape[1] != 5:
        return False
    for r in range(NUM_PARAMS):
        for c in range(5):
            if basis[r, c] != (1.0 if r == c else 0.0):
                return False
    for j in range(vel.shape[0]):
        if vel[j] != 0.0:
            return False
    return True


@nb.njit(**JIT)
def _lm_one(R, t, vel, x_prev, x_curr, s_prev, s_curr, cam, idx, iterations, lam, rel_tol,
            robust, p2, mu, basis, limits, anchor):
    """Marquardt's damped Gauss-Newton ``(H + lambda diag(H)) d = -g`` in the span of
    ``basis`` (17, k); a step that raises the cost or leaves ``limits`` is rejected. Returns
    the state, its cost and the iterations run.

    A step within the limits is evaluated with its normal equations (one pass over the points
    for the cost, the Jacobian and ``H``), which an accepted step then keeps: most steps are
    accepted, and a cost pass followed by a normal-equation pass read every point twice."""
    k = basis.shape[1]
    full = k == NUM_PARAMS  # the identity basis: no projection
    gs = _is_gs(basis, vel)
    H = np.empty((NUM_PARAMS, NUM_PARAMS))
    g = np.empty(NUM_PARAMS)
    H_c = np.empty((NUM_PARAMS, NUM_PARAMS))  # the candidate's
    g_c = np.empty(NUM_PARAMS)
    cost = _normal_equations(R, t, vel, x_prev, x_curr, s_prev, s_curr, cam, idx, robust,
                             p2, mu, H, g, gs)
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007
        if full:
            Hb, gb = H, g
        else:
            Hb = basis.T @ H @ basis
            gb = basis.T @ g
        dmax = 0.0
        for i in range(k):
            dmax = max(dmax, Hb[i, i])
        A = Hb.copy()
        for i in range(k):
            A[i, i] += lam * max(Hb[i, i], 1e-12 * max(dmax, 1e-300))
        step, ok = _cholesky_solve(A, -gb)
        accepted = False
        if ok:
            delta = step.copy() if full else basis @ step
            for i in range(NUM_PARAMS):
                if not np.isfinite(delta[i]):
                    delta[i] = 0.0
            R_c, t_c, vel_c = _retract(R, t, vel, delta)
            if _within_limits(R_c, vel_c, delta, limits, anchor):
                cost_c = _normal_equations(R_c, t_c, vel_c, x_prev, x_curr, s_prev, s_curr,
                                           cam, idx, robust, p2, mu, H_c, g_c, gs)
                accepted = np.isfinite(cost_c) and cost_c < cost
        if not accepted:
            lam *= 4.0
            if lam > LAMBDA_MAX:
                break
            continue
        rel = (cost - cost_c) / max(cost, 1e-300)
        R, t, vel, cost = R_c, t_c, vel_c, cost_c
        H, H_c = H_c, H
        g, g_c = g_c, g
        lam = max(lam / 3.0, 1e-12)
        if rel < rel_tol:
            break
    return R, t, vel, cost, it


@nb.njit(**JIT)
def _lm_into(b, R, t, vel, x_prev, x_curr, s_prev, s_curr, cam, idx, iterations, lambda_init,
             rel_tol, robust, p2, mu, basis, limits, anchor, R_out, t_out, vel_out, cost,
             iters):  # fmt: skip
    """:func:`_lm_one` of hypothesis ``b``, into row ``b`` of the outputs."""
    Rb, tb, vb, cb, ib = _lm_one(R[b].copy(), t[b].copy(), vel[b].copy(), x_prev, x_curr,
                                 s_prev, s_curr, cam, idx[b], iterations, lambda_init, rel_tol,
                                 robust, p2, mu[b], basis, limits, anchor[b])
    R_out[b], t_out[b], vel_out[b], cost[b], iters[b] = Rb, tb, vb, cb, ib


@nb.njit(**JIT, parallel=True)
def lm_batch(R, t, vel, x_prev, x_curr, s_prev, s_curr, cam, idx, iterations, lambda_init,
             rel_tol, robust, p2, mu, basis, limits, anchor):
    """LM for each of B hypotheses on its own correspondences ``idx[b]``.

    ``R`` (B, 3, 3), ``t`` (B, 3), ``vel`` (B, 12); ``idx`` (B, n) int64; ``robust`` the
    Cauchy scale in px (0: squares); ``p2`` (12,) squared inverse prior std; ``mu`` (B, 12)
    the prior's centres; ``basis`` (17, k);
    ``limits`` (5,) as :func:`_within_limits`; ``anchor`` (B, 3, 3). Returns new states, costs
    (B,) and iterations (B,).
    """
    B = R.shape[0]
    R_out, t_out, vel_out = np.empty_like(R), np.empty_like(t), np.empty_like(vel)
    cost, iters = np.empty(B), np.empty(B, np.int64)
    for b in nb.prange(B):  # hypotheses are independent: over the cores, same result
        # prange's index is unsigned: as int64 the serial loop's compiled _lm_into serves
        # (a second, uint64 specialisation took 4 s more of a cold first start)
        _lm_into(np.int64(b), R, t, vel, x_prev, x_curr, s_prev, s_curr, cam, idx, iterations,
                 lambda_init, rel_tol, robust, p2, mu, basis, limits, anchor, R_out, t_out,
                 vel_out, cost, iters)  # fmt: skip
    return R_out, t_out, vel_out, cost, iters


@nb.njit(**JIT)
def lm_serial(R, t, vel, x_prev, x_curr, s_prev, s_curr, cam, idx, iterations, lambda_init,
              rel_tol, robust, p2, mu, basis, limits, anchor):
    """:func:`lm_batch` on the calling thread (the same results)."""
    B = R.shape[0]
    R_out, t_out, vel_out = np.empty_like(R), np.empty_like(t), np.empty_like(vel)
    cost, iters = np.empty(B), np.empty(B, np.int64)
    for b in range(B):
        _lm_into(b, R, t, vel, x_prev, x_curr, s_prev, s_curr, cam, idx, iterations,
                 lambda_init, rel_tol, robust, p2, mu, basis, limits, anchor, R_out, t_out,
                 vel_out, cost, iters)  # fmt: skip
    return R_out, t_out, vel_out, cost, iters


@nb.njit(**JIT)
def _residuals_one(R, t, vel, x_prev, x_curr, s_prev, s_curr, cam, out):
    """Sampson errors (px) of one hypothesis on all correspondences, into ``out`` (N,)."""
    Rr = _rows(R)
    tt = (t[0], t[1], t[2])
    V = _velocities(vel)
    gs = not vel.any()  # the GS model: the same bits by its shorter path
    for i in range(x_prev.shape[0]):
        xp = (x_prev[i, 0], x_prev[i, 1], x_prev[i, 2])
        xc = (x_curr[i, 0], x_curr[i, 1], x_curr[i, 2])
        if gs:
            out[i] = _epipolar_gs(Rr, tt, xp, xc, cam[0])[0]
        else:
            out[i] = _residual(Rr, tt, V, xp, xc, s_prev[i], s_curr[i], cam)


@nb.njit(**JIT, parallel=True)
def residuals_batch(R, t, vel, x_prev, x_curr, s_prev, s_curr, cam):
    """(B, N) Sampson errors (px) of B hypotheses on all N correspondences (hypotheses over
    the cores, as :func:`lm_batch`)."""
    e = np.empty((R.shape[0], x_prev.shape[0]))
    for b in nb.prange(R.shape[0]):
        _residuals_one(R[b], t[b], vel[b], x_prev, x_curr, s_prev, s_curr, cam, e[b])
    return e


@nb.njit(**JIT)
def residuals_serial(R, t, vel, x_prev, x_curr, s_prev, s_curr, cam):
    """:func:`residuals_batch` on the calling thread."""
    e = np.empty((R.shape[0], x_prev.shape[0]))
    for b in range(R.shape[0]):
        _residuals_one(R[b], t[b], vel[b], x_prev, x_curr, s_prev, s_curr, cam, e[b])
    return e


@nb.njit(**JIT)
def depths_batch(R, t, vel, x_prev, x_curr, s_prev, s_curr):
    """(B, N) depths of every correspondence in both frames, as
    :func:`rsvo_ros.twoview.reference.rs_depths` (nan where the rays are parallel)."""
    B = R.shape[0]
    N = x_prev.shape[0]
    lam_p = np.empty((B, N))
    lam_c = np.empty((B, N))
    for b in range(B):
        Rr = _rows(R[b])
        tt = (t[b, 0], t[b, 1], t[b, 2])
        V = _velocities(vel[b])
        gs = not vel[b].any()  # no row motion: the same bits without the rows' rotations
        for i in range(N):
            xp = (x_prev[i, 0], x_prev[i, 1], x_prev[i, 2])
            xc = (x_curr[i, 0], x_curr[i, 1], x_curr[i, 2])
            if gs:
                a, bb, T = _mv(Rr, xp), xc, tt
            else:
                _, _, _, _, _, a, bb, _, T = _rays(Rr, tt, V, xp, xc, s_prev[i], s_curr[i])
            aa, b2, ab = _dot(a, a), _dot(bb, bb), _dot(a, bb)
            aT, bT = _dot(a, T), _dot(bb, T)
            det = aa * b2 - ab * ab
            if abs(det) < 1e-15:
                lam_p[b, i] = np.nan
                lam_c[b, i] = np.nan
            else:
                lam_p[b, i] = (ab * bT - b2 * aT) / det
                lam_c[b, i] = (aa * bT - ab * aT) / det
    return lam_p, lam_c


# --------------------------------------------------------------------------- rotation-only fit


@nb.njit(**JIT)
def _kabsch_masked(b_prev, b_curr, keep):
    """The rotation best mapping unit bearings ``b_curr ~ R b_prev`` of the rows ``keep``
    (bool (n,)): Kabsch, the SVD of their correlation with the sign of the determinant
    fixed."""
    H = np.zeros((3, 3))
    for i in range(b_prev.shape[0]):
        if keep[i]:
            for r in range(3):
                for c in range(3):
                    H[r, c] += b_curr[i, r] * b_prev[i, c]
    U, _, Vt = np.linalg.svd(H)
    UV = U @ Vt
    if np.linalg.det(UV) < 0.0:
        for r in range(3):
            U[r, 2] = -U[r, 2]
        UV = U @ Vt
    return UV


@nb.njit(**JIT)
def _rotation_residuals_px(R, b_prev, x_curr, focal, out):
    """Image distances (px) between ``R b_prev`` and ``x_curr`` (normalized), into ``out``."""
    for i in range(b_prev.shape[0]):
        p0 = R[0, 0] * b_prev[i, 0] + R[0, 1] * b_prev[i, 1] + R[0, 2] * b_prev[i, 2]
        p1 = R[1, 0] * b_prev[i, 0] + R[1, 1] * b_prev[i, 1] + R[1, 2] * b_prev[i, 2]
        z = R[2, 0] * b_prev[i, 0] + R[2, 1] * b_prev[i, 1] + R[2, 2] * b_prev[i, 2]
        if not abs(z) > 1e-12:
            z = 1e-12
        out[i] = focal * np.sqrt((p0 / z - x_curr[i, 0]) ** 2 + (p1 / z - x_curr[i, 1]) ** 2)


@nb.njit(**JIT)
def rotation_only_fit(b_prev, b_curr, x_curr, focal, draws, voters):
    """2-point RANSAC of a rotation-only motion and two refits on the better half of the
    points (:func:`rsvo_ros.twoview.essential.rotation_only_residual_px`): each row of
    ``draws`` (hypotheses, n) picks its two smallest entries' points; the hypotheses are ranked
    by the median residual (px) on the rows ``voters``. Returns the median residual of the
    final rotation on all points and the rotation."""
    n = b_prev.shape[0]
    keep = np.zeros(n, np.bool_)
    r_all = np.empty(n)
    r_vote = np.empty(voters.shape[0])
    sub = np.empty((voters.shape[0], 3))
    xsub = np.empty((voters.shape[0], 3))
    for m in range(voters.shape[0]):
        sub[m] = b_prev[voters[m]]
        xsub[m] = x_curr[voters[m]]
    best_R = np.eye(3)
    best = np.inf
    for h in range(draws.shape[0]):
        i0, i1 = -1, -1
        for i in range(n):  # the two smallest draws
            if i0 < 0 or draws[h, i] < draws[h, i0]:
                i1, i0 = i0, i
            elif i1 < 0 or draws[h, i] < draws[h, i1]:
                i1 = i
        keep[:] = False
        keep[i0] = True
        keep[i1] = True
        R = _kabsch_masked(b_prev, b_curr, keep)
        _rotation_residuals_px(R, sub, xsub, focal, r_vote)
        med = np.median(r_vote)
        if med < best:
            best, best_R = med, R
    R = best_R
    for _ in range(2):
        _rotation_residuals_px(R, b_prev, x_curr, focal, r_all)
        med = np.median(r_all)
        for i in range(n):
            keep[i] = r_all[i] <= med
        R = _kabsch_masked(b_prev, b_curr, keep)
    _rotation_residuals_px(R, b_prev, x_curr, focal, r_all)
    return np.median(r_all), R
