"""Synthetic rolling-shutter image sequences with exact ground truth.

Pure numpy + OpenCV. The world is a textured corridor that follows the paper's ~80 m loop
(two elliptic-cylinder walls, a floor and a ceiling); every image row ``r`` is rendered from the
camera pose at ``stamp + r * line_delay`` (per-row pose, per-pixel ray/surface intersection,
texture lookup with ``cv2.remap``), so the images carry true rolling-shutter distortion.

Motions (``MOTIONS``):
- ``paper``: the paper's setting (Sec. 7.1): the smooth loop sampled at 5 Hz, each frame with
  its own random instantaneous RS velocity at level 1-6; rows follow the RS model of
  CONTRACTS.md exactly: ``X_row0 = Exp(r tau w) X_row_r + r tau v``.
- ``handheld`` / ``vehicle``: a continuous 30 Hz camera walking (1.4 m/s) or driving (8 m/s)
  along the loop, shaken by hand tremor or road vibration; ``severity`` scales the shaking.
- ``walk``: a person walking (about 1 m/s) with a hand-held camera at 30 Hz: head bob and sway
  at the step frequency, hand shake inside (3-5 Hz) and above (8-15 Hz) the readout band, fast
  pans every few seconds and, in sequences of 8 s and more, a stop to look around (a stretch
  of pure rotation); ``severity`` scales the shake (0.5 mild, 1 strong, 2 strongest).
  Rows follow the continuous trajectory; the frame's (w, v) ground truth is its instantaneous
  velocity at the row-0 time.
Conventions: world frame y down (the loop lies in x-z), camera optical frame, poses
``T_world_camera`` at row-0 times, velocities in the row-0 camera frame.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from rsvo_ros.core.geometry import project_rs_rows, so3_exp, so3_log
from rsvo_ros.core.lens import LensModel
from rsvo_ros.sim import paper_scene

MOTIONS = ("paper", "handheld", "vehicle", "walk")
# lenses a synthetic bag can be rendered through (CameraInfo models; a wide-angle look: the
# corners of a 640x360 image move by 20-50 px)
LENSES = {
    "plumb_bob": LensModel("plumb_bob", (-0.25, 0.07, 0.0005, -0.0004, -0.008)),
    "rational_polynomial": LensModel("rational_polynomial",
                                     (0.25, -0.02, 0.0005, -0.0004, 0.0, 0.5, 0.02, 0.0)),
    "equidistant": LensModel("equidistant", (0.02, -0.01, 0.003, -0.001)),
}
FRAME_RATE_HZ = {"paper": paper_scene.FRAME_RATE_HZ, "handheld": 30.0, "vehicle": 30.0,
                 "walk": 30.0}
SPEED_M_S = {"handheld": 1.4, "vehicle": 8.0}
REFERENCE_READOUT_S = 720 * paper_scene.LINE_DELAY  # 36 ms: the paper's 720 rows x 50 us
CORRIDOR_HALF_WIDTH_M = 3.0
CAMERA_HEIGHT_M = 1.5  # above the floor (the floor is at y = loop height + 1.5, y down)
CEILING_HEIGHT_M = 4.0  # above the floor
TEXTURE_SIZE = 1024  # texels per side of each (tiling) texture
TEXELS_PER_M = 160.0

RowPoseFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


def resolution_arg(text: str) -> tuple[int, int]:
    """``WIDTHxHEIGHT`` (positive whole numbers) as ``(width, height)``: the ``--resolution``
    of every program that renders a synthetic sequence (``rsvo_synth``, the tools, the latency
    and transport probes); an ``argparse`` type, so a bad size is a usage error."""
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        w = h = 0
    if w <= 0 or h <= 0:
        raise argparse.ArgumentTypeError(
            f"{text!r}: expected WIDTHxHEIGHT in positive whole numbers, e.g. 640x360")
    return w, h


def default_line_delay(height: int) -> float:
    """Seconds per row giving the paper's 36 ms readout at any image height."""
    return REFERENCE_READOUT_S / height


def intrinsics(width: int, height: int) -> np.ndarray:
    """The paper's 1000 px focal length at 1280 px width, scaled to ``width``."""
    return paper_scene.intrinsics(paper_scene.FOCAL_PX * width / paper_scene.IMAGE_WIDTH,
                                  width, height)


# --------------------------------------------------------------------------- textures


def to_uint8(img: np.ndarray) -> np.ndarray:
    """Float grey levels rounded and clipped to uint8."""
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def make_texture(rng: np.random.Generator, size: int = TEXTURE_SIZE) -> np.ndarray:
    """A tiling, corner-rich grayscale texture (float32, 0..255): multi-scale noise plus
    random rectangles, discs and lines, so that a tracker finds features everywhere."""
    tex = np.zeros((size, size), np.float32)
    for cells, amp in ((4, 60.0), (16, 45.0), (64, 30.0), (256, 15.0)):
        coarse = rng.uniform(-1.0, 1.0, (cells, cells)).astype(np.float32)
        tiled = np.tile(coarse, (3, 3))  # resize a 3x3 tiling and crop: seamless
        big = cv2.resize(tiled, (3 * size, 3 * size), interpolation=cv2.INTER_CUBIC)
        tex += amp * big[size:2 * size, size:2 * size]
    canvas = np.zeros((size, size), np.float32)
    for _ in range(int(size * size / 2500)):
        kind = rng.integers(3)
        c = tuple(int(x) for x in rng.integers(0, size, 2))
        val = float(rng.uniform(-110, 110))
        if kind == 0:
            s = rng.integers(6, 40, 2)
            cv2.rectangle(canvas, c, (c[0] + int(s[0]), c[1] + int(s[1])), val, -1)
        elif kind == 1:
            cv2.circle(canvas, c, int(rng.integers(3, 18)), val, -1)
        else:
            d = rng.integers(-40, 40, 2)
            cv2.line(canvas, c, (c[0] + int(d[0]), c[1] + int(d[1])), val, int(rng.integers(2, 5)))
    tex += cv2.GaussianBlur(canvas, (0, 0), 1.0)
    return np.clip(tex + 128.0, 0.0, 255.0)


MOVER_TEXTURE = 4  # the surface index of the movers (the corridor's are 0-3)
# how close (m, centre to camera, horizontal) a mover's path may come to the camera's over the
# sequence: people step aside for a walker and keep off a car's path; without it a car drove
# through the people in front of it and the panel filled the whole view
MOVER_CLEARANCE_M = {"walk": 1.0, "handheld": 1.0, "vehicle": 2.0}


@dataclass
class Mover:
    """A pedestrian-sized textured panel that moves at constant velocity through the corridor
    (``SynthConfig.movers``): what people and cars are to visual odometry, a coherent group of
    points whose motion is not the camera's. Its centre is at ``centre0`` (world) at time
    ``t0`` (s, the sequence's clock); it faces ``normal`` (unit, horizontal)."""

    centre0: np.ndarray
    t0: float
    velocity: np.ndarray  # m/s, world
    normal: np.ndarray
    half_width: float = 0.35
    half_height: float = 0.85
    texture_offset: float = 0.0  # m along the mover texture: each mover wears its own part

    def centres(self, times: np.ndarray) -> np.ndarray:
        """(N, 3) the panel's centre at ``times`` (N,) s."""
        return self.centre0 + (np.asarray(times, float) - self.t0)[:, None] * self.velocity


@dataclass
class CorridorScene:
    """Walls, floor and ceiling of a corridor along the paper's loop, each with a texture.

    Walls: elliptic cylinders ``((x-cx)/A)^2 + ((z-cz)/B)^2 = 1`` with the loop's semi-axes
    minus / plus the half width (inner / outer). Texture coordinates in metres: walls
    (arc parameter, height), floor and ceiling (x, z).
    """

    textures: list[np.ndarray]
    # the movers' texture (:class:`Mover`; surface MOVER_TEXTURE); None: the scene has none
    mover_texture: np.ndarray | None = None
    centre: tuple[float, float] = (paper_scene.LOOP_START[0] + paper_scene.LOOP_SEMI_AXES_M[0],
                                   paper_scene.LOOP_START[2])  # fmt: skip
    semi_axes: tuple[float, float] = paper_scene.LOOP_SEMI_AXES_M
    half_width: float = CORRIDOR_HALF_WIDTH_M
    floor_y: float = float(paper_scene.LOOP_START[1]) + CAMERA_HEIGHT_M
    ceiling_y: float = float(paper_scene.LOOP_START[1]) + CAMERA_HEIGHT_M - CEILING_HEIGHT_M

    @staticmethod
    def create(seed: int) -> CorridorScene:
        rng = np.random.default_rng([seed, 7])
        textures = [make_texture(rng) for _ in range(4)]
        return CorridorScene(textures, make_texture(np.random.default_rng([seed, 19])))

    def wall_axes(self, which: int) -> tuple[float, float]:
        a, b = self.semi_axes
        sign = -1.0 if which == 0 else 1.0
        return a + sign * self.half_width, b + sign * self.half_width

    def render(self, R_rows: np.ndarray, p_rows: np.ndarray, K: np.ndarray, width: int,
               height: int, rays: tuple[np.ndarray, np.ndarray] | None = None,
               movers: Sequence[Mover] = (), row_times: np.ndarray | None = None) -> np.ndarray:
        """uint8 (height, width) image; row ``r`` seen from ``(R_rows[r], p_rows[r])``
        (``T_world_camera`` of that row). ``rays``: each pixel's normalized ``(x, y)`` (a lens:
        :func:`pixel_rays`); None: the pinhole ``K``. ``movers`` are drawn where each row sees
        them at its time ``row_times[r]`` (s)."""
        return to_uint8(self.radiance(R_rows, p_rows, K, width, height, rays, movers,
                                      row_times))  # fmt: skip

    def radiance(self, R_rows: np.ndarray, p_rows: np.ndarray, K: np.ndarray, width: int,
                 height: int, rays: tuple[np.ndarray, np.ndarray] | None = None,
                 movers: Sequence[Mover] = (), row_times: np.ndarray | None = None
                 ) -> np.ndarray:  # fmt: skip
        """:meth:`render` before quantisation: float32 grey levels (0..255)."""
        if movers and (row_times is None or self.mover_texture is None):
            raise ValueError("movers need the rows' times and a scene with a mover texture")
        f32 = np.float32
        # world ray of pixel (r, c): R_r (x, y, 1) = x R_r[:, 0] + y R_r[:, 1] + R_r[:, 2]
        if rays is None:  # pinhole: x depends on the column only, y on the row only
            Kinv = np.linalg.inv(K)
            a = (Kinv[0, 0] * np.arange(width) + Kinv[0, 2]).astype(f32)[None, :]
            b = Kinv[1, 1] * np.arange(height) + Kinv[1, 2]
            X = R_rows[:, :, 0].astype(f32)
            W = (b[:, None] * R_rows[:, :, 1] + R_rows[:, :, 2]).astype(f32)
            d = [a * X[:, i:i + 1] + W[:, i:i + 1] for i in range(3)]  # (H, W) each
        else:
            x, y = rays
            d = [(x * R_rows[:, i, 0][:, None] + y * R_rows[:, i, 1][:, None]
                  + R_rows[:, i, 2][:, None]).astype(f32) for i in range(3)]
        o = [p_rows[:, i:i + 1].astype(f32) for i in range(3)]  # (H, 1) each
        best = np.full((height, width), np.inf, f32)
        surf = np.full((height, width), -1, np.int8)
        tex_s = np.zeros((height, width), f32)
        tex_t = np.zeros((height, width), f32)
        cx, cz = self.centre
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            for which in (0, 1):  # inner wall (camera outside it), outer wall (camera inside)
                A, B = self.wall_axes(which)
                ox, oz = (o[0] - cx) / A, (o[2] - cz) / B
                dx, dz = d[0] / A, d[2] / B
                qa = dx * dx + dz * dz
                qb = ox * dx + oz * dz
                qc = ox * ox + oz * oz - 1.0
                disc = qb * qb - qa * qc
                root = np.sqrt(np.maximum(disc, 0.0))
                lam = (-qb - root) / qa if which == 0 else (-qb + root) / qa
                hit = (disc > 0) & (lam > 1e-3) & (lam < best)
                lam_h = lam[hit]
                px = np.broadcast_to(o[0], lam.shape)[hit] + lam_h * d[0][hit]
                pz = np.broadcast_to(o[2], lam.shape)[hit] + lam_h * d[2][hit]
                best[hit] = lam_h
                surf[hit] = which
                tex_s[hit] = np.arctan2((pz - cz) / B, (px - cx) / A) * 0.5 * (A + B)
                tex_t[hit] = np.broadcast_to(o[1], lam.shape)[hit] + lam_h * d[1][hit]
            for which, y0 in ((2, self.floor_y), (3, self.ceiling_y)):
                lam = (y0 - o[1]) / d[1]
                hit = (lam > 1e-3) & (lam < best)
                lam_h = lam[hit]
                best[hit] = lam_h
                surf[hit] = which
                tex_s[hit] = np.broadcast_to(o[0], lam.shape)[hit] + lam_h * d[0][hit]
                tex_t[hit] = np.broadcast_to(o[2], lam.shape)[hit] + lam_h * d[2][hit]
            for mover in movers:  # a vertical panel, its centre where it is at each row's time
                n = mover.normal.astype(f32)
                e1 = np.cross([0.0, 1.0, 0.0], mover.normal).astype(f32)  # horizontal, in plane
                rel = (mover.centres(row_times) - p_rows).astype(f32)  # (H, 3) camera to centre
                nd = n[0] * d[0] + n[1] * d[1] + n[2] * d[2]
                lam = (rel @ n)[:, None] / nd
                # the hit point from the centre, along e1 and down (y)
                u = lam * (e1[0] * d[0] + e1[1] * d[1] + e1[2] * d[2]) - (rel @ e1)[:, None]
                v = lam * d[1] - rel[:, 1:2]
                hit = (lam > 1e-3) & (lam < best) & (np.abs(u) <= mover.half_width) \
                    & (np.abs(v) <= mover.half_height)  # fmt: skip
                best[hit] = lam[hit]
                surf[hit] = MOVER_TEXTURE
                tex_s[hit] = u[hit] + mover.texture_offset
                tex_t[hit] = v[hit]
        img = np.zeros((height, width), f32)
        map_x = np.mod(tex_s * TEXELS_PER_M, TEXTURE_SIZE).astype(f32)
        map_y = np.mod(tex_t * TEXELS_PER_M, TEXTURE_SIZE).astype(f32)
        textures = list(self.textures)
        if movers:
            textures.append(self.mover_texture)
        for which, tex in enumerate(textures):
            mask = surf == which
            if not mask.any():
                continue
            sample = cv2.remap(tex, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
            img[mask] = sample[mask]
        return img

    def first_hit(self, origin: np.ndarray,
                  directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
        """Where rays from ``origin`` (3,) along ``directions`` (N, 3) first meet the corridor
        (walls, floor, ceiling; no movers), in float64: the distance in units of each
        direction's length (N,) (inf: no hit) and the surface (N,) (0 inner wall, 1 outer
        wall, 2 floor, 3 ceiling; -1: none). The exact-track tools' scene points."""
        o = np.asarray(origin, float)
        d = np.atleast_2d(np.asarray(directions, float))
        best = np.full(len(d), np.inf)
        surface = np.full(len(d), -1, np.int64)
        cx, cz = self.centre
        with np.errstate(invalid="ignore", divide="ignore"):
            for which in (0, 1):
                A, B = self.wall_axes(which)
                ox, oz, dx, dz = (o[0] - cx) / A, (o[2] - cz) / B, d[:, 0] / A, d[:, 2] / B
                qa, qb = dx * dx + dz * dz, ox * dx + oz * dz
                disc = qb * qb - qa * (ox * ox + oz * oz - 1.0)
                root = np.sqrt(np.maximum(disc, 0.0))
                for lam in ((-qb - root) / qa, (-qb + root) / qa):
                    hit = (disc > 0) & (lam > 1e-3) & (lam < best)
                    best[hit], surface[hit] = lam[hit], which
            for which, y0 in ((2, self.floor_y), (3, self.ceiling_y)):
                lam = (y0 - o[1]) / d[:, 1]
                hit = (lam > 1e-3) & (lam < best)
                best[hit], surface[hit] = lam[hit], which
        return best, surface

    def surface_points(self, which: int, s: np.ndarray, t: np.ndarray) -> np.ndarray:
        """World points (N, 3) at texture coordinates (metres) of surface ``which``
        (0 inner wall, 1 outer wall, 2 floor, 3 ceiling): the inverse of the texture mapping."""
        s, t = np.broadcast_arrays(np.asarray(s, float), np.asarray(t, float))
        cx, cz = self.centre
        if which in (0, 1):
            A, B = self.wall_axes(which)
            theta = s / (0.5 * (A + B))
            return np.stack([cx + A * np.cos(theta), t, cz + B * np.sin(theta)], axis=-1)
        y0 = self.floor_y if which == 2 else self.ceiling_y
        return np.stack([s, np.full_like(s, y0), t], axis=-1)


# --------------------------------------------------------------------------- trajectories


def _loop_point(theta: np.ndarray, lateral: np.ndarray | float = 0.0):
    """Position and unit tangent on the loop at parameter theta (ellipse), shifted sideways."""
    a, b = paper_scene.LOOP_SEMI_AXES_M
    c = paper_scene.LOOP_START
    p = np.stack([c[0] + a * (1 - np.cos(theta)), np.full_like(theta, c[1]),
                  c[2] + b * np.sin(theta)], axis=-1)  # fmt: skip
    tangent = np.stack([a * np.sin(theta), np.zeros_like(theta), b * np.cos(theta)], axis=-1)
    tangent /= np.linalg.norm(tangent, axis=-1, keepdims=True)
    normal = np.cross(tangent, [0.0, 1.0, 0.0])
    return p + np.asarray(lateral)[..., None] * normal, tangent


def _heading_rotation(tangent: np.ndarray) -> np.ndarray:
    """Camera looking along ``tangent`` with its y axis down: columns (x, y, z) in world."""
    z = tangent
    y = np.broadcast_to([0.0, 1.0, 0.0], z.shape)
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=-1)


@dataclass
class ShakeModel:
    """Sum-of-sines shaking: rotation vector (rad) and offset (m) as functions of time."""

    rot_amp: np.ndarray  # (k, 3) rad
    rot_freq: np.ndarray  # (k,) Hz
    rot_phase: np.ndarray  # (k, 3)
    pos_amp: np.ndarray  # (k, 3) m
    pos_freq: np.ndarray
    pos_phase: np.ndarray

    @staticmethod
    def create(motion: str, severity: float, rng: np.random.Generator) -> ShakeModel:
        if motion == "handheld":  # hand tremor and walking: 1-9 Hz, a few degrees
            rf = np.array([1.1, 2.3, 4.7, 8.9])
            ra = np.radians([1.5, 1.0, 0.6, 0.35])[:, None] * rng.uniform(0.6, 1.0, (4, 3))
            pf = np.array([1.8, 3.6, 0.9, 7.0])
            pa = np.array([[0.01, 0.03, 0.005], [0.004, 0.01, 0.003], [0.02, 0.01, 0.01],
                           [0.002, 0.003, 0.002]])  # fmt: skip
        else:  # vehicle: body pitch / roll / yaw on a rough road, 1-6 Hz (slower than a
            # frame's readout, so each frame's RS motion is close to constant velocity)
            rf = np.array([1.2, 2.6, 4.1, 5.9])
            ra = np.radians([1.0, 0.8, 0.6, 0.4])[:, None] * rng.uniform(0.6, 1.0, (4, 3))
            pf = np.array([1.2, 2.6, 4.1, 5.9])
            pa = np.array([[0.01, 0.02, 0.0], [0.005, 0.01, 0.0], [0.002, 0.006, 0.0],
                           [0.001, 0.003, 0.0]])  # fmt: skip
        return ShakeModel(severity * ra, rf, rng.uniform(0, 2 * np.pi, (4, 3)),
                          severity * pa, pf, rng.uniform(0, 2 * np.pi, (4, 3)))

    def rotation(self, t: np.ndarray) -> np.ndarray:
        arg = 2 * np.pi * self.rot_freq[None, :, None] * t[:, None, None] + self.rot_phase
        return np.sum(self.rot_amp[None] * np.sin(arg), axis=1)

    def offset(self, t: np.ndarray) -> np.ndarray:
        arg = 2 * np.pi * self.pos_freq[None, :, None] * t[:, None, None] + self.pos_phase
        return np.sum(self.pos_amp[None] * np.sin(arg), axis=1)


@dataclass
class ContinuousTrajectory:
    """Camera walking or driving along the loop with shaking; poses at any time."""

    speed: float
    shake: ShakeModel

    def pose(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``T_world_camera`` at times ``t`` (N,): R (N, 3, 3), p (N, 3)."""
        t = np.atleast_1d(np.asarray(t, float))
        a, b = paper_scene.LOOP_SEMI_AXES_M
        perimeter = np.pi * (3 * (a + b) - np.sqrt((3 * a + b) * (a + 3 * b)))  # Ramanujan
        theta = 2 * np.pi * self.speed * t / perimeter
        p, tangent = _loop_point(theta)
        R_heading = _heading_rotation(tangent)
        R = R_heading @ so3_exp(self.shake.rotation(t))
        p = p + np.einsum("nij,nj->ni", R_heading, self.shake.offset(t))
        return R, p

    def velocity(self, t: float, dt: float = 1e-5) -> tuple[np.ndarray, np.ndarray]:
        """Instantaneous (w, v) at ``t`` in the camera frame at ``t`` (central differences),
        i.e. the RS velocities of a frame whose row 0 is exposed at ``t``."""
        R, p = self.pose(np.array([t - dt, t, t + dt]))
        w = so3_log(R[0].T @ R[2]) / (2 * dt)
        v = R[1].T @ (p[2] - p[0]) / (2 * dt)
        return w, v


@dataclass
class WalkTrajectory:
    """A hand-held camera carried by a walking person along the loop; poses at any time.

    Speed 1 m/s (stopping for ``stop`` = (start, duration) s, where the camera pans: pure
    rotation), head bob (2.5 cm vertical at the 1.8 Hz step frequency, 2 cm sway at half of
    it, 1 deg of pitch), pans (``pans``: (time, yaw deg) smooth turns of 0.6 s) and hand shake
    ``ShakeModel``-like in two bands, scaled by ``severity``.
    """

    severity: float
    rng_phases: np.ndarray  # (6, 3) random phases
    pans: list[tuple[float, float]]
    stop: tuple[float, float] | None
    speed: float = 1.0
    _grid: np.ndarray | None = None
    _arc: np.ndarray | None = None

    @staticmethod
    def create(severity: float, rng: np.random.Generator, duration: float) -> WalkTrajectory:
        pans = []
        t = rng.uniform(0.8, 1.5)
        while t < duration - 0.6:
            pans.append((t, float(rng.choice([-1.0, 1.0]) * rng.uniform(15.0, 30.0))))
            t += rng.uniform(2.0, 3.5)
        stop = (0.45 * duration, min(2.0, 0.15 * duration)) if duration >= 8.0 else None
        return WalkTrajectory(severity, rng.uniform(0, 2 * np.pi, (6, 3)), pans, stop)

    def _speed(self, t: np.ndarray) -> np.ndarray:
        v = np.full_like(t, self.speed)
        if self.stop is not None:
            t0, dur = self.stop
            inside = (t > t0) & (t < t0 + dur)
            v[inside] *= 0.5 * (1 + np.cos(2 * np.pi * (t[inside] - t0) / dur))  # 1 -> 0 -> 1
        return v

    def _arc_length(self, t: np.ndarray) -> np.ndarray:
        if self._grid is None:
            self._grid = np.arange(-1.0, 600.0, 1e-3)
            self._arc = np.concatenate([[0.0], np.cumsum(self._speed(self._grid[:-1]) * 1e-3)])
        return np.interp(t, self._grid, self._arc)

    def _yaw(self, t: np.ndarray) -> np.ndarray:
        """Pans: smooth yaw steps (rad), and the look-around while stopped."""
        yaw = np.zeros_like(t)
        for t0, deg in self.pans:
            u = np.clip((t - t0) / 0.6, 0.0, 1.0)
            yaw += np.radians(deg) * (u - np.sin(2 * np.pi * u) / (2 * np.pi))
        if self.stop is not None:
            t0, dur = self.stop
            u = np.clip((t - t0) / dur, 0.0, 1.0)
            yaw += np.radians(40.0) * np.sin(2 * np.pi * u)  # look left and right, come back
        return yaw

    def pose(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``T_world_camera`` at times ``t`` (N,): R (N, 3, 3), p (N, 3)."""
        t = np.atleast_1d(np.asarray(t, float))
        a, b = paper_scene.LOOP_SEMI_AXES_M
        perimeter = np.pi * (3 * (a + b) - np.sqrt((3 * a + b) * (a + 3 * b)))
        theta = 2 * np.pi * self._arc_length(t) / perimeter
        p, tangent = _loop_point(theta)
        R_heading = _heading_rotation(tangent)
        ph = self.rng_phases
        walking = self._speed(t) / self.speed  # the bob fades when the person stops
        step = 2 * np.pi * 1.8 * t
        bob = np.stack([0.02 * np.sin(step / 2 + ph[0, 0]), 0.025 * np.sin(step + ph[0, 1]),
                        np.zeros_like(t)], axis=1) * walking[:, None]  # fmt: skip
        sev = self.severity
        rot = np.zeros((len(t), 3))
        rot[:, 0] += np.radians(1.0) * np.sin(step + ph[1, 0]) * walking  # pitch with the steps
        for band, (freqs, amp) in enumerate((((3.1, 4.3, 4.9), 0.8), ((8.3, 11.7, 14.6), 0.4))):
            for i, f in enumerate(freqs):
                rot[:, i] += sev * np.radians(amp) * np.sin(2 * np.pi * f * t + ph[2 + band, i])
        rot[:, 1] += self._yaw(t)
        pos_shake = sev * 0.004 * np.sin(2 * np.pi * np.array([3.7, 5.3, 4.1]) * t[:, None]
                                         + ph[4])  # fmt: skip
        R = R_heading @ so3_exp(rot)
        p = p + np.einsum("nij,nj->ni", R_heading, bob + pos_shake)
        return R, p

    velocity = ContinuousTrajectory.velocity


# --------------------------------------------------------------------------- sequences


@dataclass
class SynthConfig:
    """What to render. ``line_delay`` None: the paper's 36 ms readout at this height."""

    frames: int = 30
    motion: str = "handheld"
    level: int = 6  # paper motion only
    severity: float = 1.0  # handheld / vehicle only
    width: int = 640
    height: int = 360
    line_delay: float | None = None
    seed: int = 0
    lens: str = "none"  # "none" or a key of LENSES: the images are rendered through that lens
    # what real sensors add: each row integrates light for ``exposure`` s centred on its
    # readout time (motion blur; the ground truth stays the row's mid-exposure pose), rendered
    # as the mean of ``exposure_samples`` instants; then Gaussian noise of ``noise`` grey levels
    exposure: float = 0.0
    exposure_samples: int = 8
    noise: float = 0.0
    # auto exposure / gain: each frame's brightness times exp(gain_variation * g(t)), g a smooth
    # random signal of unit RMS (three sines of 0.2-1.5 Hz from the seed); before the noise,
    # clipped to 0-255 like a sensor's output
    gain_variation: float = 0.0
    # frames per second of the handheld / vehicle / walk motions (None: their 30 Hz); the same
    # continuous motion sampled at another rate (a 15 Hz robot camera, a 60 Hz drone camera);
    # then the default readout is the lesser of the paper's 36 ms and one frame interval
    frame_rate: float | None = None
    # people crossing or walking along in front of the camera (handheld / vehicle / walk):
    # this many pedestrian-sized textured panels (:class:`Mover`), spread over the sequence
    movers: int = 0

    def __post_init__(self):
        if self.lens != "none" and self.lens not in LENSES:
            raise ValueError(f"lens must be none or one of {sorted(LENSES)}, got {self.lens!r}")
        if self.motion not in MOTIONS:
            raise ValueError(f"motion must be one of {MOTIONS}, got {self.motion!r}")
        if self.level not in paper_scene.RS_LEVELS:
            raise ValueError(f"level must be 1-6, got {self.level}")
        if self.frames < 1:
            raise ValueError(f"frames must be >= 1, got {self.frames}")
        if self.width < 16 or self.height < 16:
            raise ValueError(f"resolution must be at least 16x16, got {self.width}x{self.height}")
        if self.line_delay is not None and not (0.0 <= self.line_delay < 1.0):
            raise ValueError(f"line delay must be in [0, 1) s/row, got {self.line_delay}")
        if not np.isfinite(self.severity) or self.severity < 0:
            raise ValueError(f"severity must be >= 0, got {self.severity}")
        if self.frame_rate is not None:
            if self.motion == "paper":
                raise ValueError("frame rate: the paper motion has its own "
                                 f"{paper_scene.FRAME_RATE_HZ:g} Hz loop")
            if not (np.isfinite(self.frame_rate) and 1.0 <= self.frame_rate <= 1000.0):
                raise ValueError(f"frame rate must be in [1, 1000] Hz, got {self.frame_rate}")
        if self.movers < 0 or self.movers and self.motion == "paper":
            raise ValueError(f"movers must be >= 0, and the paper motion has none, got "
                             f"{self.movers} with motion {self.motion}")
        if not (np.isfinite(self.exposure) and 0.0 <= self.exposure < 1.0 / self.rate_hz):
            raise ValueError(f"exposure must be in [0, {1.0 / self.rate_hz:g}) s (under one frame "
                             f"interval at {self.rate_hz:g} Hz), got {self.exposure}")
        if self.exposure_samples < 2:
            raise ValueError(f"exposure_samples must be >= 2, got {self.exposure_samples}")
        if not np.isfinite(self.noise) or self.noise < 0:
            raise ValueError(f"noise must be >= 0 grey levels, got {self.noise}")
        if not (np.isfinite(self.gain_variation) and 0.0 <= self.gain_variation <= 1.0):
            raise ValueError("gain variation must be in [0, 1] (log-gain RMS), got "
                             f"{self.gain_variation}")

    @property
    def tau(self) -> float:
        if self.line_delay is not None:
            return self.line_delay
        if self.frame_rate is not None:
            return min(REFERENCE_READOUT_S, 1.0 / self.frame_rate) / self.height
        return default_line_delay(self.height)

    @property
    def rate_hz(self) -> float:
        return FRAME_RATE_HZ[self.motion] if self.frame_rate is None else float(self.frame_rate)

    @property
    def lens_model(self) -> LensModel | None:
        return None if self.lens == "none" else LENSES[self.lens]


def pixel_rays(lens: LensModel, K: np.ndarray, width: int,
               height: int) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Normalized ``(x, y)`` (each (height, width)) of every raw pixel seen through ``lens``."""
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    und = lens.undistort(np.column_stack([u.ravel(), v.ravel()]), K)
    x = (und[:, 0] - K[0, 2]) / K[0, 0]
    y = (und[:, 1] - K[1, 2]) / K[1, 1]
    return x.reshape(height, width), y.reshape(height, width)


@dataclass
class Frame:
    """One rendered image and its ground truth (row-0 pose, RS velocities)."""

    index: int
    stamp: float  # s, row-0 exposure time
    image: np.ndarray  # uint8 (H, W)
    R_world_cam: np.ndarray
    p_world_cam: np.ndarray
    w: np.ndarray  # rad/s, row-0 camera frame
    v: np.ndarray  # m/s, row-0 camera frame
    row_pose: RowPoseFn  # rows (n,) -> T_world_camera of those rows

    def pose(self) -> np.ndarray:
        """(4, 4) row-0 ``T_world_camera``."""
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.R_world_cam, self.p_world_cam
        return T


class SequenceRenderer:
    """Renders the frames of a :class:`SynthConfig` one at a time (constant memory)."""

    def __init__(self, config: SynthConfig, scene: CorridorScene | None = None):
        self.config = config
        self.K = intrinsics(config.width, config.height)
        self.scene = scene or CorridorScene.create(config.seed)
        lens = config.lens_model
        self._rays = None if lens is None else pixel_rays(lens, self.K, config.width,
                                                          config.height)  # fmt: skip
        rng = np.random.default_rng([config.seed, 11])
        if config.motion == "paper":
            n_loop = max(config.frames, paper_scene.NUM_FRAMES)  # the paper's spacing, 250/loop
            self._loop = paper_scene.loop_trajectory(rng, n_loop, config.rate_hz)
            # the loop has its own small pose noise; keep the corridor's centre line
            self._rs = [paper_scene.random_rs_velocity(rng, config.level)
                        for _ in range(config.frames)]  # fmt: skip
            self._traj = None
        elif config.motion == "walk":
            self._traj = WalkTrajectory.create(config.severity, rng,
                                               config.frames / config.rate_hz)
        else:
            self._traj = ContinuousTrajectory(SPEED_M_S[config.motion],
                                              ShakeModel.create(config.motion, config.severity,
                                                                rng))  # fmt: skip
        self.movers = self._create_movers() if config.movers else []

    def _create_movers(self) -> list[Mover]:
        """``config.movers`` people, each in front of the camera (3-6 m ahead) at a time of
        its own spread over the sequence: alternately crossing the view (1.0-1.6 m/s across
        the camera's heading) and walking along it (towards or away, 0.8-1.5 m/s), facing the
        camera (from their own seed: the bag without movers is the same bag), and kept
        ``MOVER_CLEARANCE_M`` from the camera's path (:meth:`_keep_clear`)."""
        cfg = self.config
        rng = np.random.default_rng([cfg.seed, 23])
        duration = cfg.frames / cfg.rate_hz
        movers = []
        for i in range(cfg.movers):
            t0 = duration * (0.1 + 0.8 * (i + rng.uniform(0.2, 0.8)) / cfg.movers)
            R, p = self._traj.pose(np.array([t0]))
            forward = R[0][:, 2] * [1.0, 0.0, 1.0]
            forward /= np.linalg.norm(forward)
            right = np.cross([0.0, 1.0, 0.0], forward)  # the camera's x, horizontal
            half_height = 0.85
            centre = p[0] + rng.uniform(3.0, 6.0) * forward + rng.uniform(-0.5, 0.5) * right
            centre[1] = self.scene.floor_y - half_height  # standing on the floor (y down)
            if i % 2 == 0:
                velocity = rng.choice([-1.0, 1.0]) * rng.uniform(1.0, 1.6) * right
            else:
                velocity = rng.choice([-1.0, 1.0]) * rng.uniform(0.8, 1.5) * forward
            mover = Mover(centre, float(t0), velocity, -forward, 0.35, half_height,
                          texture_offset=2.0 * i)  # fmt: skip
            movers.append(self._keep_clear(mover, right, duration))
        return movers

    def _keep_clear(self, mover: Mover, right: np.ndarray, duration: float) -> Mover:
        """``mover`` shifted sideways (along ``right``, the camera's horizontal x at its ``t0``)
        by the least distance that keeps its path ``MOVER_CLEARANCE_M`` from the camera's
        over the sequence (a crossing person then crosses earlier or later); unchanged when it
        is clear already, or where no shift within 8 m clears it. Deterministic, no random
        draws: a bag whose people were clear is the same bag."""
        clearance = MOVER_CLEARANCE_M[self.config.motion]
        times = np.linspace(0.0, duration, max(2, int(np.ceil(duration * 100.0)) + 1))
        offsets = (mover.centres(times) - self._traj.pose(times)[1])[:, [0, 2]]
        side = right[[0, 2]]
        if np.min(np.linalg.norm(offsets, axis=1)) >= clearance:
            return mover
        for step in sorted(range(-160, 161), key=lambda k: (abs(k), k)):  # 5 cm steps, 8 m
            shift = 0.05 * step
            if np.min(np.linalg.norm(offsets + shift * side, axis=1)) >= clearance:
                return replace(mover, centre0=mover.centre0 + shift * right)
        return mover

    @property
    def trajectory(self) -> ContinuousTrajectory | WalkTrajectory | None:
        """The continuous camera trajectory (``pose(t)``, ``velocity(t)``); None for the paper
        motion, whose frames are drawn one by one."""
        return self._traj

    def frame_pose(self, k: int) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                          RowPoseFn]:  # fmt: skip
        cfg = self.config
        stamp = k / cfg.rate_hz
        tau = cfg.tau
        if self._traj is None:
            R0, p0 = self._loop.R_world_cam[k], self._loop.p_world_cam[k]
            w, v = self._rs[k]

            def row_pose(rows, dt=0.0, R0=R0, p0=p0, w=w, v=v):
                s = np.asarray(rows, float) * tau + dt
                return R0 @ so3_exp(s[:, None] * w), p0 + (s[:, None] * v) @ R0.T

            return stamp, R0, p0, w, v, row_pose
        R0, p0 = self._traj.pose(np.array([stamp]))
        w, v = self._traj.velocity(stamp)

        def row_pose(rows, dt=0.0, stamp=stamp):
            return self._traj.pose(stamp + np.asarray(rows, float) * tau + dt)

        return stamp, R0[0], p0[0], w, v, row_pose

    def readout_turn_rate(self, k: int) -> np.ndarray:
        """The constant turn rate (rad/s, row-0 camera frame) that takes frame ``k``'s row-0
        camera to its last row's: the mean over the readout, what a frame's single ``w``
        (the paper's constant velocity within a frame) can represent. Under shake faster than
        the readout it differs from the instantaneous row-0 ``w`` of the ground truth."""
        cfg = self.config
        _, R0, _, w, _, row_pose = self.frame_pose(k)
        readout = (cfg.height - 1) * cfg.tau
        if readout <= 0:
            return w
        R_last = row_pose(np.array([cfg.height - 1.0]))[0]
        return so3_log(R0.T @ np.asarray(R_last).reshape(3, 3)) / readout

    def gain(self, k: int) -> float:
        """Frame ``k``'s brightness gain (``SynthConfig.gain_variation``; 1 without)."""
        cfg = self.config
        if cfg.gain_variation <= 0:
            return 1.0
        rng = np.random.default_rng([cfg.seed, 17])
        freq, phase = rng.uniform(0.2, 1.5, 3), rng.uniform(0.0, 2 * np.pi, 3)
        g = np.sum(np.sin(2 * np.pi * freq * k / cfg.rate_hz + phase)) / np.sqrt(1.5)
        return float(np.exp(cfg.gain_variation * g))

    def render(self, k: int) -> Frame:
        cfg = self.config
        stamp, R0, p0, w, v, row_pose = self.frame_pose(k)
        rows = np.arange(cfg.height)
        if cfg.exposure > 0:  # motion blur: the mean over instants spread over the exposure
            n = cfg.exposure_samples
            img = np.zeros((cfg.height, cfg.width), np.float32)
            for dt in cfg.exposure * ((np.arange(n) + 0.5) / n - 0.5):
                img += self.scene.radiance(*row_pose(rows, dt), self.K, cfg.width, cfg.height,
                                           self._rays, self.movers,
                                           stamp + rows * cfg.tau + dt)  # fmt: skip
            img /= n
        else:
            img = self.scene.radiance(*row_pose(rows), self.K, cfg.width, cfg.height,
                                      self._rays, self.movers,
                                      stamp + rows * cfg.tau)  # fmt: skip
        if cfg.gain_variation > 0:
            img = img * np.float32(self.gain(k))
        if cfg.noise > 0:  # per frame, from the seed: the same bag every time
            rng = np.random.default_rng([cfg.seed, 13, k])
            img = img + rng.normal(0.0, cfg.noise, img.shape).astype(np.float32)
        return Frame(k, stamp, to_uint8(img), R0, p0, w, v, row_pose)

    def __iter__(self) -> Iterator[Frame]:
        for k in range(self.config.frames):
            yield self.render(k)


def render_sequence(config: SynthConfig) -> list[Frame]:
    """All frames in memory (tests and small sequences)."""
    return list(SequenceRenderer(config))


def project_points(X_world: np.ndarray, row_pose: RowPoseFn, K: np.ndarray, height: int,
                   iterations: int = 50, tol_px: float = 1e-6) -> np.ndarray:
    """Exact RS projection of (N, 3) world points through a frame's per-row poses
    (:func:`rsvo_ros.core.geometry.project_rs_rows`): (N, 2) pixels, nan where a point is behind
    the camera, outside the rows, or the fixed-point iteration on the row did not settle."""
    return project_rs_rows(X_world, row_pose, K, height, iterations, tol_px)[0]
