"""The offline trainer's batch stream: made ahead on a background thread, the same batches in the same order."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from coworld.config import make_config
from coworld.data import open_dataset
from coworld.errors import TrainingDiverged
from coworld.training.logger import Logger
from coworld.training.offline import OfflineSchedule, OfflineTrainer


class Recorder:
    """An agent that keeps each batch it trains on; its ``prepare`` notes the thread it ran on."""

    def __init__(self) -> None:
        self.batches: list[dict[str, Any]] = []

    def prepare(self, batch: dict[str, np.ndarray]) -> dict[str, Any]:
        return {**batch, "prepared_on": threading.current_thread().name}

    def train(self, batch: dict[str, Any]) -> dict[str, float]:
        self.batches.append(batch)
        return {"loss": 0.0}

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        pass


def _run(path: Path, logdir: Path, prefetch: bool) -> list[dict[str, Any]]:
    config = make_config("tiny")
    agent = Recorder()
    schedule = OfflineSchedule(updates=7, log_every=2, eval_every=100, eval_episodes=1, checkpoint_every=3)
    with open_dataset(path) as dataset, Logger(logdir) as logger:
        trainer = OfflineTrainer(
            agent=agent,
            kind="recorder",
            task="toy_reach",
            config=config,
            schedule=schedule,
            logdir=logdir,
            logger=logger,
            make_sampler=lambda seed: iter(dataset.sampler(4, 8, seed=seed)),
            prefetch=prefetch,
            prepare=agent.prepare,
        )

        def evaluate() -> None:  # no environment here: the batch stream is what is under test
            trainer.last_eval = 0.0

        trainer.evaluate = evaluate  # type: ignore[method-assign]
        trainer.run(progress=False)
    return agent.batches


def test_prefetching_trains_on_the_same_batches_in_the_same_order(tmp_path: Path, toy_dataset_writer) -> None:
    path = toy_dataset_writer(tmp_path / "toy.h5")
    plain = _run(path, tmp_path / "plain", prefetch=False)
    ahead = _run(path, tmp_path / "ahead", prefetch=True)
    assert len(plain) == len(ahead) == 7  # across two checkpoints, where each chunk's sampler is seeded anew
    for a, b in zip(plain, ahead, strict=True):
        assert set(a) == {*b} - {"prepared_on"}
        for key in a:
            np.testing.assert_array_equal(a[key], b[key])
    assert {b["prepared_on"] for b in ahead} == {"coworld-prefetch_0"}
    assert not [t for t in threading.enumerate() if t.name.startswith("coworld-prefetch")]
    assert not np.array_equal(plain[0]["image"], plain[1]["image"])  # batches that differ, so the order counts


class Diverging(Recorder):
    """An agent whose loss stops being a number at its fourth update."""

    def train(self, batch: dict[str, Any]) -> dict[str, float]:
        super().train(batch)
        return {"wm/loss": float("nan") if len(self.batches) >= 4 else 1.0, "actor/entropy": 0.5}


def test_a_loss_that_stops_being_a_number_stops_the_run_before_its_weights_are_kept(
    tmp_path: Path, toy_dataset_writer
) -> None:
    path = toy_dataset_writer(tmp_path / "d.h5", "toy_reach", episodes=2)
    config = make_config("tiny")
    agent = Diverging()
    schedule = OfflineSchedule(updates=7, log_every=1, eval_every=100, eval_episodes=1, checkpoint_every=3)
    saved: list[int] = []
    with open_dataset(path) as dataset, Logger(tmp_path / "run") as logger:
        trainer = OfflineTrainer(
            agent=agent,
            kind="recorder",
            task="toy_reach",
            config=config,
            schedule=schedule,
            logdir=tmp_path / "run",
            logger=logger,
            make_sampler=lambda seed: iter(dataset.sampler(4, 8, seed=seed)),
        )
        trainer.save = lambda: saved.append(trainer.updates)  # type: ignore[method-assign]
        expected = r"^the agent's world-model loss \(wm/loss\) became nan at update 4 \(offline training\); lower"
        with pytest.raises(TrainingDiverged, match=expected):
            trainer.run(progress=False)
    assert saved == [3] and len(agent.batches) == 4  # the checkpoint of update 3 is the last; nothing after it
