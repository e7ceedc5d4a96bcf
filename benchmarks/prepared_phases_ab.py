"""What a prepared batch's float32 phases save inside the update: one process, one DreamerV2 agent, alternating
updates on the same prepared batch with the encoder's phases as :meth:`WorldModel.prepare
<coworld.models.world_model.WorldModel.prepare>` leaves them on a CPU (the pixels' values as float32) and as uint8
(which the encoder's first layer then converts inside the update, as every update did before).

    LD_PRELOAD=<tcmalloc> .venv/bin/python benchmarks/prepared_phases_ab.py [--pairs 40] [--set KEY=VALUE ...]

Tiny preset, batch 16 x 32 and one torch thread unless ``--set`` says otherwise; random frames. Each pair runs
both kinds, in alternating order; prints the median, mean and minimum milliseconds of each kind and the median of
the per-pair differences.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from train_throughput import random_batch  # this script's folder is first on sys.path

from coworld.agents.dreamerv2 import DreamerV2
from coworld.config import make_config


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=40, help="alternating pairs of updates to time")
    parser.add_argument("--warmup", type=int, default=3, help="untimed updates first")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override")
    args = parser.parse_args()
    torch.set_num_threads(1)
    overrides = ["device=cpu", "train.batch_size=16", "train.seq_len=32", *args.set]
    config = make_config("tiny", dict(item.split("=", 1) for item in overrides))
    agent = DreamerV2(config=config, action_size=6)
    batch = random_batch(config.train.batch_size, config.train.seq_len, 6)
    kinds = {"float32": agent.prepare(batch)}
    kinds["uint8"] = {**kinds["float32"], "phases": kinds["float32"]["phases"].to(torch.uint8)}
    for _ in range(args.warmup):
        agent.train(kinds["float32"])
    times: dict[str, list[float]] = {kind: [] for kind in kinds}
    for pair in range(args.pairs):
        for kind in sorted(kinds, reverse=pair % 2 == 1):
            start = time.perf_counter()
            agent.train(kinds[kind])
            times[kind].append((time.perf_counter() - start) * 1e3)
    for kind, ms in times.items():
        print(f"{kind:8s} median {statistics.median(ms):7.2f} ms  mean {statistics.mean(ms):7.2f}  min {min(ms):7.2f}")
    saved = [a - b for a, b in zip(times["uint8"], times["float32"], strict=True)]
    print(f"uint8 - float32, median of pairs: {statistics.median(saved):.2f} ms")


if __name__ == "__main__":
    main()
