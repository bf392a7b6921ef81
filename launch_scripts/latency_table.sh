#!/usr/bin/env bash
# The README's live-node latency table: for each resolution (640x480, 1280x720) and input rate
# (10, 15, 30 Hz) start a fresh rsvo_node (window backend, RS model, async mapping) and feed it
# rendered hand-held walk frames over DDS with python -m rsvo_ros.ros.latency, then print the
# table (python -m rsvo_ros.ros.latency --summary). A fresh node per rate: a probe that paused
# between rates would lose its first frame to the node's "stamp far ahead" rule. Results (one
# JSON per run) go to results/latency (override with RSVO_LATENCY_OUTPUT); frames per run with
# RSVO_LATENCY_FRAMES (default 300). RSVO_LATENCY_DDS_PROFILES lists the Fast DDS profiles to
# run the node and the probe (the camera) with, each row with each in turn: "default" (Fast
# DDS's own defaults; the default) and "large_images" (the shipped profile, python -m
# rsvo_ros.ros.dds; README "Large images over DDS"), e.g. "default large_images".
# RSVO_LATENCY_DECIMATIONS lists the node's tracking_decimation values to run each row with
# (default "1"; e.g. "1 2 auto", auto: tracking_decimation_mode auto from full resolution:
# README "Tracking at a reduced resolution"). RSVO_LATENCY_RESOLUTIONS lists the resolutions
# (default "640x480 1280x720"). RSVO_LATENCY_MOTION_AT_RATE=1, the default since the
# thirty-fourth session, samples the walk at each rate, as a camera at that rate sees it (the
# probe's --motion-at-rate: at 15 Hz twice the motion per frame, at 10 Hz three times);
# RSVO_LATENCY_MOTION_AT_RATE=0 plays the walk's 30 Hz frames at each rate (a slowed-down
# walk), as every table before the thirty-fourth session did. Every row has the live ATE.
# RSVO_LATENCY_SEEDS lists the walks' seeds (default "0", every table so far): each row with
# each in turn, since the live ATE of one walk scatters with the node's timing.
# About 8 minutes per profile and decimation at both resolutions; run it on an otherwise idle
# machine.
set -euo pipefail
REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$REPO_ROOT/launch_scripts/setup.sh" >/dev/null
# shellcheck source=/dev/null
source "$REPO_ROOT/launch_scripts/ros_env.sh"
OUT="${RSVO_LATENCY_OUTPUT:-$REPO_ROOT/results/latency}"
FRAMES="${RSVO_LATENCY_FRAMES:-300}"
PROFILES="${RSVO_LATENCY_DDS_PROFILES:-default}"
DECIMATIONS="${RSVO_LATENCY_DECIMATIONS:-1}"
MOTION_AT_RATE="${RSVO_LATENCY_MOTION_AT_RATE:-1}"
RESOLUTIONS="${RSVO_LATENCY_RESOLUTIONS:-640x480 1280x720}"
SEEDS="${RSVO_LATENCY_SEEDS:-0}"
for seed in $SEEDS; do
    case "$seed" in
        '' | *[!0-9]*) echo "RSVO_LATENCY_SEEDS takes non-negative integers, got $seed" >&2
                       exit 2 ;;
    esac
done
for res in $RESOLUTIONS; do
    case "$res" in
        [1-9]*x[1-9]*) ;;
        *) echo "RSVO_LATENCY_RESOLUTIONS takes WIDTHxHEIGHT values, got $res" >&2
           exit 2 ;;
    esac
done
for decimation in $DECIMATIONS; do
    case "$decimation" in
        1 | 2 | 3 | 4 | auto) ;;
        *) echo "RSVO_LATENCY_DECIMATIONS takes 1-4 and auto, got $decimation" >&2
           exit 2 ;;
    esac
done
case "$MOTION_AT_RATE" in
    0) motion=() ;;
    1) motion=(--motion-at-rate) ;;
    *) echo "RSVO_LATENCY_MOTION_AT_RATE takes 0 and 1, got $MOTION_AT_RATE" >&2
       exit 2 ;;
esac
for profile in $PROFILES; do
    case "$profile" in
        default | large_images) ;;
        *) echo "RSVO_LATENCY_DDS_PROFILES takes default and large_images, got $profile" >&2
           exit 2 ;;
    esac
done
LARGE_IMAGES="$(python -m rsvo_ros.ros.dds)"
mkdir -p "$OUT"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-87}"
results=()
for res in $RESOLUTIONS; do
    for rate in 10 15 30; do
        # the node runs with the line delay the probe renders with: a 36 ms readout, at
        # most one frame interval (33 ms at 30 Hz with the motion at the rate; until the
        # forty-seventh session the 30 Hz rows told the node 36 ms). Reliable images (the
        # probe renders before it advertises, so the node's auto QoS would time out and fall
        # back to best effort)
        ld=$(python -m rsvo_ros.ros.latency --rate "$rate" --resolution "$res" --motion walk \
             "${motion[@]}" --print-line-delay)
        for profile in $PROFILES; do
            if [ "$profile" = large_images ]; then
                export FASTRTPS_DEFAULT_PROFILES_FILE="$LARGE_IMAGES"
            else
                unset FASTRTPS_DEFAULT_PROFILES_FILE
            fi
            for decimation in $DECIMATIONS; do
                if [ "$decimation" = auto ]; then
                    mode=(-p tracking_decimation_mode:=auto -p tracking_decimation:=1)
                else
                    mode=(-p tracking_decimation:="$decimation")
                fi
                for seed in $SEEDS; do
                    run="${res}_${rate}hz_${profile}_d${decimation}"
                    if [ "$seed" != 0 ]; then
                        run="${run}_s${seed}"
                    fi
                    rsvo_node --ros-args -p line_delay:="$ld" \
                        -p image_qos_reliability:=reliable "${mode[@]}" \
                        > "$OUT/node_$run.log" 2>&1 &
                    node_pid=$!
                    python -m rsvo_ros.ros.latency --rate "$rate" --resolution "$res" \
                        --frames "$FRAMES" --motion walk "${motion[@]}" --seed "$seed" \
                        --node-pid "$node_pid" --json "$OUT/latency_$run.json"
                    kill -INT "$node_pid"
                    wait "$node_pid" || true
                    results+=("$OUT/latency_$run.json")
                done
            done
        done
    done
done
python -m rsvo_ros.ros.latency --summary "${results[@]}" | tee "$OUT/table.md"
echo "wrote $OUT/table.md and one JSON per run"
