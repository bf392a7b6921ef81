#!/usr/bin/env bash
# Set up (or reuse) .venv and run the whole test suite, lint included. Extra args go to pytest.
set -euo pipefail
REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$REPO_ROOT/launch_scripts/setup.sh"
# shellcheck source=/dev/null
source "$REPO_ROOT/launch_scripts/ros_env.sh"
cd "$REPO_ROOT"
# two pytest-xdist workers (the CI machine's two cores), each test file on one of them (its
# module fixtures are built once); `-n 0` after it runs in one process (debugging one test).
# Not in pytest.ini: a plain `pytest` or `colcon test` works without pytest-xdist.
exec python -m pytest -n 2 --dist loadfile "$@"
