"""Scripted toy_reach data and a return measure shared by the offline baselines' learning tests."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from coworld.data import DatasetWriter
from coworld.envs import make

Policy = Callable[[np.ndarray, object, np.ndarray], tuple[np.ndarray, object]]


def write_dataset(path: Path, *, episodes: int, noise: float, seed: int) -> float:
    """Scripted toy_reach data (the env's head-for-the-goal action plus Gaussian noise); returns the mean return."""
    env = make("toy_reach", seed=seed)
    rng = np.random.default_rng(seed)
    returns = []
    with DatasetWriter(
        path,
        task="toy_reach",
        env_config={"task": "toy_reach"},
        quality="expert",
        collector={"algorithm": "scripted expert", "action_noise": noise, "seed": seed},
        action_size=2,
    ) as writer:
        for _ in range(episodes):
            obs, _ = env.reset()
            frames, actions, rewards = [obs], [], []
            done = False
            while not done:
                action = env.unwrapped.expert_action() + noise * rng.standard_normal(2)
                action = np.clip(action, -1, 1).astype(np.float32)
                obs, reward, terminated, truncated, _ = env.step(action)
                frames.append(obs), actions.append(action), rewards.append(reward)
                done = terminated or truncated
            writer.add_episode(np.stack(frames), np.stack(actions), np.array(rewards), terminated=False)
            returns.append(sum(rewards))
        writer.close(complete=True)
    return float(np.mean(returns))


def mean_return(policy: Policy, *, episodes: int, seed: int) -> float:
    """Mean return of ``policy`` on toy_reach, driven the way the evaluation loop drives every agent."""
    env = make("toy_reach", seed=seed)
    returns = []
    for _ in range(episodes):
        obs, _ = env.reset()
        state, first, total, done = None, True, 0.0, False
        while not done:
            action, state = policy(obs[None], state, np.array([first]))
            obs, reward, terminated, truncated, _ = env.step(action[0])
            total, first, done = total + reward, False, terminated or truncated
        returns.append(total)
    return float(np.mean(returns))
