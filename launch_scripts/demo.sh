#!/usr/bin/env bash
# Set up (or reuse) .venv and run the main job on built-in synthetic data. Today that is the
# paper's synthetic experiment (rsvo_bench); extra args go to rsvo_bench.
set -euo pipefail
REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$REPO_ROOT/launch_scripts/setup.sh"
# shellcheck source=/dev/null
source "$REPO_ROOT/launch_scripts/ros_env.sh"
cd "$REPO_ROOT"
exec rsvo_bench --output "${RSVO_DEMO_OUTPUT:-$REPO_ROOT/results/bench}" "$@"
