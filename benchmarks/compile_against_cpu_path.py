"""Is the CPU fast path still worth a second form? Offline DreamerV2 through ``coworld train`` at the ``cpu`` preset,
``compile=true`` (the reference model compiled whole) against ``train.backend=cpu`` (the fast path, eager), each for
the same wall-clock budget, compilation included; it prints the updates each had made after every quarter of the
budget and their ratio.

    python benchmarks/compile_against_cpu_path.py DATASET.h5 OUT [--minutes 60] [--side-by-side]

``DATASET`` is any 64 x 64 dataset of a 6-d action task (e.g. ``coworld collect --task cheetah_uphill --policy random
--episodes 4``: the update's cost does not depend on the frames); ``OUT`` receives one run folder per side. With
``--side-by-side`` the two runs share the machine, each pinned to a core of its own (``taskset``); otherwise they run
one after the other. Each run is one torch thread, as the ``coworld`` command runs by default. Set
``TORCHINDUCTOR_CACHE_DIR`` to an empty folder to include compiling from scratch.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SIDES = {"compiled reference": ["compile=true"], "cpu path": ["train.backend=cpu"]}


def command(dataset: Path, run: Path, sets: list[str]) -> list[str]:
    args = [sys.executable, "-c", "from coworld.cli import run; run()", "train", "--algo", "dreamerv2"]
    args += ["--target", "cheetah_uphill", "--dataset", str(dataset), "--preset", "cpu", "--logdir", str(run)]
    args += ["--threads", "1", "--no-progress", "--device", "cpu"]
    for item in ["coworld.iterations=1", "coworld.target_updates=1000000", "train.log_every=25", *sets]:
        args += ["--set", item]
    return args


def updates_by(run: Path, seconds: float) -> int:
    """The updates a run had logged within ``seconds`` of its start (its log's ``time`` column)."""
    done = 0
    for line in (run / "metrics.jsonl").read_text().splitlines():
        row = json.loads(line)
        if row.get("unit") == "update" and row["time"] <= seconds:
            done = max(done, int(row["step"]))
    return done


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--minutes", type=float, default=60.0)
    parser.add_argument("--side-by-side", action="store_true")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    budget = 60.0 * args.minutes
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    runs = {name: args.out / name.replace(" ", "-") for name in SIDES}
    procs = []
    for core, (name, sets) in enumerate(SIDES.items()):
        pin = ["taskset", "-c", str(core)] if args.side_by_side else []
        log = open(args.out / f"{runs[name].name}.log", "w")  # noqa: SIM115 (closed with the process)
        print(f"{name}: started, load {os.getloadavg()[0]:.2f}", flush=True)
        proc = subprocess.Popen([*pin, *command(args.dataset, runs[name], sets)], env=env, stdout=log, stderr=log)
        procs.append(proc)
        if not args.side_by_side:
            try:
                proc.wait(timeout=budget)
            except subprocess.TimeoutExpired:
                proc.terminate()
                proc.wait()
    if args.side_by_side:
        time.sleep(budget)
        for proc in procs:
            proc.terminate()
            proc.wait()
    print("minutes  " + "  ".join(f"{name:>18}" for name in SIDES) + "   compiled / cpu path")
    for quarter in (0.25, 0.5, 0.75, 1.0):
        done = [updates_by(run, quarter * budget) for run in runs.values()]
        ratio = done[0] / done[1] if done[1] else float("nan")
        print(f"{quarter * args.minutes:7.1f}  " + "  ".join(f"{d:>18,}" for d in done) + f"   {ratio:.3f}")


if __name__ == "__main__":
    main()
