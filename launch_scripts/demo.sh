#!/usr/bin/env bash
# Set up (or reuse) .venv and run the main job on built-in synthetic data:
#  1. the paper's synthetic experiment (rsvo_bench, 10 trials per cell: about 2 minutes);
#  2. a synthetic rolling-shutter bag (rsvo_synth), replayed offline with the RS and the GS model
#     (rsvo_replay);
#  3. the live graph: rsvo_node, rsvo_play publishing the bag, and a separate subscriber process
#     recording /rsvo/odom, once per model; then RS vs GS accuracy against ground truth and a plot.
# Outputs go to results/demo (override with RSVO_DEMO_OUTPUT). Extra args go to rsvo_bench.
set -euo pipefail
REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$REPO_ROOT/launch_scripts/setup.sh"
# shellcheck source=/dev/null
source "$REPO_ROOT/launch_scripts/ros_env.sh"
OUT="${RSVO_DEMO_OUTPUT:-$REPO_ROOT/results/demo}"
mkdir -p "$OUT"
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$((40 + RANDOM % 50))}"

rsvo_bench --trials 10 --output "$OUT/bench" "$@"

BAG="$OUT/vehicle_bag"
rsvo_synth "$BAG" --motion vehicle --severity 2 --frames 60 --overwrite
LINE_DELAY="$(python -c "from rsvo_ros.ros import bagio; print(bagio.custom_data('$BAG')['rsvo.line_delay'])")"
for model in rs gs; do
    rsvo_replay "$BAG" --output "$OUT/replay_$model" --model "$model" --overwrite
done

pids=()
cleanup() { for p in "${pids[@]}"; do kill -INT "$p" 2>/dev/null || true; done; }
trap cleanup EXIT
declare -A RATE=([rs]=0.5 [gs]=0.5)  # 15 frames/s: both models keep up here
for model in rs gs; do
    echo "[demo] live graph, model $model (bag played at ${RATE[$model]}x)"
    rm -f "$OUT/live_$model.tum" "$OUT/live_$model.tum.ready"
    rsvo_node --ros-args -p model:="$model" -p line_delay:="$LINE_DELAY" \
        > "$OUT/node_$model.log" 2>&1 &
    pids+=($!)
    node_pid=$!
    python -m rsvo_ros.ros.record "$OUT/live_$model.tum" --idle 8 &
    rec_pid=$!
    pids+=($rec_pid)
    for _ in $(seq 1200); do [ -f "$OUT/live_$model.tum.ready" ] && break; sleep 0.1; done
    rsvo_play "$BAG" --rate "${RATE[$model]}" --wait-for-subscribers 30 --start-delay 1 \
        --topics /camera/image_raw /camera/camera_info
    wait "$rec_pid" || true
    kill -INT "$node_pid" 2>/dev/null || true
    wait "$node_pid" 2>/dev/null || true
done
python -m rsvo_ros.tools.compare "$BAG" "RS=$OUT/live_rs.tum" "GS=$OUT/live_gs.tum" \
    --plot "$OUT/live_trajectories.png"
echo "demo outputs: $OUT (bench/bench_boxplot.png, replay_*/trajectory.png, live_trajectories.png)"
