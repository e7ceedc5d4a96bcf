"""What :func:`coworld.models.networks.linear`'s choice of forms saves inside the update: one process, one DreamerV2
agent, alternating updates on the same prepared batch with the choice on (each linear layer from 2,048 rows in the
faster of the matrix product and oneDNN's 1 x 1 convolution, per shape) and off (every one ``F.linear``).

    LD_PRELOAD=<tcmalloc> .venv/bin/python benchmarks/linear_ab.py [--preset paper] [--pairs 20] [--set KEY=VALUE ...]

Batch 16 x 32 and one torch thread unless ``--set`` says otherwise; random frames. Each pair runs both, in
alternating order, after one untimed update of each (the forms are timed on the first call of each shape); prints
the forms chosen, then the median, mean and minimum seconds of each side, the median of the per-pair ratios and
the ratio of the medians.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from train_throughput import random_batch  # this script's folder is first on sys.path

from coworld.agents.dreamerv2 import DreamerV2
from coworld.config import PRESETS, make_config
from coworld.models import autotune, networks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="tiny", choices=sorted(PRESETS))
    parser.add_argument("--pairs", type=int, default=20, help="alternating pairs of updates to time")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override")
    args = parser.parse_args()
    torch.set_num_threads(1)
    overrides = ["device=cpu", "train.batch_size=16", "train.seq_len=32", *args.set]
    config = make_config(args.preset, dict(item.split("=", 1) for item in overrides))
    agent = DreamerV2(config=config, action_size=6)
    batch = agent.prepare(random_batch(config.train.batch_size, config.train.seq_len, 6))
    sides = {"chosen": networks._LINEAR_MIN_ROWS, "F.linear": 2**62}  # side -> linear's threshold of rows

    def update(side: str) -> float:
        networks._LINEAR_MIN_ROWS = sides[side]
        start = time.perf_counter()
        agent.train(batch)
        return time.perf_counter() - start

    for side in sides:
        update(side)
    print("forms chosen:", {key: form for key, form in autotune.chosen().items() if key[0].startswith("linear")})
    times: dict[str, list[float]] = {side: [] for side in sides}
    for pair in range(args.pairs):
        for side in sorted(sides, reverse=pair % 2 == 1):
            times[side].append(update(side))
    for side, s in times.items():
        print(f"{side:9s} median {statistics.median(s):8.3f} s  mean {statistics.mean(s):8.3f}  min {min(s):8.3f}")
    ratios = [b / a for a, b in zip(times["chosen"], times["F.linear"], strict=True)]
    medians = statistics.median(times["F.linear"]) / statistics.median(times["chosen"])
    print(f"F.linear / chosen: median of pairs {statistics.median(ratios):.3f}, of medians {medians:.3f}")


if __name__ == "__main__":
    main()
