"""One digest per algorithm of what a short `tiny` run at seed 0 ends with: every tensor and number of its final
checkpoint, so that a change which should not alter behaviour can be shown not to.

    MUJOCO_GL=egl .venv/bin/python scripts/behaviour_digest.py --dir /tmp/digest > before.txt
    ... change the code ...
    MUJOCO_GL=egl .venv/bin/python scripts/behaviour_digest.py --dir /tmp/digest2 > after.txt
    diff before.txt after.txt    # no output: the same weights, optimiser states and counters, bit for bit

Each algorithm trains on one random toy_reach_shifted dataset (5 episodes, seed 0), with toy_reach as the source
where it takes one; the online DreamerV2 collector is digested as ``collect``. Left out of a digest: where the
metrics log stood (``metrics_mark``, a byte offset into a log of wall times) and the saved config's text of where the
run came from; ``--skip KEY`` leaves out more (a change that adds a checkpoint entry shows the rest unchanged).
"""

from __future__ import annotations

import argparse
import hashlib
import subprocess
import sys
from pathlib import Path
from typing import Any

import torch

CLI = [sys.executable, "-c", "from coworld.cli import run; run()"]
FAST = ["--set", "train.prefill=100", "--set", "train.eval_episodes=2", "--device", "cpu", "--threads", "1"]
SCHEDULE = [
    "coworld.pretrain_steps=200",
    "coworld.iterations=2",
    "coworld.target_updates=10",
    "coworld.source_updates=4",
    "offline.updates=20",
    "offline.log_every=10",
    "offline.eval_every=10",
    "offline.checkpoint_every=10",
]
SKIPPED = {"metrics_mark"}


def digest(state: Any) -> str:
    h = hashlib.sha256()

    def walk(value: Any, path: str) -> None:
        if isinstance(value, dict):
            for key in sorted(value, key=str):
                if key not in SKIPPED:
                    walk(value[key], f"{path}/{key}")
        elif isinstance(value, list | tuple):
            for i, item in enumerate(value):
                walk(item, f"{path}/{i}")
        elif isinstance(value, torch.Tensor):
            h.update(f"{path}:{value.dtype}:{tuple(value.shape)}".encode())
            h.update(value.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
        else:
            h.update(f"{path}={value!r}".encode())

    walk(state, "")
    return h.hexdigest()


def cli(*args: str) -> None:
    proc = subprocess.run([*CLI, *args], capture_output=True, text=True)
    if proc.returncode != 0:
        sys.exit(f"`coworld {' '.join(args)}` failed:\n{proc.stdout[-2000:]}{proc.stderr[-2000:]}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dir", type=Path, required=True, help="an empty or new folder for the runs")
    parser.add_argument("--algos", default="", help="comma-separated; default every algorithm and the collector")
    parser.add_argument(
        "--skip",
        action="append",
        default=[],
        metavar="KEY",
        help="leave the entries named KEY (at any depth) out of the digests too: a checkpoint entry a change added",
    )
    args = parser.parse_args()
    SKIPPED.update(args.skip)
    from coworld.algorithms import ALGOS, algorithm

    chosen = args.algos.split(",") if args.algos else ["collect", *ALGOS]
    args.dir.mkdir(parents=True, exist_ok=True)
    data = args.dir / "toy_reach_shifted-random.h5"
    if not data.exists():
        cli(
            "collect",
            "--task",
            "toy_reach_shifted",
            "--policy",
            "random",
            "--episodes",
            "5",
            "--seed",
            "0",
            "--out",
            str(data),
            "--quiet",
        )
    for algo in chosen:
        run = args.dir / algo
        if algo == "collect":
            cli(
                "collect",
                "--task",
                "toy_reach",
                "--preset",
                "tiny",
                "--max-steps",
                "300",
                "--out",
                f"{run}.h5",
                "--seed",
                "0",
                "--quiet",
                "--force",
                *FAST,
            )
            run = run.with_name(f"{algo}.run")  # the collector's agent sits beside its dataset
        else:
            source = ["--source", "toy_reach"] if algorithm(algo).needs_source else []
            schedule = [arg for key in SCHEDULE for arg in ("--set", key)]
            cli(
                "train",
                "--algo",
                algo,
                *source,
                "--target",
                "toy_reach_shifted",
                "--dataset",
                str(data),
                "--preset",
                "tiny",
                "--logdir",
                str(run),
                "--no-progress",
                "--seed",
                "0",
                "--force",
                *FAST,
                *schedule,
            )
        state = torch.load(run / "checkpoint.pt", weights_only=True, map_location="cpu")
        state.pop("config", None)
        print(f"{algo:24s} {digest(state)}", flush=True)


if __name__ == "__main__":
    main()
