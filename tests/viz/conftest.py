"""Fixtures for the viz tests: tiny untrained agents and synthetic run folders (no training needed)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from coworld.config import make_config
from coworld.envs import task_spec

TARGET, SOURCE = "toy_reach_shifted", "toy_reach"


@pytest.fixture(autouse=True)
def _single_thread(one_torch_thread: None) -> None:
    torch.manual_seed(0)


def tiny_agent(seed: int = 0):
    from coworld.agents.dreamerv2 import DreamerV2

    torch.manual_seed(seed)
    return DreamerV2(config=make_config("tiny"), action_size=task_spec(TARGET).action_size, device="cpu")


def contains(canvas: np.ndarray, patch: np.ndarray) -> bool:
    """Whether ``patch`` appears pixel for pixel somewhere in ``canvas`` (both uint8 (H, W, 3))."""
    scores = cv2.matchTemplate(canvas.astype(np.float32), patch.astype(np.float32), cv2.TM_SQDIFF)
    y, x = np.unravel_index(np.argmin(scores), scores.shape)  # the best match, then checked exactly
    return bool((canvas[y : y + patch.shape[0], x : x + patch.shape[1]] == patch).all())


def make_run(root: Path, algo: str, dataset: Path, seed: int = 0) -> Path:
    """A run folder as `coworld train` leaves it, holding untrained tiny agents."""
    from coworld.training.checkpoint import save_checkpoint
    from coworld.training.run import prepare_run_dir

    logdir = root / algo
    info = {"algo": algo, "source": SOURCE if algo == "coworld" else None, "target": TARGET, "dataset": str(dataset)}
    prepare_run_dir(logdir, make_config("tiny"), {**info, "preset": "tiny"})
    if algo in ("curl", "curl-cql"):
        from coworld.agents.curl import Curl

        agent = Curl(config=make_config("tiny"), action_size=2, device="cpu", cql=algo == "curl-cql")
        save_checkpoint(logdir / "checkpoint.pt", {"kind": algo, "agent": agent.state_dict(), "updates": 0})
        return logdir
    state = {"kind": "coworld" if algo == "coworld" else "dreamerv2-offline", "agent": tiny_agent(seed).state_dict()}
    if algo == "coworld":
        state["source"] = tiny_agent(seed + 1).state_dict()
    save_checkpoint(logdir / "checkpoint.pt", state)
    return logdir


@pytest.fixture(scope="session")
def target_dataset(tmp_path_factory, toy_dataset_writer) -> Path:
    return toy_dataset_writer(tmp_path_factory.mktemp("viz") / "target.h5", TARGET, episodes=4)


@pytest.fixture(scope="session")
def source_dataset(tmp_path_factory, toy_dataset_writer) -> Path:
    return toy_dataset_writer(tmp_path_factory.mktemp("viz") / "source.h5", SOURCE, episodes=3, seed=7)
