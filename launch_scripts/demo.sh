#!/usr/bin/env bash
# Set up (or reuse) .venv and run the main job on built-in synthetic data:
#  1. the paper's synthetic experiment (rsvo_bench, 10 trials per cell: about 2 minutes);
#  2. a synthetic rolling-shutter bag (rsvo_synth) replayed with the RS and the GS model
#     (rsvo_replay), printing both trajectories' accuracy against ground truth.
# Outputs go to results/demo (override with RSVO_DEMO_OUTPUT). Extra args go to rsvo_bench.
set -euo pipefail
REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$REPO_ROOT/launch_scripts/setup.sh"
# shellcheck source=/dev/null
source "$REPO_ROOT/launch_scripts/ros_env.sh"
OUT="${RSVO_DEMO_OUTPUT:-$REPO_ROOT/results/demo}"
mkdir -p "$OUT"
rsvo_bench --trials 10 --output "$OUT/bench" "$@"
rsvo_synth "$OUT/vehicle_bag" --motion vehicle --severity 2 --frames 60 --overwrite
for model in rs gs; do
    rsvo_replay "$OUT/vehicle_bag" --output "$OUT/replay_$model" --model "$model" --overwrite
done
echo "demo outputs: $OUT (bench/bench_boxplot.png, replay_rs/trajectory.png, replay_gs/...)"
