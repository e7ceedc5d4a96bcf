"""The stand-in reference returns of tasks without a published DreamerV2 score (see coworld/envs/registry.py).

Meta-World: Meta-World's scripted expert on our task setup, ``--episodes`` episodes seeded 0, 1, ... (no frames
are drawn: the policies read the simulator state). Toy tasks: the scripted expert, 200 episodes.

    MUJOCO_GL=egl .venv/bin/python benchmarks/reference_returns.py --episodes 10

``--robodesk``: the RoboDesk tasks instead, both numbers the registry records for them: the random return
(episode ``i``: ``reset(seed=i)``, actions ``numpy.random.default_rng(i).uniform(-1, 1)``, as for every task) and
our waypoint policy's return (``coworld.envs.experts.ROBODESK_WAYPOINTS``), without drawing frames (the rewards
read the simulator state only).

    MUJOCO_GL=egl .venv/bin/python benchmarks/reference_returns.py --robodesk --episodes 10
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from coworld.envs.experts import METAWORLD_POLICIES, ROBODESK_WAYPOINTS, expert_returns, robodesk_random_returns


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--robodesk", action="store_true", help="the RoboDesk tasks' random and scripted returns")
    args = parser.parse_args()
    start = time.perf_counter()
    if args.robodesk:
        print("| task | random mean return | std | scripted mean return | std | success |")
        print("|---|---:|---:|---:|---:|---:|")
        for task in ROBODESK_WAYPOINTS:
            rand = robodesk_random_returns(task, args.episodes)
            returns, successes = expert_returns(task, args.episodes)
            print(
                f"| {task} | {np.mean(rand):.1f} | {np.std(rand):.1f} | {np.mean(returns):.1f} | {np.std(returns):.1f}"
                f" | {np.mean(successes):.0%} |"
            )
        print(f"\n{time.perf_counter() - start:.0f} s")
        return
    print("| task | expert mean return | std | success |")
    print("|---|---:|---:|---:|")
    for task in METAWORLD_POLICIES:
        returns, successes = expert_returns(task, args.episodes)
        print(f"| {task} | {np.mean(returns):.1f} | {np.std(returns):.1f} | {np.mean(successes):.0%} |")
    for task in ("toy_reach", "toy_reach_shifted"):
        returns, _ = expert_returns(task, 200)
        print(f"| {task} (200 episodes) | {np.mean(returns):.1f} | {np.std(returns):.1f} | - |")
    print(f"\n{time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
