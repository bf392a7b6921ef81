"""Lint is part of the suite: ruff with the ament_flake8 line length (99), see ruff.toml."""

import shutil
import subprocess
import sys
from pathlib import Path

from conftest import REPO_ROOT


def test_ruff_clean():
    ruff = shutil.which("ruff") or str(Path(sys.executable).parent / "ruff")
    proc = subprocess.run(
        [ruff, "check", "--no-cache", str(REPO_ROOT)],
        capture_output=True, text=True, cwd=REPO_ROOT,
    )
    assert proc.returncode == 0, f"ruff found problems:\n{proc.stdout}\n{proc.stderr}"


def test_python_files_compile():
    proc = subprocess.run(
        [sys.executable, "-m", "compileall", "-q", "rsvo_ros", "test", "launch_scripts"],
        capture_output=True, text=True, cwd=REPO_ROOT,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
