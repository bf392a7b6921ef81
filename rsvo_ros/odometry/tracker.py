"""Feature tracking for the frame-pair pipeline: bucketed corners, pyramidal KLT with a
forward-backward check, re-detection where tracks thin out.

Pure numpy + OpenCV, no ROS.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

DEFAULT_MAX_FEATURES = 500  # paper, Sec. 7.1: "limited up to 500 with a bucketing strategy"


@dataclass
class TrackerOptions:
    max_features: int = DEFAULT_MAX_FEATURES
    grid: tuple[int, int] = (8, 6)  # bucketing cells (columns, rows)
    quality_level: float = 0.01  # goodFeaturesToTrack, relative to the best corner
    min_distance_px: float = 8.0
    window_px: int = 21  # KLT window
    pyramid_levels: int = 3
    fb_threshold_px: float = 1.0  # forward-backward consistency
    redetect_fraction: float = 0.8  # top up when fewer than this share of max_features remain


@dataclass
class TrackedPair:
    """Correspondences of the previous and current frame (raw, distorted pixels) and ids."""

    pts_prev: np.ndarray  # (N, 2)
    pts_curr: np.ndarray  # (N, 2)
    ids: np.ndarray  # (N,) int track ids


class FeatureTracker:
    """Tracks corners from frame to frame; call :meth:`track` with each new gray image."""

    def __init__(self, options: TrackerOptions | None = None):
        self.options = options or TrackerOptions()
        self._prev_img: np.ndarray | None = None
        self._pts = np.zeros((0, 2), np.float32)
        self._ids = np.zeros(0, np.int64)
        self._next_id = 0

    def reset(self) -> None:
        self._prev_img = None
        self._pts = np.zeros((0, 2), np.float32)
        self._ids = np.zeros(0, np.int64)

    @property
    def num_tracks(self) -> int:
        return len(self._pts)

    def current(self) -> tuple[np.ndarray, np.ndarray]:
        """Ids (n,) and raw pixels (n, 2) of every feature of the last image (tracked ones and
        the corners detected in it)."""
        return self._ids.copy(), self._pts.astype(float)

    def track(self, img: np.ndarray) -> TrackedPair:
        """Track the current features into ``img`` (uint8 gray), then top up by detection.

        Returns the correspondences that survived KLT and the forward-backward check (empty for
        the first frame or a changed image size).
        """
        o = self.options
        empty = TrackedPair(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, np.int64))
        if self._prev_img is None or self._prev_img.shape != img.shape or not len(self._pts):
            pair = empty
            self._pts = np.zeros((0, 2), np.float32)
            self._ids = np.zeros(0, np.int64)
        else:
            lk = dict(winSize=(o.window_px, o.window_px), maxLevel=o.pyramid_levels,
                      criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
            p0 = self._pts.reshape(-1, 1, 2)
            p1, st1, _ = cv2.calcOpticalFlowPyrLK(self._prev_img, img, p0, None, **lk)
            p0b, st2, _ = cv2.calcOpticalFlowPyrLK(img, self._prev_img, p1, None, **lk)
            fb = np.linalg.norm((p0b - p0).reshape(-1, 2), axis=1)
            h, w = img.shape
            p1f = p1.reshape(-1, 2)
            good = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < o.fb_threshold_px)
            good &= np.isfinite(p1f).all(axis=1)
            good &= (p1f[:, 0] >= 0) & (p1f[:, 0] <= w - 1) & (p1f[:, 1] >= 0)
            good &= p1f[:, 1] <= h - 1
            pair = TrackedPair(self._pts[good].astype(float), p1f[good].astype(float),
                               self._ids[good].copy())  # fmt: skip
            self._pts = p1f[good].astype(np.float32)
            self._ids = self._ids[good]
        if len(self._pts) < o.redetect_fraction * o.max_features:
            self._detect(img)
        self._prev_img = img
        return pair

    def _detect(self, img: np.ndarray) -> None:
        """Add corners in grid cells with fewer than their share of tracks."""
        o = self.options
        h, w = img.shape
        cols, rows = o.grid
        per_cell = max(1, int(np.ceil(o.max_features / (cols * rows))))
        mask = np.full((h, w), 255, np.uint8)
        for x, y in self._pts:
            cv2.circle(mask, (int(x), int(y)), int(o.min_distance_px), 0, -1)
        cx = np.clip((self._pts[:, 0] * cols / w).astype(int), 0, cols - 1)
        cy = np.clip((self._pts[:, 1] * rows / h).astype(int), 0, rows - 1)
        counts = np.zeros((rows, cols), int)
        np.add.at(counts, (cy, cx), 1)
        new = []
        budget = o.max_features - len(self._pts)
        for r in range(rows):
            for c in range(cols):
                need = min(per_cell - counts[r, c], budget - sum(len(n) for n in new))
                if need <= 0:
                    continue
                x0, x1 = c * w // cols, (c + 1) * w // cols
                y0, y1 = r * h // rows, (r + 1) * h // rows
                corners = cv2.goodFeaturesToTrack(img[y0:y1, x0:x1], need, o.quality_level,
                                                  o.min_distance_px, mask=mask[y0:y1, x0:x1])
                if corners is not None:
                    new.append(corners.reshape(-1, 2) + [x0, y0])
        if new:
            pts = np.concatenate(new).astype(np.float32)
            self._pts = np.concatenate([self._pts, pts])
            self._ids = np.concatenate([self._ids,
                                        np.arange(self._next_id, self._next_id + len(pts))])
            self._next_id += len(pts)
