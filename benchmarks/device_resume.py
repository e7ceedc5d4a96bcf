"""Resumes on a device: ``coworld train`` killed (SIGKILL) after its checkpoints and rerun, against the same command
never killed, on the device given (``cuda`` on a GPU machine; ``cpu`` is the reference, where they end equal).

The run is the fault-injection test's CoWorld command (tests/test_kill.py: the tiny preset on the toy pair, an
online source phase and offline target phases) with ``--device`` swapped in, on a dataset of random toy episodes
collected first. It prints one JSON line per step and a last one with the keys of the final checkpoints that
differ from the never-killed run's and the largest differences. On a CPU a resume is exact: no leaf differs. A
GPU's kernels need not be bitwise deterministic, so the never-killed command runs twice: the differences between
those two are the device's own, the yardstick for the resumed run's.

Usage::

    python benchmarks/device_resume.py --device cuda --dir OUT/resume --json OUT/device_resume.json
    python benchmarks/device_resume.py --device cpu --dir /tmp/resume      # the reference, on any machine
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from coworld.training.checkpoint import load_checkpoint

CLI = [sys.executable, "-c", "from coworld.cli import main; main()"]
TRAIN = (
    "train --algo coworld --target toy_reach_shifted --source toy_reach --preset tiny --no-progress"
    " --set train.eval_episodes=1 --set train.prefill=100 --set coworld.pretrain_steps=200"
    " --set coworld.iterations=3 --set coworld.target_updates=10 --set coworld.source_updates=10"
).split()


def emit(record: dict[str, Any]) -> None:
    print(json.dumps(record), flush=True)


def run(args: list[str], timeout: float) -> float:
    start = time.perf_counter()
    done = subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=timeout)
    if done.returncode:
        sys.exit(f"coworld {' '.join(args[:2])} failed (exit {done.returncode}): {done.stderr[-3000:]}")
    return time.perf_counter() - start


def killed_run(args: list[str], checkpoint: Path, kills: int, rng: np.random.Generator, timeout: float) -> list[int]:
    """Start ``args``, SIGKILL it a random moment after each new checkpoint, ``kills`` times; the iterations the
    checkpoints had reached."""
    reached = []
    for _ in range(kills):
        mtime = checkpoint.stat().st_mtime_ns if checkpoint.exists() else None
        proc = subprocess.Popen(
            [*CLI, *args], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True
        )
        deadline = time.monotonic() + timeout
        while not (checkpoint.exists() and checkpoint.stat().st_mtime_ns != mtime):
            if proc.poll() is not None or time.monotonic() > deadline:
                proc.kill()
                err = proc.stderr.read().decode()[-3000:] if proc.stderr else ""
                sys.exit(f"the run ended (exit {proc.returncode}) before a new checkpoint: {err}")
            time.sleep(0.05)
        time.sleep(float(rng.uniform(0.0, 2.0)))
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
        reached.append(int(load_checkpoint(checkpoint)["progress"]["iteration"]))
    return reached


def differences(a: Any, b: Any, key: str = "") -> dict[str, float]:
    """Every leaf of two nested states that differs: its path and largest absolute difference (inf: structure)."""
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return {key or "/": float("inf")}
        return {k: v for name in a for k, v in differences(a[name], b[name], f"{key}/{name}").items()}
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if len(a) != len(b):
            return {key: float("inf")}
        pairs = enumerate(zip(a, b, strict=True))
        return {k: v for i, (x, y) in pairs for k, v in differences(x, y, f"{key}/{i}").items()}
    if isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor):
        if a.shape != b.shape or a.dtype != b.dtype:
            return {key: float("inf")}
        return {} if torch.equal(a, b) else {key: float((a.double() - b.double()).abs().max())}
    return {} if a == b else {key: float("inf")}


def summary(diff: dict[str, float]) -> dict[str, Any]:
    worst = sorted(diff.items(), key=lambda kv: -kv[1])[:5]
    floats = [v for k, v in diff.items() if not k.endswith("/obs")]  # frames: whole pixel values apart
    return {"leaves_differing": len(diff), "largest_not_frames": max(floats, default=0.0), "largest": worst}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--dir", required=True, help="a new folder for the dataset and the runs")
    parser.add_argument("--kills", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--timeout", type=float, default=300.0, help="seconds each command may take")
    parser.add_argument("--json", help="also write every record to this file")
    args = parser.parse_args()
    root = Path(args.dir)
    root.mkdir(parents=True, exist_ok=False)
    records: list[dict[str, Any]] = []

    def record(**r: Any) -> None:
        records.append(r)
        emit(r)

    dataset = root / "toy.h5"
    collect = ["collect", "--policy", "random", "--task", "toy_reach_shifted", "--episodes", "20", "--quiet"]
    record(step="collect", seconds=run([*collect, "--out", str(dataset)], args.timeout))
    train = [*TRAIN, "--device", args.device, "--threads", str(args.threads), "--dataset", str(dataset)]
    killed = root / "killed"
    rng = np.random.default_rng(0)
    start = time.perf_counter()
    reached = killed_run([*train, "--logdir", str(killed)], killed / "checkpoint.pt", args.kills, rng, args.timeout)
    record(step="killed", iterations_at_kills=reached, seconds=time.perf_counter() - start)
    record(step="resumed to the end", seconds=run([*train, "--logdir", str(killed)], args.timeout))
    for name in ("whole", "whole-again"):
        record(step=name, seconds=run([*train, "--logdir", str(root / name)], args.timeout))
    final = {name: load_checkpoint(root / name / "checkpoint.pt") for name in ("killed", "whole", "whole-again")}
    own = differences(final["whole"], final["whole-again"])
    resumed = differences(final["killed"], final["whole"])
    record(step="compare", resumed_vs_whole=summary(resumed), whole_vs_again=summary(own))
    if torch.cuda.is_available() and args.device.startswith("cuda"):
        record(step="device", gpu=torch.cuda.get_device_name(), torch=torch.__version__)
    if args.json:
        Path(args.json).write_text(json.dumps({"records": records}, indent=1))


if __name__ == "__main__":
    main()
