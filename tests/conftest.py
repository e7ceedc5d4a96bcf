"""Fixtures shared across the test packages.

The suite runs on one torch (OpenMP) thread, in this process and in every CLI process it starts: tiny networks
gain little from a second thread, and two threads crawl when another job holds a core (benchmarks/RESULTS.md,
"Threads"). Tests about threads set their own count.
"""

from __future__ import annotations

import os

os.environ["OMP_NUM_THREADS"] = "1"  # before torch starts its thread pool; inherited by subprocesses
os.environ["MKL_NUM_THREADS"] = "1"

import dataclasses  # noqa: E402
from collections.abc import Iterator  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

from coworld import envs  # noqa: E402
from coworld.data import DatasetWriter  # noqa: E402


def write_toy_dataset(path: Path, task: str = "toy_reach", episodes: int = 4, seed: int = 0) -> Path:
    """Random-policy episodes of a toy task written with the real writer."""
    spec = envs.task_spec(task)
    env = envs.make(task, seed=seed)
    rng = np.random.default_rng(seed)
    with DatasetWriter(
        path,
        task=task,
        env_config=dataclasses.asdict(spec),
        quality="random",
        collector={"algorithm": "random", "seed": seed},
        action_size=spec.action_size,
    ) as writer:
        for episode in range(episodes):
            obs, _ = env.reset(seed=seed + episode)
            frames, actions, rewards = [obs], [], []
            done = False
            while not done:
                action = rng.uniform(-1, 1, spec.action_size).astype(np.float32)
                obs, reward, terminated, truncated, _ = env.step(action)
                frames.append(obs)
                actions.append(action)
                rewards.append(reward)
                done = terminated or truncated
            writer.add_episode(
                observations=np.stack(frames),
                actions=np.stack(actions),
                rewards=np.asarray(rewards, np.float32),
                terminated=bool(terminated),
            )
        writer.close(complete=True)
    env.close()
    return path


@pytest.fixture(scope="session", autouse=True)
def _one_torch_thread_for_the_session() -> Iterator[None]:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def toy_dataset_writer():
    """The function writing random-policy toy datasets: ``(path, task, episodes, seed) -> path``."""
    return write_toy_dataset


@pytest.fixture
def one_torch_thread() -> Iterator[None]:
    """One torch thread for the test, restored after: tiny networks gain little from a second one, and two crawl
    when another job holds a core (benchmarks/RESULTS.md, "Threads")."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
