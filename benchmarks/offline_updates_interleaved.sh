#!/usr/bin/env bash
# The same offline DreamerV2 command (tiny sizes, batch 16 x 32, one torch thread) on two coworld checkouts,
# alternating, and the perf/updates_per_s each run logged (every 50 updates, 200 updates a run).
#
#   bash benchmarks/offline_updates_interleaved.sh BASE_TREE NEW_TREE DATASET.h5 OUT [BLOCKS] [--set KEY=VALUE ...]
#
# DATASET is a toy_reach_shifted dataset (e.g. from `coworld collect --task toy_reach_shifted --preset tiny`); OUT
# receives one run folder and log per side and block, and prints the 1-minute load average before each run and
# the logged rates.
#
# NEW_SETS in the environment adds settings to NEW_TREE's runs alone (e.g. NEW_SETS="train.backend=reference", a
# key an older checkout does not have).
#
# With ALGO=coworld in the environment the command is CoWorld's instead (toy_reach as the online source, 600 source
# steps of pretraining, then 200 target updates and 100 source updates): it prints each run's logged
# target/perf/updates_per_s (every 50 target updates, dataset batches made ahead as the run makes them) and
# source/perf/updates_per_s (every 50 source steps, 5 updates, with the source environment's steps between them;
# the pretraining's windows left out).
set -euo pipefail
[ $# -ge 4 ] || { echo "usage: $0 BASE_TREE NEW_TREE DATASET.h5 OUT [BLOCKS] [--set KEY=VALUE ...]" >&2; exit 2; }
base=$(realpath "$1"); new=$(realpath "$2"); data=$(realpath "$3"); out=$4; blocks=${5:-3}
shift $(( $# >= 5 ? 5 : 4 ))
python=$(dirname "$(realpath "$0")")/../.venv/bin/python
algo=${ALGO:-dreamerv2}
pretrain=600  # CoWorld's source steps before its first target phase
case $algo in
  dreamerv2) length=(--set coworld.iterations=1 --set coworld.target_updates=200); rates=(perf) ;;
  coworld) length=(--set coworld.iterations=1 --set coworld.target_updates=200 --set coworld.source_updates=100
                   --set coworld.pretrain_steps=$pretrain); rates=(target/perf source/perf) ;;
  *) echo "ALGO must be dreamerv2 or coworld, not $algo" >&2; exit 2 ;;
esac
mkdir -p "$out"
for block in $(seq 0 $((blocks - 1))); do
  for side in base new; do
    tree=$base; sets=()
    if [ $side = new ]; then tree=$new; for item in ${NEW_SETS:-}; do sets+=(--set "$item"); done; fi
    run="$out/$side-b$block"
    [ -e "$run" ] && { echo "$run exists; choose an empty OUT" >&2; exit 2; }
    load=$(cut -d' ' -f1 /proc/loadavg)
    # `python -c` rather than `-m coworld.cli`: older checkouts' cli.py has no __main__ guard, nor run() (the
    # entry that preloads tcmalloc), so each tree runs as its own `coworld` command does.
    (cd "$tree" && PYTHONPATH="$tree" "$python" -c 'import coworld.cli as c; getattr(c, "run", c.main)()' \
      train --algo "$algo" \
      --source toy_reach --target toy_reach_shifted --dataset "$data" --preset tiny --threads 1 --no-progress \
      --set train.batch_size=16 --set train.seq_len=32 "${length[@]}" \
      --set train.log_every=50 --set train.eval_episodes=1 --logdir "$run" "${sets[@]}" "$@" > "$run.log" 2>&1)
    for rate in "${rates[@]}"; do
      # the source's windows from its pretraining (no target batch in its updates) are left out
      logged=$("$python" -c 'import json, sys
rows = [json.loads(line) for line in open(sys.argv[1])]
key = sys.argv[2] + "/updates_per_s"
print(" ".join(f"{row[key]:.3f}" for row in rows if key in row and not (key.startswith("source/") and row["step"] <= int(sys.argv[3]))))' \
        "$run/metrics.jsonl" "$rate" "$pretrain")
      echo "block $block $side load $load $rate/updates_per_s $logged"
    done
  done
done
