"""Fixtures for the DreamerV2 model tests: the tiny preset and random batches in the replay convention."""

from __future__ import annotations

import pytest
import torch

from coworld.config import Config, make_config

ACTION_SIZE = 3


@pytest.fixture(autouse=True)
def _seeded_single_thread(one_torch_thread: None) -> None:
    torch.manual_seed(0)


@pytest.fixture
def tiny() -> Config:
    return make_config("tiny")


def random_batch(batch: int = 2, length: int = 5, action_size: int = ACTION_SIZE) -> dict[str, torch.Tensor]:
    """A batch of random torch tensors: uint8 images ``(B, T, 64, 64, 3)``, one episode start per row."""
    is_first = torch.zeros(batch, length, dtype=torch.bool)
    is_first[:, 0] = True
    action = torch.rand(batch, length, action_size) * 2 - 1
    action[is_first] = 0.0
    is_terminal = torch.zeros(batch, length, dtype=torch.bool)
    is_terminal[0, -1] = True
    return {
        "image": torch.randint(0, 256, (batch, length, 64, 64, 3), dtype=torch.uint8),
        "action": action,
        "reward": torch.randn(batch, length),
        "is_first": is_first,
        "is_last": is_terminal.clone(),
        "is_terminal": is_terminal,
    }
