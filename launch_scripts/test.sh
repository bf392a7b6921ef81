#!/usr/bin/env bash
# Set up (or reuse) .venv and run the whole test suite, lint included. Extra args go to pytest.
set -euo pipefail
REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$REPO_ROOT/launch_scripts/setup.sh"
# shellcheck source=/dev/null
source "$REPO_ROOT/launch_scripts/ros_env.sh"
cd "$REPO_ROOT"
exec python -m pytest "$@"
