"""What the toy tasks measure: returns of simple policies, and how far the tiny DreamerV2 gets online.

For each toy task of a pair: uniform random actions, the constant action (+1, +1), the best of 16 constant
directions, and the scripted expert (50 episodes each, seeds 0-49; the best constant direction over 20). With
``--learn N``, DreamerV2 (``--preset``, ``tiny`` unless given) also learns the pair's source task online for N
environment steps (``coworld collect`` with no stop return), evaluated every ``--eval-every`` steps (1,000) on 10
episodes.

``--pair corner`` (default): toy_reach and toy_reach_shifted. ``--pair centre``: toy_reach_centre and
toy_reach_centre_shifted, the goal at the centre, where a constant action cannot score, so a return above the random
policy's needs perception. (Before the centre tasks were registered, an option ``--goal 0 0`` moved the corner
pair's goal to the centre; that made the same envs, colours, dynamics and seeds.)

    MUJOCO_GL=egl .venv/bin/python benchmarks/toy_baselines.py --learn 8000
    MUJOCO_GL=egl .venv/bin/python benchmarks/toy_baselines.py --pair centre --learn 6000
    MUJOCO_GL=egl .venv/bin/python benchmarks/toy_baselines.py --pair centre --learn 4000 --preset cpu --eval-every 500
"""

from __future__ import annotations

import argparse
import json
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

import coworld.envs.toy as toy
from coworld import envs

PAIRS = {"corner": ("toy_reach", "toy_reach_shifted"), "centre": ("toy_reach_centre", "toy_reach_centre_shifted")}


def mean_return(task: str, policy: Callable[[object], np.ndarray], episodes: int) -> float:
    env = envs.make(task, seed=0)
    totals = []
    for episode in range(episodes):
        env.reset(seed=episode)
        total, done = 0.0, False
        while not done:
            _, reward, terminated, truncated, _ = env.step(policy(env))
            total += float(reward)
            done = terminated or truncated
        totals.append(total)
    env.close()
    return float(np.mean(totals))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pair", choices=sorted(PAIRS), default="corner", help="which toy pair")
    parser.add_argument("--learn", type=int, default=0, help="also train DreamerV2 online this many steps")
    parser.add_argument("--preset", default="tiny", help="config preset of the --learn run")
    parser.add_argument("--eval-every", type=int, default=1000, help="env steps between the --learn run's evaluations")
    parser.add_argument("--seed", type=int, default=0, help="seed of the --learn run")
    args = parser.parse_args()
    tasks = PAIRS[args.pair]
    print(f"goal at {tuple(toy.VARIANTS[tasks[0]].goal)}")
    print("| task | random | constant (+1, +1) | best constant | expert |")
    print("|---|---:|---:|---:|---:|")
    for task in tasks:
        rng = np.random.default_rng(0)
        directions = [np.array([np.cos(a), np.sin(a)]) for a in np.linspace(0, 2 * np.pi, 16, endpoint=False)]
        row = [
            mean_return(task, lambda env, rng=rng: rng.uniform(-1, 1, 2), 50),
            mean_return(task, lambda env: np.array([1.0, 1.0]), 50),
            max(mean_return(task, lambda env, d=d: d, 20) for d in directions),
            mean_return(task, lambda env: env.unwrapped.expert_action(), 50),
        ]
        print(f"| {task} | " + " | ".join(f"{value:.1f}" for value in row) + " |")
    if args.learn:
        from coworld.training.collect import collect_dreamerv2

        torch.set_num_threads(1)
        with tempfile.TemporaryDirectory() as folder:
            out = Path(folder) / f"{tasks[0]}.h5"
            overrides = [f"train.eval_every={args.eval_every}", "train.eval_episodes=10"]
            collect_dreamerv2(
                tasks[0], out, preset=args.preset, overrides=overrides, max_steps=args.learn, stop_return=1e9,
                device="cpu", progress=False, seed=args.seed,
            )  # fmt: skip
            records = [json.loads(line) for line in (Path(folder) / f"{tasks[0]}.run" / "metrics.jsonl").open()]
        curve = [(r["step"], r["eval/return"]) for r in records if "eval/return" in r]
        print(
            f"DreamerV2 ({args.preset} preset, seed {args.seed}) online on {tasks[0]}, evaluation return by env step:"
        )
        print(", ".join(f"{step}: {value:.1f}" for step, value in curve))


if __name__ == "__main__":
    main()
