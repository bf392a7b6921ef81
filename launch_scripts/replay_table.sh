#!/usr/bin/env bash
# The README's rsvo_replay tables: synthetic vehicle bags and hand-held walks, each replayed with
# the RS and GS models and the window and pairwise backends (python -m rsvo_ros.tools.replay_table;
# every figure is read from the summary.json that rsvo_replay writes). Outputs go to
# results/replay_table (override with RSVO_TABLE_OUTPUT): tables.md, rows.json and the plots
# replay_ate_vehicle.png, replay_ate_walk.png (the README's docs/ figures).
#   bash launch_scripts/replay_table.sh                    # about 20 minutes on 2 cores
#   RSVO_TABLE_ONLY=walk bash launch_scripts/replay_table.sh
#   RSVO_TABLE_HD=1 bash launch_scripts/replay_table.sh    # plus the 1280x720 frame rate
set -euo pipefail
REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$REPO_ROOT/launch_scripts/setup.sh" >/dev/null
# shellcheck source=/dev/null
source "$REPO_ROOT/launch_scripts/ros_env.sh"
OUT="${RSVO_TABLE_OUTPUT:-$REPO_ROOT/results/replay_table}"
mkdir -p "$OUT"
python -m rsvo_ros.tools.replay_table "$OUT" ${RSVO_TABLE_ONLY:+--only "$RSVO_TABLE_ONLY"}

fps() { python -c "import json,sys; print('%.1f' % json.load(open(sys.argv[1]))['frames_per_second'])" "$1"; }
if [ -n "${RSVO_TABLE_HD:-}" ]; then
    for motion in vehicle walk; do
        rsvo_synth "$OUT/hd_$motion" --motion "$motion" --severity 1 --frames 90 \
            --resolution 1280x720 --overwrite --no-progress >/dev/null
        for backend in window pairwise; do
            for model in rs gs; do
                /usr/bin/time -v rsvo_replay "$OUT/hd_$motion" --output "$OUT/hd_${motion}_${backend}_$model" \
                    --model "$model" --backend "$backend" --overwrite --no-progress \
                    2> "$OUT/hd_$motion.$backend.$model.time" >/dev/null
                rss="$(awk '/Maximum resident/ {printf "%.0f", $6 / 1024}' "$OUT/hd_$motion.$backend.$model.time")"
                echo "1280x720 $motion, $backend backend, model $model: $(fps "$OUT/hd_${motion}_${backend}_$model/summary.json") frames/s end to end, peak RSS $rss MB"
            done
        done
    done
fi
