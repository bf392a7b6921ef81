#!/usr/bin/env bash
# The README's live-node latency table: start rsvo_node (window backend, RS model), feed it
# rendered hand-held walk frames over DDS at 10, 15 and 30 Hz with python -m rsvo_ros.ros.latency,
# at 640x480 and 1280x720. Results (one JSON per resolution) go to results/latency (override
# with RSVO_LATENCY_OUTPUT). About 3 minutes; run it on an otherwise idle machine.
set -euo pipefail
REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$REPO_ROOT/launch_scripts/setup.sh" >/dev/null
# shellcheck source=/dev/null
source "$REPO_ROOT/launch_scripts/ros_env.sh"
OUT="${RSVO_LATENCY_OUTPUT:-$REPO_ROOT/results/latency}"
mkdir -p "$OUT"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-87}"
for res in 640x480 1280x720; do
    # a 36 ms readout at either height; reliable images (the probe renders before it
    # advertises, so the node's auto QoS would time out and fall back to best effort)
    ld=$(python -c "print(0.036 / int('$res'.split('x')[1]))")
    rsvo_node --ros-args -p line_delay:="$ld" -p image_qos_reliability:=reliable \
        > "$OUT/node_$res.log" 2>&1 &
    node_pid=$!
    python -m rsvo_ros.ros.latency --rate 10 15 30 --resolution "$res" --frames 90 \
        --motion walk --node-pid "$node_pid" --json "$OUT/latency_$res.json"
    kill -INT "$node_pid"
    wait "$node_pid" || true
done
echo "wrote $OUT/latency_640x480.json, $OUT/latency_1280x720.json"
