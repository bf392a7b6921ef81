#!/usr/bin/env bash
# The README's live-node latency table: for each resolution (640x480, 1280x720) and input rate
# (10, 15, 30 Hz) start a fresh rsvo_node (window backend, RS model, async mapping) and feed it
# rendered hand-held walk frames over DDS with python -m rsvo_ros.ros.latency, then print the
# table (python -m rsvo_ros.ros.latency --summary). A fresh node per rate: a probe that paused
# between rates would lose its first frame to the node's "stamp far ahead" rule. Results (one
# JSON per run) go to results/latency (override with RSVO_LATENCY_OUTPUT); frames per run with
# RSVO_LATENCY_FRAMES (default 300). About 8 minutes; run it on an otherwise idle machine.
set -euo pipefail
REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$REPO_ROOT/launch_scripts/setup.sh" >/dev/null
# shellcheck source=/dev/null
source "$REPO_ROOT/launch_scripts/ros_env.sh"
OUT="${RSVO_LATENCY_OUTPUT:-$REPO_ROOT/results/latency}"
FRAMES="${RSVO_LATENCY_FRAMES:-300}"
mkdir -p "$OUT"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-87}"
results=()
for res in 640x480 1280x720; do
    # a 36 ms readout at either height; reliable images (the probe renders before it
    # advertises, so the node's auto QoS would time out and fall back to best effort)
    ld=$(python -c "print(0.036 / int('$res'.split('x')[1]))")
    for rate in 10 15 30; do
        rsvo_node --ros-args -p line_delay:="$ld" -p image_qos_reliability:=reliable \
            > "$OUT/node_${res}_${rate}hz.log" 2>&1 &
        node_pid=$!
        python -m rsvo_ros.ros.latency --rate "$rate" --resolution "$res" --frames "$FRAMES" \
            --motion walk --node-pid "$node_pid" --json "$OUT/latency_${res}_${rate}hz.json"
        kill -INT "$node_pid"
        wait "$node_pid" || true
        results+=("$OUT/latency_${res}_${rate}hz.json")
    done
done
python -m rsvo_ros.ros.latency --summary "${results[@]}" | tee "$OUT/table.md"
echo "wrote $OUT/table.md and one JSON per run"
