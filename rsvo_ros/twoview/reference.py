"""The rolling-shutter essential matrix of Lee & Yoon (Sec. 5) and its Sampson error (Sec. 6).

Pure numpy, vectorized over a batch of hypotheses (leading axis ``B``) so that many LM runs
advance together. Convention: ``X_curr = R X_prev + t`` between the two frames' cameras at a
reference row, ``x_curr^T E_i x_prev = 0`` per correspondence ``i``. Inside the solver, row
times are measured from a reference row ``row_ref`` (the principal point's row, near the image
centre): ``s = (r - row_ref) * tau``; :func:`rsvo_ros.core.geometry.pose_from_row` converts results
back to the row-0 convention of CONTRACTS.md.

Per correspondence, with ``Rp = Exp(s_p w_p)``, ``Rc = Exp(s_c w_c)`` (exact exponential, not
the paper's first-order ``I + s[w]x``):

    E_i = Rc^T [t + R (s_p v_p) - s_c v_c]x R Rp          (paper Sec. 5, transposed convention)

The Sampson error is that of the paper's Sec. 6, ``e_i = x_c^T E_i x_p / sqrt((E_i x_p)_1^2 +
(E_i x_p)_2^2 + (E_i^T x_c)_1^2 + (E_i^T x_c)_2^2)``, in normalized coordinates, multiplied by
the focal length (pixels), with one addition: ``E_i`` depends on the points' rows, and the
gradient in the denominator includes that (``Correspondences.ds_dy``; 0 gives the paper's
constant-``E_i`` error).

This is the readable specification: the tests check the compiled kernels
(:mod:`rsvo_ros.twoview.kernels`) and their analytic Jacobian against it; the estimator's runtime
path does not use it.
"""

from __future__ import annotations

import numpy as np

from rsvo_ros.core.geometry import so3_exp, so3_right_jacobian
from rsvo_ros.twoview.state import NUM_PARAMS, Correspondences, RSBatch, tangent_basis


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product over the last axis (faster than np.cross for small trailing axes)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def _broadcast(corr: Correspondences, B: int, idx: np.ndarray | None):
    """Per-hypothesis views (B, n, ...) of the correspondences (all, or the (B, n) ``idx``)."""
    if idx is None:
        return (corr.x_prev[None], corr.x_curr[None], corr.s_prev[None], corr.s_curr[None])
    return corr.x_prev[idx], corr.x_curr[idx], corr.s_prev[idx], corr.s_curr[idx]


def sampson_residuals(
    state: RSBatch, corr: Correspondences, jacobian: bool = False,
    idx: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:  # fmt: skip
    """Signed Sampson errors (B, n) in pixels and, optionally, their Jacobian (B, n, 17).

    Each hypothesis ``b`` is evaluated on all correspondences, or on ``corr``'s rows
    ``idx[b]`` when the (B, n) index array is given. The Jacobian is analytic, with respect to
    the increment of :meth:`RSBatch.retract`.
    """
    x_p, x_c, s_p, s_c = _broadcast(corr, len(state), idx)
    R, t, vel = state.R, state.t, state.vel
    w_p, v_p, w_c, v_c = vel[:, 0:3], vel[:, 3:6], vel[:, 6:9], vel[:, 9:12]
    phi_p = s_p[..., None] * w_p[:, None, :]
    phi_c = s_c[..., None] * w_c[:, None, :]
    Rp, Rc = so3_exp(phi_p), so3_exp(phi_c)
    q = np.einsum("bnij,bnj->bni", Rp, x_p)  # Rp x_p
    a = np.einsum("bij,bnj->bni", R, q)  # R Rp x_p
    b = np.einsum("bnij,bnj->bni", Rc, x_c)  # Rc x_c
    tp = s_p[..., None] * v_p[:, None, :]
    T = t[:, None, :] + np.einsum("bij,bnj->bni", R, tp) - s_c[..., None] * v_c[:, None, :]
    g = _cross(T, a)  # [T]x a
    h = _cross(b, T)  # -[T]x b
    n = np.einsum("bni,bni->bn", b, g)  # x_c^T E x_p
    Ex = np.einsum("bnji,bnj->bni", Rc, g)  # Rc^T g = E x_p
    Rth = np.einsum("bji,bnj->bni", R, h)  # R^T h
    ETx = np.einsum("bnji,bnj->bni", Rp, Rth)  # Rp^T R^T h = E^T x_c
    # E_i moves with the points' rows: dn/ds_c and dn/ds_p (d/ds Exp(s w) = Exp(s w) [w]x)
    m_p = _cross(w_p[:, None, :], x_p)  # w_p x x_p
    m_c = _cross(w_c[:, None, :], x_c)
    mp2 = np.einsum("bnij,bnj->bni", Rp, m_p)
    da = np.einsum("bij,bnj->bni", R, mp2)  # da/ds_p = R Rp [w_p]x x_p
    db = np.einsum("bnij,bnj->bni", Rc, m_c)  # db/ds_c
    Rv = np.einsum("bij,bj->bi", R, v_p)[:, None, :]  # dT/ds_p
    vc = v_c[:, None, :]  # -dT/ds_c
    dn_c = np.einsum("bni,bni->bn", db, g) + np.einsum("bni,bni->bn", b, _cross(a, vc))
    dn_p = np.einsum("bni,bni->bn", da, h) + np.einsum("bni,bni->bn", Rv, _cross(a, b))
    kappa = corr.ds_dy
    # gradient of n with respect to the normalized image coordinates, rows included
    u = Ex.copy()
    u[..., 1] += kappa * dn_c
    u[..., 2] = 0.0
    z = ETx.copy()
    z[..., 1] += kappa * dn_p
    z[..., 2] = 0.0
    d2 = u[..., 0] ** 2 + u[..., 1] ** 2 + z[..., 0] ** 2 + z[..., 1] ** 2
    inv_d = 1.0 / np.sqrt(np.maximum(d2, 1e-300))
    e = corr.focal * n * inv_d
    if not jacobian:
        return e, None

    # e = f n / sqrt(d2), n = b.(T x a), d2 = |u|^2 + |z|^2 with u = P Ex + kappa dn_c e_y,
    # z = P ETx + kappa dn_p e_y (P: first two components).
    # Every parameter moves a, b, T (and da, db, Rv, v_c) and rotates Ex / ETx (through Rc^T,
    # Rp^T, R^T): collect the gradient of e with respect to those as vectors, then chain to each
    # parameter block.
    U = np.einsum("bnij,bnj->bni", Rc, u)
    A = np.einsum("bij,bnjk->bnik", R, Rp)  # R Rp; E^T x_c = A^T h
    Z = np.einsum("bnij,bnj->bni", A, z)
    k = (corr.focal * n * inv_d**3)[..., None]
    f_inv_d = (corr.focal * inv_d)[..., None]
    alpha = -k * kappa * u[..., 1:2]  # multiplies d(dn_c)
    beta = -k * kappa * z[..., 1:2]  # multiplies d(dn_p)
    c_a = f_inv_d * h - k * _cross(U, T) + alpha * (_cross(db, T) + _cross(vc, b)) \
        + beta * _cross(b, Rv)  # multiplies da
    c_b = f_inv_d * g - k * _cross(T, Z) + alpha * _cross(a, vc) \
        + beta * (_cross(T, da) + _cross(Rv, a))  # multiplies db
    c_T = f_inv_d * _cross(a, b) - k * (_cross(a, U) + _cross(Z, b)) \
        + alpha * _cross(a, db) + beta * _cross(da, b)  # multiplies dT
    c_Ex = -k * u  # multiplies the rotation term of Ex
    c_ETx = -k * z  # multiplies the rotation terms of ETx
    c_db = alpha * g  # multiplies d(db/ds_c)
    c_da = beta * h  # multiplies d(da/ds_p)
    c_Rv = beta * _cross(a, b)  # multiplies d(R v_p)
    c_vc = alpha * _cross(b, a)  # multiplies dv_c (dn_c's explicit v_c)
    RtcT = np.einsum("bji,bnj->bni", R, c_T)  # R^T c_T
    Rtc_da = np.einsum("bji,bnj->bni", R, c_da)
    Rtc_Rv = np.einsum("bji,bnj->bni", R, c_Rv)

    Jr_p, Jr_c = so3_right_jacobian(phi_p), so3_right_jacobian(phi_c)
    J = np.empty(e.shape + (NUM_PARAMS,))
    # rotation, R <- R Exp(d): da = -R [q]x d, dT = -R [tp]x d, ETx gains Rp^T [R^T h]x d,
    # d(da/ds_p) = -R [Rp m_p]x d, d(R v_p) = -R [v_p]x d
    J[..., 0:3] = (
        _cross(q, np.einsum("bji,bnj->bni", R, c_a))
        + _cross(tp, RtcT)
        + _cross(np.einsum("bnij,bnj->bni", Rp, c_ETx), Rth)
        + _cross(mp2, Rtc_da)
        + _cross(v_p[:, None, :], Rtc_Rv)
    )
    # translation direction: dT = B d
    J[..., 3:5] = np.einsum("bni,bik->bnk", c_T, tangent_basis(t))
    # w_prev: dRp = Rp [M_p d]x with M_p = s_p J_r(s_p w_p); d(da/ds_p) also gains A [d]x x_p
    y_p = np.einsum("bnji,bnj->bni", A, c_a)
    y_da = np.einsum("bnji,bnj->bni", A, c_da)
    J[..., 5:8] = s_p[..., None] * np.einsum(
        "bnji,bnj->bni", Jr_p, _cross(x_p, y_p) + _cross(c_ETx, ETx) + _cross(m_p, y_da)
    ) + _cross(x_p, y_da)
    # v_prev: dT = s_p R d, d(R v_p) = R d
    J[..., 8:11] = s_p[..., None] * RtcT + Rtc_Rv
    # w_curr: dRc = Rc [M_c d]x; d(db/ds_c) also gains Rc [d]x x_c
    y_c = np.einsum("bnji,bnj->bni", Rc, c_b)
    y_db = np.einsum("bnji,bnj->bni", Rc, c_db)
    J[..., 11:14] = s_c[..., None] * np.einsum(
        "bnji,bnj->bni", Jr_c, _cross(x_c, y_c) + _cross(c_Ex, Ex) + _cross(m_c, y_db)
    ) + _cross(x_c, y_db)
    # v_curr: dT = -s_c d, and dn_c's own v_c
    J[..., 14:17] = -s_c[..., None] * c_T + c_vc
    return e, J


def rs_depths(state: RSBatch, corr: Correspondences) -> tuple[np.ndarray, np.ndarray]:
    """Depths (along the bearings) of every correspondence in both frames, (B, N) each.

    Least squares of ``lam_c Rc x_c = lam_p R Rp x_p + T`` per point (the rows' own cameras).
    """
    x_p, x_c, s_p, s_c = _broadcast(corr, len(state), None)
    vel = state.vel
    Rp = so3_exp(s_p[..., None] * vel[:, None, 0:3])
    Rc = so3_exp(s_c[..., None] * vel[:, None, 6:9])
    a = np.einsum("bij,bnj->bni", state.R, np.einsum("bnij,bnj->bni", Rp, x_p))
    b = np.einsum("bnij,bnj->bni", Rc, x_c)
    tp = s_p[..., None] * vel[:, None, 3:6]
    T = state.t[:, None, :] + np.einsum("bij,bnj->bni", state.R, tp)
    T = T - s_c[..., None] * vel[:, None, 9:12]
    # minimise |lam_p a - lam_c b + T|^2 over (lam_p, lam_c)
    aa, bb, ab = (a * a).sum(-1), (b * b).sum(-1), (a * b).sum(-1)
    aT, bT = (a * T).sum(-1), (b * T).sum(-1)
    det = aa * bb - ab * ab
    det = np.where(np.abs(det) < 1e-15, np.nan, det)
    return (ab * bT - bb * aT) / det, (aa * bT - ab * aT) / det
