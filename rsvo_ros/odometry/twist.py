"""The odometry's twist: each posed frame's velocity from the motion since the last posed frame.

nav_msgs/Odometry carries a twist (linear and angular velocity in the child frame) beside the
pose; filters such as robot_localization fuse it where a monocular pose's scale drifts. Until
2026-11-26 the package left it zero with a zero covariance, which claims a camera that is
certainly at rest.

What is published is the backward difference of the last two poses of one trajectory, as
body-frame velocities of the later one (Convention: ``T_world_cam`` poses at row-0 times;
``R_cur = R_prev Exp(w dt)``, ``v = R_cur^T (p_cur - p_prev) / dt``), not the RS model's
per-frame velocity: against the renderer's instantaneous row-0 angular velocity the frame's RS
velocity was better on one bag of six (29-110 % median error on vehicles, walks and hand-held
bags against 27-95 % for the difference; docs/notebook.md, "The odometry's twist"). The linear
part is in the map's units per second (monocular: the trajectory's scale).

Its covariance is measured, not assumed: half the mean squared change of each component between
consecutive twists over the last ``TwistOptions.window`` frames (white noise of variance s^2
changes by 2 s^2 on average; a real acceleration adds to it). Where there is no previous pose of
the same trajectory (the first frame, after a reset, a held or lost frame, a re-found map, a
gap of over ``max_gap_s``) or too few twists to measure the scatter, the covariance is infinite
(unknown: the ROS shells publish it as 1e6, rtabmap's convention).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from rsvo_ros.core.geometry import so3_log


@dataclass
class TwistOptions:
    window: int = 30  # twists over which the scatter is measured
    min_samples: int = 5  # consecutive twists needed before a covariance is finite
    max_gap_s: float = 0.5  # a longer time between two poses: no twist
    min_variance: float = 1e-8  # floor of each measured variance ((m/s)^2, (rad/s)^2)


@dataclass
class Twist:
    """A frame's velocity in its own (body) frame: ``linear`` (3,) map units/s, ``angular`` (3,)
    rad/s; ``covariance`` (6, 6) of ``[linear, angular]`` (infinite where unknown)."""

    linear: np.ndarray = field(default_factory=lambda: np.zeros(3))
    angular: np.ndarray = field(default_factory=lambda: np.zeros(3))
    covariance: np.ndarray = field(default_factory=lambda: np.diag(np.full(6, np.inf)))
    since_ns: int | None = None  # the stamp of the earlier pose (None: no twist)

    @property
    def known(self) -> bool:
        return bool(np.isfinite(self.covariance).all())

    @property
    def vector(self) -> np.ndarray:
        """(6,) ``[linear, angular]``."""
        return np.concatenate([self.linear, self.angular])


def body_twist(T_world_prev: np.ndarray, T_world_cur: np.ndarray,
               dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Body-frame ``(linear, angular)`` velocity of the later pose from two ``(4, 4)`` poses
    ``dt`` s apart. Convention: ``R_cur = R_prev Exp(angular dt)``, ``linear = R_cur^T (p_cur -
    p_prev) / dt``."""
    if not dt > 0:
        raise ValueError(f"dt must be positive, got {dt}")
    R0, R1 = T_world_prev[:3, :3], T_world_cur[:3, :3]
    angular = so3_log(R0.T @ R1) / dt
    linear = R1.T @ (T_world_cur[:3, 3] - T_world_prev[:3, 3]) / dt
    return linear, angular


def twist_in_frame(twist: Twist, T_child_cam: np.ndarray) -> Twist:
    """The camera's body twist as the twist of a frame rigidly attached to it (``T_child_cam``
    (4, 4): the camera in the child frame, e.g. ``base_link``): ``w_c = R w``, ``v_c = R (v + w
    x p_cam_child)`` with ``p_cam_child`` the child's origin in the camera frame; the covariance
    through the same linear map."""
    R = T_child_cam[:3, :3]
    p = -R.T @ T_child_cam[:3, 3]  # the child's origin in the camera frame
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[:3, 3:] = -R @ np.array([[0.0, -p[2], p[1]], [p[2], 0.0, -p[0]], [-p[1], p[0], 0.0]])
    A[3:, 3:] = R
    out = A @ twist.vector
    cov = twist.covariance
    if np.isfinite(cov).all():
        cov = A @ cov @ A.T
    return Twist(out[:3], out[3:], cov.copy(), twist.since_ns)


class TwistEstimator:
    """Feed every frame's outcome with :meth:`update`; returns that frame's :class:`Twist`."""

    def __init__(self, options: TwistOptions | None = None):
        self.options = options or TwistOptions()
        self.reset()

    def reset(self) -> None:
        """A new trajectory: the next pose has no predecessor."""
        self._prev: tuple[int, np.ndarray] | None = None
        self._history: deque = deque(maxlen=self.options.window + 1)

    def update(self, stamp_ns: int, T_world_cam: np.ndarray | None, continuous: bool) -> Twist:
        """``continuous``: this pose continues the last one's trajectory (False for a first,
        held, lost or re-found frame: no twist, and the next one starts from it if posed)."""
        o = self.options
        prev, self._prev = self._prev, None
        if T_world_cam is None or not np.isfinite(T_world_cam).all():
            self._history.clear()
            return Twist()
        self._prev = (int(stamp_ns), np.array(T_world_cam, float))
        if not continuous or prev is None:
            self._history.clear()
            return Twist()
        dt = (int(stamp_ns) - prev[0]) * 1e-9
        if not 0.0 < dt <= o.max_gap_s:
            self._history.clear()
            return Twist()
        linear, angular = body_twist(prev[1], T_world_cam, dt)
        twist = Twist(linear, angular, since_ns=prev[0])
        self._history.append(twist.vector)
        if len(self._history) > o.min_samples:
            steps = np.diff(np.asarray(self._history), axis=0)
            var = np.maximum(0.5 * np.mean(steps**2, axis=0), o.min_variance)
            twist.covariance = np.diag(var)
        return twist
