"""Compiled (numba) algebra of 3-vectors and 3 x 3 matrices as tuples, and SO(3)'s exponential
with its right Jacobian: the inner loops of the RS solver and of the odometry's reprojection
kernels allocate nothing.

Vectors are 3-tuples, matrices tuples of rows. Same conventions as
:mod:`rsvo_ros.core.geometry` (``so3_exp``, ``so3_right_jacobian``).
"""

from __future__ import annotations

import numba as nb
import numpy as np

JIT = {"cache": True, "nogil": True, "fastmath": False}
SERIES_ANGLE = 0.25  # rad; below this Exp and J_r use their Taylor series (row rotations are
# s * |w| <= 20 ms * 5 rad/s = 0.1 rad)


@nb.njit(**JIT, inline="always")
def dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@nb.njit(**JIT, inline="always")
def cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@nb.njit(**JIT, inline="always")
def add(a, b):
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


@nb.njit(**JIT, inline="always")
def scale(s, a):
    return (s * a[0], s * a[1], s * a[2])


@nb.njit(**JIT, inline="always")
def mv(M, x):
    """``M x`` for a matrix given as a tuple of rows."""
    return (dot(M[0], x), dot(M[1], x), dot(M[2], x))


@nb.njit(**JIT, inline="always")
def mtv(M, x):
    """``M^T x``."""
    return add(add(scale(x[0], M[0]), scale(x[1], M[1])), scale(x[2], M[2]))


@nb.njit(**JIT, inline="always")
def mm(A, B):
    """``A B``: row ``i`` of the product is ``B^T`` applied to row ``i`` of ``A``."""
    return (mtv(B, A[0]), mtv(B, A[1]), mtv(B, A[2]))


@nb.njit(**JIT, inline="always")
def exp_jr(p):
    """``Exp(p)`` and the right Jacobian ``J_r(p)`` (tuples of rows), as
    :func:`rsvo_ros.core.geometry.so3_exp` and
    :func:`rsvo_ros.core.geometry.so3_right_jacobian`."""
    th2 = dot(p, p)
    if th2 < SERIES_ANGLE**2:
        # Taylor series in th^2 (truncation < 1e-17 here): no sqrt, sin or cos per point
        a = 1.0 + th2 * (-1 / 6 + th2 * (1 / 120 + th2 * (-1 / 5040 + th2 * (
            1 / 362880 - th2 / 39916800))))  # fmt: skip
        b = 0.5 + th2 * (-1 / 24 + th2 * (1 / 720 + th2 * (-1 / 40320 + th2 * (
            1 / 3628800 - th2 / 479001600))))  # fmt: skip
        c = 1 / 6 + th2 * (-1 / 120 + th2 * (1 / 5040 + th2 * (-1 / 362880 + th2 * (
            1 / 39916800 - th2 / 6227020800))))  # fmt: skip
    else:
        th = np.sqrt(th2)
        sn = np.sin(th)
        a = sn / th
        b = (1.0 - np.cos(th)) / th2
        c = (th - sn) / (th2 * th)
    x, y, z = p
    d = 1.0 - b * th2
    R = ((d + b * x * x, -a * z + b * x * y, a * y + b * x * z),
         (a * z + b * x * y, d + b * y * y, -a * x + b * y * z),
         (-a * y + b * x * z, a * x + b * y * z, d + b * z * z))  # fmt: skip
    d = 1.0 - c * th2
    J = ((d + c * x * x, b * z + c * x * y, -b * y + c * x * z),
         (-b * z + c * x * y, d + c * y * y, b * x + c * y * z),
         (b * y + c * x * z, -b * x + c * y * z, d + c * z * z))  # fmt: skip
    return R, J


@nb.njit(**JIT)
def rows(M):
    return ((M[0, 0], M[0, 1], M[0, 2]), (M[1, 0], M[1, 1], M[1, 2]),
            (M[2, 0], M[2, 1], M[2, 2]))  # fmt: skip


@nb.njit(**JIT)
def rot_update(R, dth):
    """``R @ Exp(dth)`` as a new (3, 3) array: the SO(3) retraction both LM kernels use."""
    dR, _ = exp_jr((dth[0], dth[1], dth[2]))
    Rr = mm(rows(R), dR)
    out = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            out[i, j] = Rr[i][j]
    return out
