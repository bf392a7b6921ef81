"""Global-shutter two-view geometry: the GS baselines and the GS fits the RS search starts from.

OpenCV's 5-point RANSAC/USAC, the paper's normalized 8-point MVO baseline, the decomposition of
an essential matrix by cheirality, Sampson distances, and the rotation-only fit that measures
the translation parallax. Convention: ``X_curr = R X_prev + t``, ``x_curr^T E x_prev = 0`` with
``E = [t]x R``, on normalized points.
"""

from __future__ import annotations

import cv2
import numpy as np

from rsvo_ros.twoview import kernels
from rsvo_ros.twoview.solver import depths
from rsvo_ros.twoview.state import Correspondences, RSBatch

MIN_POINTS_GS = 5  # the 5-point solver
CHEIRALITY_VOTERS = 100  # inliers that choose among the four decompositions of E
ROTATION_VOTERS = 100  # points that rank the rotation-only hypotheses


def sampson_gs_px(E: np.ndarray, x_prev: np.ndarray, x_curr: np.ndarray, focal: float):
    """Sampson distances (…, N) of normalized points for (…, 3, 3) essential matrices."""
    Ex = x_prev @ np.swapaxes(E, -1, -2)  # (…, N, 3): E x_p
    ETx = x_curr @ E  # E^T x_c
    num = np.einsum("...ni,ni->...n", Ex, x_curr)
    den = Ex[..., 0] ** 2 + Ex[..., 1] ** 2 + ETx[..., 0] ** 2 + ETx[..., 1] ** 2
    return focal * np.abs(num) / np.sqrt(np.maximum(den, 1e-300))


def pose_from_essential(
    E: np.ndarray, x_prev: np.ndarray, x_curr: np.ndarray, mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray, int]:
    """The decomposition of ``E = [t]x R`` (Hartley & Zisserman, Result 9.19: two rotations
    times the two signs of ``t``) that puts most of the ``mask``'s points in front of both
    cameras (what OpenCV's recoverPose does, in a quarter of its time). Returns R, t (unit)
    and the number of points in front, or identity, zero and 0."""
    if mask.sum() < MIN_POINTS_GS:
        return np.eye(3), np.zeros(3), 0
    U, _, Vt = np.linalg.svd(E)
    U = U * np.sign(np.linalg.det(U))  # proper rotations; E only matters up to sign
    Vt = Vt * np.sign(np.linalg.det(Vt))
    W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    Rs = np.stack([U @ W @ Vt, U @ W.T @ Vt] * 2)
    ts = np.stack([U[:, 2], U[:, 2], -U[:, 2], -U[:, 2]])
    # depths of the four candidates (4, n); at most CHEIRALITY_VOTERS evenly spread inliers vote
    voters = np.flatnonzero(mask)
    count = min(len(voters), CHEIRALITY_VOTERS)
    voters = voters[np.linspace(0, len(voters) - 1, count).astype(int)]
    zeros = np.zeros(len(voters))
    lam_p, lam_c = depths(RSBatch.from_pose(Rs, ts),
                          Correspondences(x_prev[voters], x_curr[voters], zeros, zeros, 1.0))
    front = np.count_nonzero((lam_p > 0) & (lam_c > 0), axis=1)
    k = int(np.argmax(front))
    if front[k] == 0:
        return np.eye(3), np.zeros(3), 0
    return Rs[k], ts[k], int(front[k])


def estimate_gs_opencv(corr: Correspondences, threshold_px: float, confidence: float,
                        max_iterations: int, seed: int, method: int = cv2.RANSAC,
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:  # fmt: skip
    """OpenCV's 5-point RANSAC (``method``: ``cv2.RANSAC``, or a USAC variant, whose own
    generator is seeded by OpenCV), then the decomposition by cheirality.

    The points go to OpenCV in pixel units (``focal * x``, with ``K = diag(focal, focal, 1)``):
    USAC's scoring and local optimisation work at that scale (on normalized coordinates
    USAC_MAGSAC lost a third of the inliers of one real pair and its rotation was 1.2 deg off).
    Returns R, t, mask, n and OpenCV's E (USAC's is not always on the essential manifold)."""
    cv2.setRNGSeed(int(seed))
    f = corr.focal
    p = np.ascontiguousarray(corr.x_prev[:, :2] * f)
    c = np.ascontiguousarray(corr.x_curr[:, :2] * f)
    E, mask = cv2.findEssentialMat(
        p, c, np.diag([f, f, 1.0]), method=method, prob=confidence, threshold=threshold_px,
        maxIters=max_iterations,
    )  # fmt: skip
    if E is None or E.shape[0] < 3:
        return np.eye(3), np.zeros(3), np.zeros(len(corr), bool), 0, np.zeros((3, 3))
    E = E[:3]
    mask = mask.ravel().astype(bool)
    R, t, _ = pose_from_essential(E, corr.x_prev, corr.x_curr, mask)
    return R, t, mask, max_iterations, E


def normalized_eight_point(x_prev: np.ndarray, x_curr: np.ndarray) -> np.ndarray:
    """Batched normalized 8-point essential matrices (Hartley), (S, 8, 3) inputs -> (S, 3, 3)."""

    def normalize(x):
        mean = x[..., :2].mean(axis=-2, keepdims=True)
        d = np.linalg.norm(x[..., :2] - mean, axis=-1).mean(axis=-1)
        s = np.sqrt(2.0) / np.maximum(d, 1e-300)
        T = np.zeros(x.shape[:-2] + (3, 3))
        T[..., 0, 0] = s
        T[..., 1, 1] = s
        T[..., 0, 2] = -s * mean[..., 0, 0]
        T[..., 1, 2] = -s * mean[..., 0, 1]
        T[..., 2, 2] = 1.0
        return x @ np.swapaxes(T, -1, -2), T

    xp, Tp = normalize(x_prev)
    xc, Tc = normalize(x_curr)
    A = (xc[..., :, None] * xp[..., None, :]).reshape(xp.shape[:-1] + (9,))  # x_c^T E x_p
    _, _, Vt = np.linalg.svd(A)
    E = Vt[..., -1, :].reshape(xp.shape[:-2] + (3, 3))
    E = np.swapaxes(Tc, -1, -2) @ E @ Tp  # back to normalized camera coordinates
    U, _, Vt = np.linalg.svd(E)
    return U @ (np.array([1.0, 1.0, 0.0])[:, None] * Vt)  # closest essential matrix


def estimate_mvo(corr: Correspondences, threshold_px: float, confidence: float,
                  max_iterations: int, rng: np.random.Generator):
    """The paper's MVO baseline: normalized 8-point in RANSAC, then pose by cheirality."""
    n = len(corr)
    best_mask, best_count, iters, batch = None, -1, 0, 50
    needed = max_iterations
    while iters < min(needed, max_iterations):
        idx = np.argsort(rng.random((batch, n)), axis=1)[:, :8]
        E = normalized_eight_point(corr.x_prev[idx], corr.x_curr[idx])
        d = sampson_gs_px(E, corr.x_prev, corr.x_curr, corr.focal)  # (batch, n)
        counts = (d < threshold_px).sum(axis=1)
        k = int(np.argmax(counts))
        if counts[k] > best_count:
            best_count, best_mask = int(counts[k]), d[k] < threshold_px
            ratio = max(best_count / n, 1e-9)
            needed = np.log(1 - confidence) / np.log(max(1 - ratio**8, 1e-12))
        iters += batch
    if best_count < 8:
        return np.eye(3), np.zeros(3), np.zeros(n, bool), iters
    E = normalized_eight_point(corr.x_prev[best_mask][None], corr.x_curr[best_mask][None])[0]
    mask = sampson_gs_px(E, corr.x_prev, corr.x_curr, corr.focal) < threshold_px
    R, t, _ = pose_from_essential(E, corr.x_prev, corr.x_curr, mask)
    return R, t, mask, iters


def essential(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return tx @ R


def rotation_only_residual_px(corr: Correspondences, rng: np.random.Generator,
                               hypotheses: int = 16) -> tuple[float, np.ndarray]:
    """Median image distance (px) left by the best rotation-only motion (2-point RANSAC +
    refit): what a camera that only rotates cannot explain, i.e. the translation parallax.
    Returns it and that rotation (compiled: :func:`rsvo_ros.twoview.kernels.rotation_only_fit`;
    the hypotheses are ranked on ``ROTATION_VOTERS`` evenly spread points, the two refits on
    the better half of all points)."""
    b_p = corr.x_prev / np.linalg.norm(corr.x_prev, axis=1, keepdims=True)
    b_c = corr.x_curr / np.linalg.norm(corr.x_curr, axis=1, keepdims=True)
    n = len(corr)
    voters = np.linspace(0, n - 1, min(n, ROTATION_VOTERS)).astype(np.int64)
    med, R = kernels.rotation_only_fit(b_p, b_c, np.ascontiguousarray(corr.x_curr),
                                       float(corr.focal), rng.random((hypotheses, n)), voters)
    return float(med), R
