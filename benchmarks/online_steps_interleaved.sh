#!/usr/bin/env bash
# The same online DreamerV2 collection (walker_walk, cpu preset, one torch thread) on two coworld checkouts,
# alternating, and the perf/steps_per_s and perf/updates_per_s each run logged every 250 env steps. Evaluation
# is off, so each window after the 500-step random prefill is acting and learning alone.
#
#   [PRESET=NAME] [SETS=...] [NEW_SETS="--set KEY=VALUE ..."] \
#     bash benchmarks/online_steps_interleaved.sh BASE_TREE NEW_TREE OUT [BLOCKS] [STEPS]
#
# The two trees may be one checkout, NEW_SETS then making the difference (e.g. --set train.background_updates=true);
# NEW_SETS goes to the new side only. PRESET (default cpu) names the preset, and SETS ("--set KEY=VALUE ...") goes to
# both sides: a checkout older than the cpu preset (a9da0c3) runs PRESET=tiny SETS="--set train.train_every=2". OUT
# receives one dataset, run folder and log per side and block; the script prints the 1-minute load average before
# each run and the rates logged by the windows after the prefill.
set -euo pipefail
[ $# -ge 3 ] && [ $# -le 5 ] || { echo "usage: $0 BASE_TREE NEW_TREE OUT [BLOCKS] [STEPS]" >&2; exit 2; }
base=$(realpath "$1"); new=$(realpath "$2"); out=$3; blocks=${4:-3}; steps=${5:-2000}
python=$(dirname "$(realpath "$0")")/../.venv/bin/python
preset=${PRESET:-cpu}
mkdir -p "$out"
for block in $(seq 0 $((blocks - 1))); do
  for side in base new; do
    tree=$base; sets=${SETS:-}
    [ $side = new ] && { tree=$new; sets="${SETS:-} ${NEW_SETS:-}"; }
    data="$out/$side-b$block.h5"
    [ -e "$data" ] && { echo "$data exists; choose an empty OUT" >&2; exit 2; }
    load=$(cut -d' ' -f1 /proc/loadavg)
    (cd "$tree" && PYTHONPATH="$tree" "$python" -c 'import coworld.cli as c; getattr(c, "run", c.main)()' \
      collect --task walker_walk \
      --preset "$preset" --threads 1 --quiet --max-steps "$steps" --out "$data" --set train.eval_every=1000000000 \
      --set train.log_every=250 $sets > "$out/$side-b$block.log" 2>&1)
    metrics="$out/$side-b$block.run/metrics.jsonl"
    window() { grep -o "\"perf/$1\": [0-9.]*" "$metrics" | awk 'NR > 1 {printf "%.2f ", $2}'; }
    echo "block $block $side load $load perf/steps_per_s $(window steps_per_s)| perf/updates_per_s $(window updates_per_s)"
  done
done
