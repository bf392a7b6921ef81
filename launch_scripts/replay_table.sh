#!/usr/bin/env bash
# The README's rsvo_replay table: RS against GS on synthetic vehicle bags, with and without
# rolling shutter (and RS with --no-motion-prior: each pair on its own, as in the paper), and
# the frame rate at 1280x720. Every figure is read from the summary.json
# that rsvo_replay writes. Outputs go to results/replay_table (override with RSVO_TABLE_OUTPUT).
#   bash launch_scripts/replay_table.sh            # 24 sequences at 640x360 (about 5 minutes)
#   RSVO_TABLE_HD=1 bash launch_scripts/replay_table.sh   # plus the 1280x720 frame rate
# It also draws replay_ate.png (the README's docs/replay_ate.png).
set -euo pipefail
REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$REPO_ROOT/launch_scripts/setup.sh" >/dev/null
# shellcheck source=/dev/null
source "$REPO_ROOT/launch_scripts/ros_env.sh"
OUT="${RSVO_TABLE_OUTPUT:-$REPO_ROOT/results/replay_table}"
mkdir -p "$OUT"

# name | rsvo_synth options
SEQUENCES=()
for seed in 0 1 2 3; do SEQUENCES+=("sev1_s$seed|--severity 1 --seed $seed"); done
# seeds 8-15 were not used while the motion prior's scales were chosen
for seed in $(seq 0 15); do SEQUENCES+=("sev2_s$seed|--severity 2 --seed $seed"); done
for seed in 0 1 2 3; do
    SEQUENCES+=("gs_sev2_s$seed|--severity 2 --seed $seed --line-delay 0")
done
ate() { python -c "import json,sys; print('%.3f' % json.load(open(sys.argv[1]))['accuracy']['ate_m']['rmse'])" "$1"; }
fps() { python -c "import json,sys; print('%.1f' % json.load(open(sys.argv[1]))['frames_per_second'])" "$1"; }

rows=()
for entry in "${SEQUENCES[@]}"; do
    name="${entry%%|*}"
    # shellcheck disable=SC2086
    rsvo_synth "$OUT/$name" --motion vehicle --frames 60 ${entry#*|} --overwrite --no-progress >/dev/null
    for model in rs gs; do
        rsvo_replay "$OUT/$name" --output "$OUT/${name}_$model" --model "$model" --overwrite \
            --no-progress >/dev/null
    done
    rsvo_replay "$OUT/$name" --output "$OUT/${name}_rs_alone" --model rs --no-motion-prior \
        --overwrite --no-progress >/dev/null
    a_rs="$(ate "$OUT/${name}_rs/summary.json")"
    a_gs="$(ate "$OUT/${name}_gs/summary.json")"
    a_alone="$(ate "$OUT/${name}_rs_alone/summary.json")"
    ratio="$(python -c "print('%.2f' % ($a_rs / $a_gs))")"
    rows+=("| ${entry#*|} | $a_rs m | $a_gs m | $ratio | $a_alone m |")
done
echo "| rsvo_synth options (vehicle, 60 frames, 640x360) | RS ATE | GS ATE | RS / GS |" \
     "RS ATE, --no-motion-prior |"
echo "|---|---|---|---|---|"
printf '%s\n' "${rows[@]}"
# per group: geometric mean of RS / GS and how many are at most half / within 10 %
printf '%s\n' "${rows[@]}" | python -c "
import math, re, sys
groups = {}
for line in sys.stdin:
    cells = line.split('|')
    key = re.sub(r'--seed \\d+ ?', '', cells[1]).strip()
    gs, alone = float(cells[3].split()[0]), float(cells[5].split()[0])
    groups.setdefault(key, []).append((float(cells[4]), alone / gs))
def geo(r):
    return math.exp(sum(map(math.log, r)) / len(r))
for key, rows in groups.items():
    r, a = [x for x, _ in rows], [y for _, y in rows]
    n = len(r)
    print(f'{key}: RS/GS geometric mean {geo(r):.2f}; <= 0.5 on {sum(x <= 0.5 for x in r)} of {n},'
          f' <= 1.1 on {sum(x <= 1.1 for x in r)} of {n} (--no-motion-prior: {geo(a):.2f};'
          f' <= 0.5 on {sum(x <= 0.5 for x in a)} of {n})')
"

# the same figures as a picture: ATE per sequence, log scale
printf '%s\n' "${rows[@]}" | python -c "
import sys
import matplotlib
matplotlib.use('Agg')
import matplotlib.pyplot as plt
import numpy as np
names, ates = [], []
for line in sys.stdin:
    cells = line.split('|')
    opts = cells[1].split()
    name = 's' + opts[opts.index('--severity') + 1] + '/' + opts[opts.index('--seed') + 1]
    names.append(name + (' LD0' if '--line-delay' in opts else ''))
    ates.append([float(cells[i].split()[0]) for i in (2, 3, 5)])
ates = np.array(ates)
x = np.arange(len(names))
fig, ax = plt.subplots(figsize=(12, 4))
for j, (label, colour) in enumerate([('RS', 'tab:red'), ('GS', 'tab:blue'),
                                     ('RS --no-motion-prior', 'tab:orange')]):
    ax.bar(x + (j - 1) * 0.27, ates[:, j], 0.27, label=label, color=colour)
ax.set_yscale('log')
ax.set_xticks(x, names, rotation=60, fontsize=8)
ax.set_ylabel('ATE after Sim(3) (m)')
ax.set_title('rsvo_replay on synthetic vehicle bags (severity/seed; LD0: line delay 0)')
ax.grid(axis='y', alpha=0.3)
ax.legend()
fig.tight_layout()
fig.savefig('$OUT/replay_ate.png', dpi=100)
print('plot: $OUT/replay_ate.png')
"

if [ -n "${RSVO_TABLE_HD:-}" ]; then
    rsvo_synth "$OUT/hd" --motion vehicle --severity 2 --frames 60 --resolution 1280x720 \
        --overwrite --no-progress >/dev/null
    for model in rs gs; do
        /usr/bin/time -v rsvo_replay "$OUT/hd" --output "$OUT/hd_$model" --model "$model" \
            --overwrite --no-progress 2> "$OUT/hd_$model.time" >/dev/null
        rss="$(awk '/Maximum resident/ {printf "%.0f", $6 / 1024}' "$OUT/hd_$model.time")"
        echo "1280x720, model $model: $(fps "$OUT/hd_$model/summary.json") frames/s end to end, peak RSS $rss MB"
    done
fi
