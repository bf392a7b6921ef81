"""Frames of the window backend: a camera state at the reference row and its observations.

Convention (CONTRACTS.md, re-expressed at the reference row ``row_ref``, the principal point's
row): ``R``, ``p`` are ``T_world_camera`` of the camera that exposed row ``row_ref``; ``w``
(rad/s) and ``v`` (map units/s) its instantaneous motion in its own frame, ``a`` (rad/s^2) the
change of its turn rate; the camera of row ``r`` is that one moved by ``s = (r - row_ref) tau``
seconds of it (``R Exp(s w + s^2/2 a)``, ``p + R s v``; see
:mod:`rsvo_ros.odometry.rs_projection`). Pure numpy.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from rsvo_ros.core.geometry import so3_exp, so3_log


@dataclass
class FrameState:
    """A frame's camera at the reference row, in the world, and its RS motion."""

    stamp_ns: int
    R: np.ndarray  # (3, 3) world <- camera
    p: np.ndarray  # (3,)
    w: np.ndarray = field(default_factory=lambda: np.zeros(3))  # rad/s, camera frame
    v: np.ndarray = field(default_factory=lambda: np.zeros(3))  # map units/s, camera frame
    a: np.ndarray = field(default_factory=lambda: np.zeros(3))  # rad/s^2, camera frame

    def copy(self) -> FrameState:
        return FrameState(self.stamp_ns, self.R.copy(), self.p.copy(), self.w.copy(),
                          self.v.copy(), self.a.copy())  # fmt: skip

    def at(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        """``(R, p)`` of the camera ``s`` seconds of readout from the reference row."""
        return self.R @ so3_exp(s * (self.w + 0.5 * s * self.a)), self.p + self.R @ (s * self.v)

    def row_cameras(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(R, p)`` (n, 3, 3), (n, 3) of the cameras at row times ``s`` (n,)."""
        s = np.asarray(s, float)[:, None]
        R = self.R @ so3_exp(s * (self.w + 0.5 * s * self.a))
        return R, self.p + (s * self.v) @ self.R.T

    def pose(self, s: float = 0.0) -> np.ndarray:
        """(4, 4) ``T_world_camera`` of the camera at row time ``s`` (0: the reference row)."""
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.at(s)
        return T

    def row0_velocities(self, s0: float) -> tuple[np.ndarray, np.ndarray]:
        """``(w, v)`` of the row-0 camera (row time ``s0``) in its own frame, as CONTRACTS.md
        reports them: the turn rate there (``w + s0 a``; about its own axis, so the frame does
        not change it), ``v`` rotated into that camera."""
        return self.w + s0 * self.a, self.at(s0)[0].T @ self.R @ self.v


@dataclass
class Observations:
    """Tracked features of one frame: track ids (n,), normalized undistorted coordinates (n, 2),
    row times from the reference row (n,), undistorted pixels (n, 2) and the sensor rows
    (n,) they were exposed in (the raw, distorted rows)."""

    ids: np.ndarray
    x: np.ndarray
    s: np.ndarray
    px: np.ndarray
    rows: np.ndarray
    # ORB descriptors (n, 32) and which points have one (n,), computed on the first call
    # (the pipeline sets it with its image; odometry/relocalize.py); None: not available
    describe: Callable[[], tuple[np.ndarray, np.ndarray]] | None = field(
        default=None, repr=False, compare=False)

    def __len__(self) -> int:
        return len(self.ids)

    def subset(self, mask: np.ndarray) -> Observations:
        return Observations(self.ids[mask], self.x[mask], self.s[mask], self.px[mask],
                            self.rows[mask])


@dataclass
class KeyFrame:
    """A keyframe of the window: its state (refined by the window BA) and observations."""

    id: int
    state: FrameState
    obs: Observations
    velocity_prior: tuple[np.ndarray, np.ndarray] | None = None  # (w, v) without neighbours
    rejected: set = field(default_factory=set)  # track ids whose observation here is an outlier
    before: FrameState | None = None  # the tracked frames just before and after (for the
    after: FrameState | None = None  # velocity prior of the window: the motion between them)
    descriptors: tuple[np.ndarray, np.ndarray] | None = None  # of obs (re-finding the map)

    def trajectory_velocity(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(w, v)`` of a constant motion through the neighbouring frames (central difference,
        or with one neighbour and this keyframe's own state), in this keyframe's frame."""
        a = self.before or self.state
        b = self.after or self.state
        if a is b or b.stamp_ns <= a.stamp_ns:
            return self.velocity_prior
        w, v_b = interval_velocity(a, b)
        return w, self.state.R.T @ (b.R @ v_b)


def extrapolate(last: FrameState, before: FrameState | None, stamp_ns: int) -> FrameState:
    """Constant-velocity prediction of the reference-row camera at ``stamp_ns`` from the two
    last states (one state: no motion). The velocities are carried over."""
    out = last.copy()
    out.stamp_ns = stamp_ns
    if before is None or last.stamp_ns <= before.stamp_ns:
        return out
    a = (stamp_ns - last.stamp_ns) / (last.stamp_ns - before.stamp_ns)
    # the last interval's motion, T_before^-1 T_last, repeated (scaled to the new interval)
    dR = before.R.T @ last.R
    dp = before.R.T @ (last.p - before.p)
    out.R = last.R @ so3_exp(a * so3_log(dR))
    out.p = last.p + last.R @ (a * dp)
    return out


def interval_velocity(a: FrameState, b: FrameState) -> tuple[np.ndarray, np.ndarray]:
    """``(w, v)`` in ``b``'s frame of a constant motion from ``a`` to ``b`` over their stamps."""
    dt = max((b.stamp_ns - a.stamp_ns) * 1e-9, 1e-9)
    w = so3_log(a.R.T @ b.R) / dt
    v = b.R.T @ (b.p - a.p) / dt
    return w, v
