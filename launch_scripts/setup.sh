#!/usr/bin/env bash
# Create or reuse .venv at the repository root and install rsvo_ros with its pinned dependencies
# (requirements.txt). Idempotent: a second run only checks a stamp and returns in about a second.
# Usage: bash launch_scripts/setup.sh            (sourcing it also exports the ROS environment)
set -euo pipefail
REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${RSVO_VENV:-$REPO_ROOT/.venv}"
PYTHON="${PYTHON:-python3}"

if [ ! -x "$VENV/bin/python" ]; then
    echo "[setup] creating $VENV with $($PYTHON --version 2>&1)"
    "$PYTHON" -m venv "$VENV"
fi

# Reinstall only when what defines the install changed.
stamp_file="$VENV/.rsvo_ros_setup_stamp"
stamp="$(cat "$REPO_ROOT/requirements.txt" "$REPO_ROOT/setup.py" "$REPO_ROOT/setup.cfg" \
    "$REPO_ROOT/package.xml" | sha256sum | cut -d' ' -f1)"
if [ -f "$stamp_file" ] && [ "$(cat "$stamp_file")" = "$stamp" ]; then
    echo "[setup] $VENV is up to date"
else
    echo "[setup] installing pinned dependencies into $VENV (first run: about a minute)"
    "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check --upgrade pip
    "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check \
        -r "$REPO_ROOT/requirements.txt"
    # Editable, so the checkout is what runs; console scripts land in $VENV/bin.
    "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check --no-deps \
        --no-build-isolation -e "$REPO_ROOT"
    echo "$stamp" > "$stamp_file"
    echo "[setup] done"
fi
# tf2_msgs for /tf (not on PyPI): found, or built from its interface definition; a failed build
# is reported and leaves the rest usable (the node then says it cannot publish /tf)
bash "$REPO_ROOT/launch_scripts/build_tf2_msgs.sh" "$VENV" || true
