"""Shared fixtures and the one table of test tolerances."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:  # the checkout is what we test
    sys.path.insert(0, str(REPO_ROOT))

# Every numeric tolerance of the suite, in one place (kornia / evo style).
TOL = {
    "jacobian_rel": 1e-5,  # analytic vs central finite differences, relative to column scale
    "gt_residual_px": 1e-8,  # Sampson error of the ground-truth parameters, noise-free
    "kernel_vs_numpy": 1e-9,  # compiled kernels vs the numpy model, relative to the scale
    "roundtrip": 1e-9,  # exp/log, row re-expression round trips
    "rs_projection_px": 1e-6,  # fixed-point RS projection: row consistency
    "noise_free_rot_deg": 0.05,  # RS estimator on exact RS correspondences it converges on
    "gs_data_rot_deg": 0.05,  # any model on exact global-shutter correspondences
    "gs_data_tdir_deg": 0.5,
}


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def paper_scene():
    from rsvo_ros.sim.paper_scene import PaperScene

    return PaperScene(seed=0)


def colcon_build(workspace: Path) -> tuple[subprocess.CompletedProcess, Path]:
    """Copy the checkout to ``workspace/src/rsvo_ros`` and ``colcon build`` it there.

    Returns the colcon process and ``install/rsvo_ros``.
    """
    import shutil

    src = workspace / "src" / "rsvo_ros"
    src.parent.mkdir(parents=True, exist_ok=True)
    shutil.copytree(REPO_ROOT, src, ignore=shutil.ignore_patterns(
        ".venv", ".git", "build", "install", "log", "results", "__pycache__", "*.egg-info",
        ".pytest_cache", ".ruff_cache", "docs"))
    colcon = shutil.which("colcon") or str(Path(sys.executable).parent / "colcon")
    proc = subprocess.run([colcon, "build", "--base-paths", "src", "--event-handlers",
                           "console_direct-"], cwd=workspace, capture_output=True, text=True,
                          timeout=600)  # fmt: skip
    return proc, workspace / "install" / "rsvo_ros"


def copy_compiled_kernels(install: Path) -> int:
    """Copy the checkout's numba cache (``rsvo_ros/**/__pycache__/*.nbi, *.nbc``) into an
    installed copy of the package; numba keys it by the source file's content, so the
    install's identical sources take it. Returns the number of files copied."""
    import shutil

    site = next(install.glob("lib/python3*/site-packages"))
    copied = 0
    for f in (REPO_ROOT / "rsvo_ros").glob("**/__pycache__/*.nb[ic]"):
        dest = site / f.relative_to(REPO_ROOT)
        if dest.parent.parent.is_dir():
            dest.parent.mkdir(exist_ok=True)
            shutil.copy2(f, dest)
            copied += 1
    return copied


def ros_domain(offset: int = 0) -> int:
    """A ROS_DOMAIN_ID for this test process: the pytest-xdist workers draw from disjoint
    ranges of 10-209 (two workers: 10-109 and 110-209; four: 50 each), so tests running side
    by side never share a domain; the process id spreads concurrent suites on one machine."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")[2:]
    count = os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")
    count = min(max(int(count), 1), 20) if count.isdigit() else 1
    size = 200 // count
    index = int(worker) % count if worker.isdigit() else 0
    return 10 + size * index + (os.getpid() + offset) % size


def ros_test_env(domain_id: int) -> dict[str, str]:
    """Environment for a ROS process of a test: localhost discovery, a private domain."""
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    venv = Path(sys.prefix)
    env["AMENT_PREFIX_PATH"] = os.pathsep.join(
        p for p in (str(venv), env.get("AMENT_PREFIX_PATH", "")) if p
    )
    return env


def ground_truth_pose(frame) -> np.ndarray:
    """(4, 4) ``T_world_camera`` of a rendered :class:`rsvo_ros.sim.synth.Frame` (row 0)."""
    return frame.pose()


def rs_views(state, X: np.ndarray, focal: float, tau: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact rolling-shutter views of world points ``X`` (n, 3) by a frame (a
    :class:`rsvo_ros.odometry.frame.FrameState`, principal point at the reference row):
    normalized coordinates (n, 2) and row times from the reference row (n,), each point seen
    at the row whose camera sees it there (fixed point)."""
    s = np.zeros(len(X))
    for _ in range(30):
        R, p = state.row_cameras(s)
        Xc = np.einsum("nji,nj->ni", R, X - p)
        x = Xc[:, :2] / Xc[:, 2:]
        s = x[:, 1] * focal * tau
    return x, s
