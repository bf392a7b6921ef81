"""Re-finding the map: descriptors of the keyframes' tracks, a memory of the world points the
window placed, and a frame's pose from matches against that memory.

KLT keeps a point only while it stays in view: when a hand-held camera looks away and back (a
walker who stops and looks around), every track of the old map is gone, and the map that the
pair estimator rebuilds from the few millimetres the walker moved meanwhile has another scale
(docs/notebook.md, "Turning on the spot"). So each keyframe's tracks get ORB descriptors
(binary, computed at the tracked corners, not detected anew), every window BA writes its
landmarks' world points into a bounded memory, and a frame that the window cannot track
matches its own tracks' descriptors against the memory (Hamming distance, Lowe's ratio test),
poses itself by PnP in RANSAC (a global-shutter model: its inliers then go through the
motion-only RS refinement of tracking) and so finds the old map, its world and its scale
again. Pure numpy + OpenCV.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

ORB_PATCH_PX = 31  # ORB's patch (and keypoint size) at the full resolution
DESCRIPTOR_BYTES = 32
_LOCAL = threading.local()


def describe(gray: np.ndarray, raw_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ORB descriptors (n, 32) uint8 of the image ``gray`` at the raw pixels ``raw_px`` (n, 2)
    (the tracked corners, at full resolution), and which points have one (n,) (ORB leaves
    out points within about half a patch of the border)."""
    n = len(raw_px)
    desc = np.zeros((n, DESCRIPTOR_BYTES), np.uint8)
    valid = np.zeros(n, bool)
    if not n:
        return desc, valid
    orb = getattr(_LOCAL, "orb", None)
    if orb is None:  # one per thread (tracking and mapping may both describe)
        orb = _LOCAL.orb = cv2.ORB_create(nlevels=1, edgeThreshold=ORB_PATCH_PX,
                                          patchSize=ORB_PATCH_PX)  # fmt: skip
    kps = [cv2.KeyPoint(float(x), float(y), ORB_PATCH_PX, -1, 0, 0, i)
           for i, (x, y) in enumerate(np.asarray(raw_px, float))]  # fmt: skip
    kept, d = orb.compute(gray, kps)
    if d is None or not kept:
        return desc, valid
    idx = np.array([k.class_id for k in kept], np.int64)
    desc[idx] = d
    valid[idx] = True
    return desc, valid


class LandmarkMemory:
    """World points of landmarks (by track id) with a descriptor each, the most recently
    updated ``capacity`` kept. Thread-safe (the mapping thread writes, tracking reads)."""

    def __init__(self, capacity: int = 5000):
        self.capacity = int(capacity)
        self._lock = threading.Lock()
        self.ids = np.zeros(0, np.int64)
        self.X = np.zeros((0, 3))
        self.desc = np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
        self._age = np.zeros(0, np.int64)  # the update that last wrote each entry
        self._updates = 0

    def __len__(self) -> int:
        return len(self.ids)

    def update(self, ids: np.ndarray, X: np.ndarray, desc: np.ndarray) -> None:
        """Insert or overwrite the entries ``ids`` (m,) with world points ``X`` (m, 3) and
        descriptors ``desc`` (m, 32); then drop the least recently written beyond capacity."""
        ids = np.asarray(ids, np.int64)
        if not len(ids):
            return
        with self._lock:
            self._updates += 1
            keep = ~np.isin(self.ids, ids)
            self.ids = np.concatenate([self.ids[keep], ids])
            self.X = np.concatenate([self.X[keep], np.asarray(X, float)])
            self.desc = np.concatenate([self.desc[keep], np.asarray(desc, np.uint8)])
            self._age = np.concatenate([self._age[keep], np.full(len(ids), self._updates)])
            if len(self.ids) > self.capacity:
                newest = np.argsort(-self._age, kind="stable")[:self.capacity]
                newest.sort()
                self.ids, self.X = self.ids[newest], self.X[newest]
                self.desc, self._age = self.desc[newest], self._age[newest]

    def known(self, ids: np.ndarray) -> np.ndarray:
        """(m,) bool: which of ``ids`` the memory holds (without copying its points)."""
        with self._lock:
            return np.isin(np.asarray(ids, np.int64), self.ids)

    def snapshot(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Copies of ``(ids, X, desc)``."""
        with self._lock:
            return self.ids.copy(), self.X.copy(), self.desc.copy()

    def clear(self) -> None:
        with self._lock:
            self.ids = np.zeros(0, np.int64)
            self.X = np.zeros((0, 3))
            self.desc = np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
            self._age = np.zeros(0, np.int64)


@dataclass
class Match:
    """A frame posed against the memory: its reference-row camera ``R``, ``p`` (world from
    camera, a global-shutter PnP), and the frame's observations ``obs_idx`` (m,) that matched
    the memory's rows ``mem_idx`` (m,), world points ``X`` (m, 3), as PnP inliers."""

    R: np.ndarray
    p: np.ndarray
    obs_idx: np.ndarray
    X: np.ndarray
    mem_idx: np.ndarray


def match_memory(memory: tuple[np.ndarray, np.ndarray, np.ndarray], x: np.ndarray,
                 desc: np.ndarray, valid: np.ndarray, focal: float, ratio: float,
                 max_hamming: int, ransac_px: float, min_inliers: int,
                 seed: int = 0) -> Match | None:  # fmt: skip
    """Pose a frame whose observations have normalized coordinates ``x`` (n, 2) and
    descriptors ``desc`` (n, 32) (``valid`` (n,)) against ``memory`` (:meth:`LandmarkMemory.
    snapshot`): nearest memory descriptor per observation by Hamming distance, kept if under
    ``max_hamming`` and under ``ratio`` x the second nearest, one observation per memory entry;
    then PnP in RANSAC (reprojection threshold ``ransac_px`` at ``focal``). None with fewer
    than ``min_inliers`` inliers."""
    _, X_mem, d_mem = memory
    q = np.flatnonzero(valid)
    if len(q) < min_inliers or len(X_mem) < min_inliers:
        return None
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    pairs = matcher.knnMatch(desc[q], d_mem, k=2)
    best: dict[int, tuple[int, float]] = {}  # memory entry -> (observation, distance)
    for m in pairs:
        if len(m) < 2 or m[0].distance > max_hamming or m[0].distance >= ratio * m[1].distance:
            continue
        j = m[0].trainIdx
        if j not in best or m[0].distance < best[j][1]:
            best[j] = (int(q[m[0].queryIdx]), m[0].distance)
    if len(best) < min_inliers:
        return None
    mem_idx = np.fromiter(best, np.int64, len(best))
    obs_idx = np.array([best[j][0] for j in mem_idx.tolist()], np.int64)
    cv2.setRNGSeed(int(seed))
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        X_mem[mem_idx].astype(np.float64), x[obs_idx].astype(np.float64), np.eye(3), None,
        iterationsCount=300, reprojectionError=ransac_px / focal, confidence=0.999,
        flags=cv2.SOLVEPNP_AP3P)  # fmt: skip
    if not ok or inl is None or len(inl) < min_inliers:
        return None
    inl = inl.ravel()
    R_cw = cv2.Rodrigues(rvec)[0]
    R_wc = np.ascontiguousarray(R_cw.T)
    p_wc = -R_wc @ tvec.ravel()
    if not (np.isfinite(R_wc).all() and np.isfinite(p_wc).all()):
        return None
    return Match(R_wc, p_wc, obs_idx[inl], X_mem[mem_idx[inl]], mem_idx[inl])


def guided_matches(found: Match, memory: tuple[np.ndarray, np.ndarray, np.ndarray],
                   x: np.ndarray, desc: np.ndarray, valid: np.ndarray, focal: float,
                   radius_px: float, max_hamming: int) -> Match:  # fmt: skip
    """More matches for a frame posed by :func:`match_memory`: every memory point that the
    pose projects in front of the camera and within ``radius_px`` of an observation not
    matched yet, whose descriptors differ by under ``max_hamming`` bits (no ratio test: the
    pose has done the choosing), the nearest in descriptor distance, one each way. ORB-SLAM's
    search by projection; the ratio test over the whole memory keeps a third of the points a
    view shares with it, or fewer."""
    _, X_mem, d_mem = memory
    Xc = (X_mem - found.p) @ found.R  # the memory in the camera (R^T (X - p))
    front = Xc[:, 2] > 1e-6
    taken_obs = np.zeros(len(x), bool)
    taken_obs[found.obs_idx] = True
    in_found = np.zeros(len(X_mem), bool)
    in_found[found.mem_idx] = True
    cand = np.flatnonzero(front & ~in_found)
    free = np.flatnonzero(valid & ~taken_obs)
    if not len(cand) or not len(free):
        return found
    proj = Xc[cand, :2] / Xc[cand, 2:]
    near_f, near_c = _pairs_within(x[free], proj, radius_px, focal)
    if not len(near_f):
        return found
    # Hamming distances of the near pairs only
    bits = np.unpackbits(desc[free[near_f]] ^ d_mem[cand[near_c]], axis=1).sum(axis=1)
    ok = bits < max_hamming
    near_f, near_c, bits = near_f[ok], near_c[ok], bits[ok]
    order = np.argsort(bits, kind="stable")
    used_f, used_c, add_obs, add_mem = set(), set(), [], []
    for k in order.tolist():
        f, c = int(near_f[k]), int(near_c[k])
        if f in used_f or c in used_c:
            continue
        used_f.add(f)
        used_c.add(c)
        add_obs.append(free[f])
        add_mem.append(cand[c])
    if not add_obs:
        return found
    add_mem = np.array(add_mem, np.int64)
    return Match(found.R, found.p, np.concatenate([found.obs_idx, np.array(add_obs, np.int64)]),
                 np.concatenate([found.X, X_mem[add_mem]]),
                 np.concatenate([found.mem_idx, add_mem]))


def _pairs_within(a: np.ndarray, b: np.ndarray, radius_px: float,
                  focal: float) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Indices ``(i, j)`` of the pairs of normalized points ``a[i]`` (n, 2), ``b[j]`` (m, 2)
    closer than ``radius_px`` pixels at ``focal`` (strictly), in row-major order of ``(i, j)``:
    the pairs a dense (n, m) distance matrix gives, to the bit, found with a k-d tree (the
    memory holds thousands of points; the dense matrix took 8-16 ms per re-finding at
    1280x720)."""
    none = np.zeros(0, np.int64), np.zeros(0, np.int64)
    # (a non-finite point is never near; the tree refuses them)
    ok_a = np.flatnonzero(np.isfinite(a).all(axis=1))
    ok_b = np.flatnonzero(np.isfinite(b).all(axis=1))
    if not len(ok_a) or not len(ok_b) or not radius_px > 0:
        return none
    # candidates from the tree (a little wider), then the dense matrix's test on them
    tree = cKDTree(b[ok_b])
    near = tree.query_ball_point(a[ok_a], radius_px / focal * (1.0 + 1e-6), return_sorted=True)
    counts = np.fromiter((len(n) for n in near), np.int64, len(near))
    if not counts.sum():
        return none
    i = np.repeat(ok_a, counts)
    j = ok_b[np.concatenate([np.asarray(n, np.int64) for n in near if len(n)])]
    d2 = ((a[i] - b[j]) ** 2).sum(axis=1) * focal**2
    keep = d2 < radius_px**2
    return i[keep], j[keep]
