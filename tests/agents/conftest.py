"""Fixtures of the agent tests."""

from __future__ import annotations

import importlib.util
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
import torch


@pytest.fixture(scope="session")
def toy_expert() -> ModuleType:
    """tests/agents/toy_expert.py: scripted toy_reach datasets (``write_dataset``) and ``mean_return``."""
    spec = importlib.util.spec_from_file_location("toy_expert", Path(__file__).with_name("toy_expert.py"))
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def make_numpy_batch(rng: np.random.Generator, B: int = 2, T: int = 6) -> dict[str, np.ndarray]:
    """A random 2-d-action batch as a dataset sampler gives it (numpy; uint8 images, ``is_first`` on each window's
    first step), drawn from ``rng``."""
    is_first = np.zeros((B, T), bool)
    is_first[:, 0] = True
    return {
        "image": rng.integers(0, 256, (B, T, 64, 64, 3), dtype=np.uint8),
        "action": rng.uniform(-1, 1, (B, T, 2)).astype(np.float32),
        "reward": rng.standard_normal((B, T)).astype(np.float32),
        "is_first": is_first,
        "is_last": np.zeros((B, T), bool),
        "is_terminal": np.zeros((B, T), bool),
    }


@pytest.fixture(scope="session")
def numpy_batch() -> Callable[..., dict[str, np.ndarray]]:
    """:func:`make_numpy_batch`: ``(rng, B=2, T=6) -> batch``."""
    return make_numpy_batch


@pytest.fixture(scope="session")
def flat_params() -> Callable[[torch.nn.Module], torch.Tensor]:
    """``module -> tensor``: a copy of all of ``module``'s parameters, flattened into one vector."""
    return lambda module: torch.cat([p.detach().reshape(-1).clone() for p in module.parameters()])


def make_target_batch(b: int = 3, t: int = 4, action_size: int = 2) -> dict[str, torch.Tensor]:
    """A random batch in the replay convention: uint8 images ``(B, T, 64, 64, 3)``, actions in [-1, 1], rewards in
    [0, 1), each window starting fresh (``is_first`` on its first step). Draws from torch's default generator."""
    batch = {
        "image": torch.randint(0, 256, (b, t, 64, 64, 3), dtype=torch.uint8),
        "action": torch.rand(b, t, action_size) * 2 - 1,
        "reward": torch.rand(b, t),
        "is_first": torch.zeros(b, t, dtype=torch.bool),
        "is_last": torch.zeros(b, t, dtype=torch.bool),
        "is_terminal": torch.zeros(b, t, dtype=torch.bool),
    }
    batch["is_first"][:, 0] = True
    return batch


@pytest.fixture(scope="session")
def target_batch() -> Callable[..., dict[str, torch.Tensor]]:
    """:func:`make_target_batch`: ``(b, t, action_size) -> batch``."""
    return make_target_batch


TOY_SCHEDULE = (
    "device=cpu",
    "train.prefill=50",
    "train.pretrain_updates=2",
    "train.train_every=5",
    "train.eval_episodes=1",
    "coworld.pretrain_steps=100",
    "coworld.iterations=2",
    "coworld.target_updates=2",
    "coworld.source_updates=15",
)
"""A whole CoWorld run in seconds: 2 + (100 - 50) / 5 + 1 = 13 pretraining updates, then 2 iterations of 2 target
and 15 source updates."""


@pytest.fixture(scope="session")
def toy_schedule() -> list[str]:
    """:data:`TOY_SCHEDULE`, the overrides of a CoWorld run in seconds."""
    return list(TOY_SCHEDULE)


@pytest.fixture(scope="session")
def coworld_toy_job() -> Callable[..., Any]:
    """``(dataset, logdir, overrides, target=..., **check_job's other arguments) -> job``: a checked CoWorld job on
    toy_reach -> toy_reach_shifted (or ``target``), tiny preset, seed 0."""
    from coworld.training.train import check_job

    def job(dataset: Path, logdir: Path, overrides: list[str], target: str = "toy_reach_shifted", **extra: Any) -> Any:
        return check_job(
            algo="coworld",
            source="toy_reach",
            target=target,
            dataset=dataset,
            preset="tiny",
            logdir=logdir,
            seed=0,
            device="cpu",
            overrides=overrides,
            **extra,
        )

    return job
