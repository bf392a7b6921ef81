"""The synthetic setting of the paper's Sec. 7.1: a smooth ~80 m loop, 3D landmarks around it,
RS feature correspondences of consecutive frames at six distortion levels.

Pure numpy. World frame: x and z horizontal, y pointing down (so an un-rotated camera looks
along +z, like the optical frame); the loop starts and ends at ``[2, 2, 2]`` m as in the paper.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rsvo_ros.core.geometry import pose_at_row, project_rs, so3_exp

# Paper, Sec. 7.1.
IMAGE_WIDTH, IMAGE_HEIGHT = 1280, 720
IMAGE_SIZE = np.array([IMAGE_WIDTH, IMAGE_HEIGHT])
FOCAL_PX = 1000.0  # the paper's 5 mm lens with an assumed 5 um pixel pitch
LINE_DELAY = 50e-6  # tau, s per row
FRAME_RATE_HZ = 5.0
NUM_FRAMES = 250
MAX_FEATURES = 500  # bucketing keeps at most this many
# RS distortion levels 1-6: (linear m/s, angular deg/s) of each frame's instantaneous motion.
RS_LEVELS = {1: (0.0, 0.0), 2: (10.0, 20.0), 3: (20.0, 40.0), 4: (30.0, 60.0),
             5: (40.0, 80.0), 6: (50.0, 100.0)}  # fmt: skip
LOOP_SEMI_AXES_M = (15.0, 10.0)  # ellipse in x, z: perimeter ~79 m ("about 80 m")
LOOP_START = np.array([2.0, 2.0, 2.0])
BUCKET_GRID = (16, 9)  # columns x rows of the bucketing grid


def intrinsics(focal: float = FOCAL_PX, width: int = IMAGE_WIDTH, height: int = IMAGE_HEIGHT):
    """(3, 3) pinhole K with the principal point at the image centre."""
    return np.array(
        [[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0.0, 0.0, 1.0]]
    )


@dataclass
class LoopTrajectory:
    """Row-0 camera poses ``T_world_camera`` of the loop, (F, 3, 3) and (F, 3)."""

    R_world_cam: np.ndarray
    p_world_cam: np.ndarray
    stamps: np.ndarray


def loop_trajectory(rng: np.random.Generator, num_frames: int = NUM_FRAMES,
                    rate_hz: float = FRAME_RATE_HZ) -> LoopTrajectory:
    """The paper's smooth loop with small random pose noise ("to simulate realistic motion").

    The camera looks along the direction of travel, with a few degrees of smooth random
    yaw/pitch/roll and a few centimetres of position noise.
    """
    a, b = LOOP_SEMI_AXES_M
    theta = np.linspace(0.0, 2.0 * np.pi, num_frames, endpoint=False)
    p = np.stack([LOOP_START[0] + a * (1 - np.cos(theta)),
                  np.full_like(theta, LOOP_START[1]),
                  LOOP_START[2] + b * np.sin(theta)], axis=1)  # fmt: skip
    tangent = np.stack([a * np.sin(theta), np.zeros_like(theta), b * np.cos(theta)], axis=1)
    z_axis = tangent / np.linalg.norm(tangent, axis=1, keepdims=True)
    y_axis = np.broadcast_to([0.0, 1.0, 0.0], z_axis.shape)
    x_axis = np.cross(y_axis, z_axis)
    R = np.stack([x_axis, y_axis, z_axis], axis=2)  # columns: camera axes in world
    # smooth noise: a few low-frequency sinusoids with random phases
    k = np.arange(num_frames)[:, None]
    phases = rng.uniform(0, 2 * np.pi, (2, 3))
    slow = np.sin(2 * np.pi * k * 3 / num_frames + phases[0])
    fast = np.sin(2 * np.pi * k * 11 / num_frames + phases[1])
    ang = np.radians(2.0) * (slow + 0.5 * fast)
    R = R @ so3_exp(ang)
    p = p + 0.03 * rng.standard_normal(p.shape)
    p[0] = LOOP_START
    return LoopTrajectory(R, p, np.arange(num_frames) / rate_hz)


def landmarks(rng: np.random.Generator, count: int = 30000) -> np.ndarray:
    """(count, 3) points in a band 3-15 m to either side of the loop, -6..+2 m in height."""
    a, b = LOOP_SEMI_AXES_M
    theta = rng.uniform(0.0, 2.0 * np.pi, count)
    centre = np.stack([LOOP_START[0] + a * (1 - np.cos(theta)),
                       np.full(count, LOOP_START[1]),
                       LOOP_START[2] + b * np.sin(theta)], axis=1)  # fmt: skip
    normal = np.stack([-b * np.cos(theta), np.zeros(count), a * np.sin(theta)], axis=1)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    side = rng.choice([-1.0, 1.0], count) * rng.uniform(3.0, 15.0, count)
    height = rng.uniform(-6.0, 2.0, count)
    return centre + side[:, None] * normal + height[:, None] * np.array([0.0, 1.0, 0.0])


def random_rs_velocity(rng: np.random.Generator, level: int) -> tuple[np.ndarray, np.ndarray]:
    """A frame's instantaneous (w rad/s, v m/s): the level's magnitudes, uniform directions."""
    v_mag, w_deg = RS_LEVELS[level]
    dirs = rng.standard_normal((2, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return np.radians(w_deg) * dirs[0], v_mag * dirs[1]


def bucket_select(pts: np.ndarray, max_count: int, width: int, height: int,
                  rng: np.random.Generator, grid: tuple[int, int] = BUCKET_GRID) -> np.ndarray:
    """Indices of at most ``max_count`` points spread evenly over a grid of image cells."""
    cols = np.clip((pts[:, 0] / width * grid[0]).astype(int), 0, grid[0] - 1)
    rows = np.clip((pts[:, 1] / height * grid[1]).astype(int), 0, grid[1] - 1)
    cell = rows * grid[0] + cols
    order = rng.permutation(len(pts))
    # rank of each point inside its cell (in random order), then take round-robin by rank
    cell_sorted = cell[order]
    sort = np.argsort(cell_sorted, kind="stable")
    ranked = order[sort]
    cell_of_ranked = cell[ranked]
    starts = np.searchsorted(cell_of_ranked, np.arange(grid[0] * grid[1]))
    rank = np.arange(len(ranked)) - starts[cell_of_ranked]
    chosen = ranked[np.lexsort((rng.random(len(ranked)), rank))][:max_count]
    return np.sort(chosen)


@dataclass
class FramePair:
    """RS correspondences of two consecutive frames with their ground truth.

    ``pts_prev``/``pts_curr``: (N, 2) noise-free pixels; ``R``, ``t``: row-0 relative pose
    (``X_curr = R X_prev + t``, metres); ``w_*`` rad/s and ``v_*`` m/s in row-0 frames.
    """

    pts_prev: np.ndarray
    pts_curr: np.ndarray
    R: np.ndarray
    t: np.ndarray
    w_prev: np.ndarray
    v_prev: np.ndarray
    w_curr: np.ndarray
    v_curr: np.ndarray
    K: np.ndarray
    line_delay: float
    height: int

    def pose_at_middle_row(self) -> tuple[np.ndarray, np.ndarray]:
        """Ground-truth relative pose of the cameras at the middle image row."""
        R_m, t_m, _ = pose_at_row(self.R, self.t, self.w_prev, self.v_prev, self.w_curr,
                                  self.v_curr, (self.height - 1) / 2.0, self.line_delay)
        return R_m, t_m


class PaperScene:
    """The loop and its landmarks; :meth:`frame_pair` draws the data of one trial."""

    def __init__(self, seed: int = 0, line_delay: float = LINE_DELAY):
        rng = np.random.default_rng(seed)
        self.trajectory = loop_trajectory(rng)
        self.points = landmarks(rng)
        self.K = intrinsics()
        self.line_delay = line_delay

    def frame_pair(self, rng: np.random.Generator, level: int, frame: int | None = None,
                   max_features: int = MAX_FEATURES) -> FramePair:
        """Consecutive frames ``(frame, frame+1)``, each with its own random RS velocity."""
        traj = self.trajectory
        n = len(traj.stamps)
        k = int(rng.integers(0, n - 1)) if frame is None else frame
        w_p, v_p = random_rs_velocity(rng, level)
        w_c, v_c = random_rs_velocity(rng, level)
        R0, p0 = traj.R_world_cam[k], traj.p_world_cam[k]
        R1, p1 = traj.R_world_cam[k + 1], traj.p_world_cam[k + 1]
        # cheap pre-filter: points in front of both cameras within 60 m
        d0 = (self.points - p0) @ R0
        d1 = (self.points - p1) @ R1
        near = (d0[:, 2] > 0.5) & (d1[:, 2] > 0.5) & (d0[:, 2] < 60) & (d1[:, 2] < 60)
        for d in (d0, d1):  # and whose row-0 projection is within half an image of the image
            u = d[:, :2] / np.maximum(d[:, 2:3], 0.5) * self.K[[0, 1], [0, 1]] + self.K[:2, 2]
            near &= np.all((u > -0.5 * IMAGE_SIZE) & (u < 1.5 * IMAGE_SIZE), axis=1)
        X = self.points[near]
        pts0, _ = project_rs(X, R0, p0, self.K, self.line_delay, w_p, v_p, IMAGE_HEIGHT)
        pts1, _ = project_rs(X, R1, p1, self.K, self.line_delay, w_c, v_c, IMAGE_HEIGHT)
        inside = np.all(np.isfinite(pts0) & np.isfinite(pts1), axis=1)
        for pts in (pts0, pts1):
            inside &= (pts[:, 0] >= 0) & (pts[:, 0] <= IMAGE_WIDTH - 1)
        pts0, pts1 = pts0[inside], pts1[inside]
        keep = bucket_select(pts0, max_features, IMAGE_WIDTH, IMAGE_HEIGHT, rng)
        R = R1.T @ R0
        t = R1.T @ (p0 - p1)
        return FramePair(pts0[keep], pts1[keep], R, t, w_p, v_p, w_c, v_c, self.K,
                         self.line_delay, IMAGE_HEIGHT)
