#!/usr/bin/env bash
# Tiny DreamerV2 updates/s (benchmarks/train_throughput.py, median of 30 calls), two rounds of: {idle, one core busy} x {1 thread, 2 threads, 2 threads + OMP_WAIT_POLICY=PASSIVE}
cd /work/main
run() { env $1 .venv/bin/python benchmarks/train_throughput.py --threads $2 --updates 30 --warmup 3 2>/dev/null | grep -E "^default" | awk "{print \$NF}"; }
for load in idle busy; do
  if [ $load = busy ]; then yes > /dev/null & YES=$!; sleep 1; fi
  for round in 1 2; do
    echo "$load round$round 1T: $(run OMP_WAIT_POLICY= 1)"
    echo "$load round$round 2T: $(run OMP_WAIT_POLICY= 2)"
    echo "$load round$round 2T-passive: $(run OMP_WAIT_POLICY=PASSIVE 2)"
  done
  if [ $load = busy ]; then kill $YES; fi
done
