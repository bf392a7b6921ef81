"""Pictures of a frame's result, shared by the node's debug image and the replay's video.

Pure numpy and OpenCV (no ROS): a BGR array the callers wrap as they need.
"""

from __future__ import annotations

import cv2
import numpy as np

from rsvo_ros.odometry.pipeline import FrameResult

INLIER_BGR = (0, 200, 0)
OUTLIER_BGR = (0, 0, 255)
UNUSED_BGR = (160, 160, 160)  # window tracking: a track with no map point yet
TEXT_BGR = (255, 255, 0)


def draw_tracks(gray: np.ndarray, res: FrameResult) -> np.ndarray:
    """(H, W, 3) uint8 BGR: the frame with its tracks as in the paper's Fig. 1, inliers green,
    outliers red, each with its displacement from the previous frame (window tracking: grey
    for tracks with no map point yet), and the status and inlier ratio written on it."""
    img = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    if res.pts_prev is not None and res.pts_curr is not None:
        n = len(res.pts_curr)
        inl = res.inliers
        if inl is None or len(inl) != n:
            rel = res.relative
            inl = rel.inliers if rel is not None and len(rel.inliers) == n else np.zeros(n, bool)
        rejected = res.outliers if res.outliers is not None and len(res.outliers) == n else ~inl
        for p0, p1, ok, bad in zip(res.pts_prev, res.pts_curr, inl, rejected, strict=True):
            color = INLIER_BGR if ok else OUTLIER_BGR if bad else UNUSED_BGR
            a = (int(round(p0[0])), int(round(p0[1])))
            b = (int(round(p1[0])), int(round(p1[1])))
            cv2.line(img, a, b, color, 1)
            cv2.circle(img, b, 2, color, -1)
    text = f"{res.status} inliers {100 * res.inlier_ratio:.0f}%"
    if res.keyframe:
        text += " keyframe"
    cv2.putText(img, text, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, TEXT_BGR, 1)
    if res.status != "posed" and res.reason:
        cv2.putText(img, res.reason[:80], (8, 40), cv2.FONT_HERSHEY_SIMPLEX, 0.4, TEXT_BGR, 1)
    return img
