#!/usr/bin/env bash
# The same offline DreamerV2 command (tiny sizes, batch 16 x 32, one torch thread) on two coworld checkouts,
# alternating, and the perf/updates_per_s each run logged (every 50 updates, 200 updates a run).
#
#   bash benchmarks/offline_updates_interleaved.sh BASE_TREE NEW_TREE DATASET.h5 OUT [BLOCKS] [--set KEY=VALUE ...]
#
# DATASET is a toy_reach_shifted dataset (e.g. from `coworld collect --task toy_reach_shifted --preset tiny`); OUT
# receives one run folder and log per side and block, and prints the 1-minute load average before each run and
# the logged rates.
set -euo pipefail
[ $# -ge 4 ] || { echo "usage: $0 BASE_TREE NEW_TREE DATASET.h5 OUT [BLOCKS] [--set KEY=VALUE ...]" >&2; exit 2; }
base=$(realpath "$1"); new=$(realpath "$2"); data=$(realpath "$3"); out=$4; blocks=${5:-3}
shift $(( $# >= 5 ? 5 : 4 ))
python=$(dirname "$(realpath "$0")")/../.venv/bin/python
mkdir -p "$out"
for block in $(seq 0 $((blocks - 1))); do
  for side in base new; do
    tree=$base; [ $side = new ] && tree=$new
    run="$out/$side-b$block"
    [ -e "$run" ] && { echo "$run exists; choose an empty OUT" >&2; exit 2; }
    load=$(cut -d' ' -f1 /proc/loadavg)
    # `python -c` rather than `-m coworld.cli`: older checkouts' cli.py has no __main__ guard, nor run() (the
    # entry that preloads tcmalloc), so each tree runs as its own `coworld` command does.
    (cd "$tree" && PYTHONPATH="$tree" "$python" -c 'import coworld.cli as c; getattr(c, "run", c.main)()' \
      train --algo dreamerv2 \
      --source toy_reach --target toy_reach_shifted --dataset "$data" --preset tiny --threads 1 --no-progress \
      --set train.batch_size=16 --set train.seq_len=32 --set coworld.iterations=1 --set coworld.target_updates=200 \
      --set train.log_every=50 --set train.eval_episodes=1 --logdir "$run" "$@" > "$run.log" 2>&1)
    rates=$(grep -o '"perf/updates_per_s": [0-9.]*' "$run/metrics.jsonl" | awk '{printf "%.3f ", $2}')
    echo "block $block $side load $load perf/updates_per_s $rates"
  done
done
