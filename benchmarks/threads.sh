#!/usr/bin/env bash
# Tiny DreamerV2 updates/s (benchmarks/train_throughput.py, median of 30 calls), two rounds of
# {idle, one core kept busy by `yes`} x {1 thread, 2 threads, 2 threads with OMP_WAIT_POLICY=PASSIVE}.
#   bash benchmarks/threads.sh
set -u
cd "$(dirname "$0")/.."
run() {  # run POLICY THREADS -> updates/s
  env -u OMP_WAIT_POLICY -u OMP_NUM_THREADS ${1:+OMP_WAIT_POLICY=$1} .venv/bin/python benchmarks/train_throughput.py \
    --threads "$2" --updates 30 --warmup 3 2>/dev/null | awk '/^default/ {print $NF}'
}
for load in idle busy; do
  if [ "$load" = busy ]; then yes >/dev/null & busy=$!; sleep 1; fi
  for round in 1 2; do
    echo "$load round $round: 1 thread $(run "" 1), 2 threads $(run "" 2), 2 threads passive $(run PASSIVE 2)"
  done
  if [ "$load" = busy ]; then kill "$busy"; fi
done
