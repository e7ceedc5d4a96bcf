"""The online loop: where the acting side starts episodes, the train ratio across resumes and phase boundaries."""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from coworld import envs
from coworld.config import make_config
from coworld.data import DatasetWriter, open_dataset
from coworld.data.collect import dataset_fields
from coworld.training.logger import Logger
from coworld.training.online import OnlineTrainer

NEVER = str(10**9)


class ProbeAgent:
    """Acts uniformly at random and records what the loop tells it; counts its updates."""

    def __init__(self, action_size: int, crash_after: int | None = None) -> None:
        self.action_size = action_size
        self.calls: list[tuple[np.ndarray, np.ndarray]] = []  # (obs, is_first) per policy call
        self.trained = 0
        self.crash_after = crash_after
        self.rng = np.random.default_rng(0)

    def policy(self, obs: np.ndarray, state: Any = None, mode: str = "train", is_first: Any = None, generator=None):
        self.calls.append((obs.copy(), np.asarray(is_first, bool).copy()))
        return self.rng.uniform(-1, 1, (len(obs), self.action_size)).astype(np.float32), state

    def policy_copy(self) -> ProbeAgent:
        return self  # acts with no weights, so the copy may be the agent itself

    def train(self, batch: dict[str, np.ndarray]) -> dict[str, float]:
        if self.crash_after is not None and self.trained >= self.crash_after:
            raise RuntimeError("simulated crash")
        self.trained += 1
        return {"probe/loss": 0.0}

    def state_dict(self) -> dict[str, Any]:
        return {"trained": self.trained}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.trained = int(state["trained"])


def trainer(tmp_path: Path, agent: ProbeAgent, overrides: list[str], writer: DatasetWriter, logger: Logger):
    config = make_config("tiny", ["device=cpu", f"train.eval_every={NEVER}", *overrides])
    return OnlineTrainer(agent=agent, task="toy_reach", config=config, logdir=tmp_path, writer=writer, logger=logger)


def open_writer(path: Path, resume: bool = False) -> DatasetWriter:
    fields = dataset_fields("toy_reach")
    return DatasetWriter(
        path, task="toy_reach", quality="medium-replay", collector={}, action_size=2, resume=resume, **fields
    )


def test_the_policy_starts_a_latent_with_the_first_frame_of_every_episode_and_only_there(tmp_path: Path) -> None:
    agent = ProbeAgent(envs.task_spec("toy_reach").action_size)
    overrides = ["train.envs=2", f"train.prefill={NEVER}", f"train.checkpoint_every={NEVER}"]
    with open_writer(tmp_path / "d.h5") as writer, Logger(tmp_path, outputs=()) as logger:
        loop = trainer(tmp_path, agent, overrides, writer, logger)
        try:
            loop.run(max_steps=260, progress=False)  # 2 envs x 130 steps: 2 whole 50-step episodes each, and more
        finally:
            loop.close()
    with open_dataset(tmp_path / "d.h5") as data:
        firsts = [data.episode(i)["image"][0].tobytes() for i in range(data.num_episodes)]
        lasts = {data.episode(i)["image"][-1].tobytes() for i in range(data.num_episodes)}
        assert data.num_episodes >= 4
    flagged = [obs[i].tobytes() for obs, first in agent.calls for i in np.flatnonzero(first)]
    unflagged = [obs[i].tobytes() for obs, first in agent.calls for i in np.flatnonzero(~first)]
    assert set(firsts) <= set(flagged)  # every stored episode began a new latent at its first frame
    assert len(flagged) == len(set(flagged))  # once each
    assert not set(flagged) & lasts  # never with an episode's final frame
    assert not set(unflagged) & set(firsts)  # and no first frame went by without the flag


def test_updates_due_follow_dreamerv2s_prefill_pretrain_and_train_ratio(tmp_path: Path) -> None:
    overrides = ["train.prefill=100", "train.pretrain_updates=7", "train.train_every=5"]
    with open_writer(tmp_path / "d.h5") as writer, Logger(tmp_path, outputs=()) as logger:
        loop = trainer(tmp_path, ProbeAgent(2), overrides, writer, logger)
        due = [loop.updates_due(steps) for steps in (0, 99, 100, 104, 105, 200)]
    assert due == [0, 0, 8, 8, 9, 28]  # none in the prefill; 7 pretraining + 1 at its end; then 1 per 5 steps


def test_a_resumed_run_keeps_the_train_ratio_instead_of_bursting(tmp_path: Path) -> None:
    overrides = ["train.prefill=50", "train.train_every=5", "train.pretrain_updates=3", "train.checkpoint_every=100"]
    agent = ProbeAgent(2, crash_after=45)  # crashes well after its last checkpoint
    with open_writer(tmp_path / "d.h5") as writer, Logger(tmp_path, outputs=()) as logger:
        loop = trainer(tmp_path, agent, overrides, writer, logger)
        with pytest.raises(RuntimeError, match="simulated crash"):
            loop.run(max_steps=400, progress=False)
        loop.close()
        crashed_at = loop.steps
    # Start again as `coworld collect --resume` does: agent and counters from the checkpoint, steps from the data.
    agent = ProbeAgent(2)
    updates_per_step: list[int] = []
    with open_writer(tmp_path / "d.h5", resume=True) as writer, Logger(tmp_path, outputs=()) as logger:
        loop = trainer(tmp_path, agent, overrides, writer, logger)
        loop.restore()
        resumed = (loop.steps, loop.updates)
        assert loop.updates < loop.updates_due(loop.steps)  # the updates since the checkpoint were lost
        original = loop._train_due

        def counting() -> None:
            before = loop.updates
            original()
            updates_per_step.append(loop.updates - before)

        loop._train_due = counting  # type: ignore[method-assign]
        try:
            loop.run(max_steps=400, progress=False)
        finally:
            loop.close()
    assert resumed[0] <= crashed_at and max(updates_per_step) == 1  # no catch-up burst
    # ... and the ratio holds from the restored state on: one update per train_every steps.
    assert loop.updates - resumed[1] == pytest.approx((400 - resumed[0]) / 5, abs=1)


def test_pretraining_without_cut_leaves_no_mark_in_the_episodes(tmp_path: Path) -> None:
    overrides = [f"train.prefill={NEVER}", f"train.checkpoint_every={NEVER}"]
    agent = ProbeAgent(2)
    with open_writer(tmp_path / "d.h5") as writer, Logger(tmp_path, outputs=()) as logger:
        loop = trainer(tmp_path, agent, overrides, writer, logger)
        try:
            loop.run(max_steps=70, progress=False, cut_episodes=False)  # a phase boundary inside episode 2
            loop.run(max_steps=200, progress=False)
        finally:
            loop.close()
    with open_dataset(tmp_path / "d.h5") as data:
        assert list(data.lengths) == [50, 50, 50, 50]  # no episode cut at 70, no transition dropped


def test_running_episodes_replayed_to_other_frames_say_so_and_go_on_from_the_replayed_ones(tmp_path: Path) -> None:
    """A checkpoint taken inside episode 2 holds its seed and 20 actions; resumed, the trainer makes it again and goes
    on from there (the episode ends whole at 50 steps). Where the replayed frames are not the checkpoint's (here: its
    last frame altered, as another simulator build would give), a warning says so and the episode still goes on."""
    import torch

    overrides = [f"train.prefill={NEVER}", f"train.checkpoint_every={NEVER}"]
    with open_writer(tmp_path / "d.h5") as writer, Logger(tmp_path, outputs=()) as logger:
        loop = trainer(tmp_path, ProbeAgent(2), overrides, writer, logger)
        try:
            loop.run(max_steps=70, progress=False, cut_episodes=False)  # saves, 20 steps into episode 2
        finally:
            loop.close()
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    assert state["steps"] == 70 and len(state["acting"]["actions"][0]) == 20
    state["acting"]["obs"] = 255 - state["acting"]["obs"]
    torch.save(state, tmp_path / "checkpoint.pt")
    with open_writer(tmp_path / "d.h5", resume=True) as writer, Logger(tmp_path, outputs=()) as logger:
        loop = trainer(tmp_path, ProbeAgent(2), overrides, writer, logger)
        loop.restore(rollback=True)
        assert loop.steps == 70
        try:
            with pytest.warns(UserWarning, match="other frames than the checkpoint's"):
                loop.run(max_steps=100, progress=False, cut_episodes=False)
        finally:
            loop.close()
    with open_dataset(tmp_path / "d.h5") as data:
        assert list(data.lengths) == [50, 50]


def _dreamer_run(tmp_path: Path, in_thread: bool) -> tuple[OnlineTrainer, dict[str, Any], dict[str, np.ndarray]]:
    """A tiny DreamerV2 trained online on toy_reach for 300 steps with ``train.background_updates``, its updates on
    their thread or (``in_thread=False``) in turn; returns the loop, the agent's weights and the data."""
    from coworld.agents.dreamerv2 import DreamerV2
    from coworld.training.online import Updates
    from coworld.training.run import seed_everything

    overrides = [
        "train.background_updates=true",
        "train.prefill=100",
        "train.pretrain_updates=3",
        "train.train_every=5",
        "train.checkpoint_every=150",
        "train.eval_every=200",
        "train.eval_episodes=1",
    ]
    config = make_config("tiny", ["device=cpu", *overrides])
    seed_everything(config.seed)
    agent = DreamerV2(config=config, action_size=2, device="cpu")
    with open_writer(tmp_path / "d.h5") as writer, Logger(tmp_path, outputs=()) as logger:
        loop = OnlineTrainer(
            agent=agent, task="toy_reach", config=config, logdir=tmp_path, writer=writer, logger=logger
        )
        loop._updates = Updates(in_thread=in_thread)
        try:
            loop.run(max_steps=300, progress=False)
        finally:
            loop.close()
    with open_dataset(tmp_path / "d.h5") as data:
        episodes = [data.episode(i) for i in range(data.num_episodes)]
    columns = {key: np.concatenate([episode[key] for episode in episodes]) for key in ("image", "action", "reward")}
    return loop, agent.state_dict(), columns


def test_updates_beside_acting_record_the_same_data_and_train_the_same_weights_as_in_turn(tmp_path: Path) -> None:
    import torch

    in_turn, in_turn_weights, in_turn_data = _dreamer_run(tmp_path / "in_turn", in_thread=False)
    beside, beside_weights, beside_data = _dreamer_run(tmp_path / "beside", in_thread=True)
    # the ratio: every update due by the last step was made, in both
    assert beside.steps == in_turn.steps == 300
    assert beside.updates == in_turn.updates == beside.updates_due(300) == 3 + (300 - 100) // 5 + 1
    assert in_turn.last_eval is not None and beside.last_eval == in_turn.last_eval  # evaluation ran between updates
    for key in in_turn_data:
        np.testing.assert_array_equal(beside_data[key], in_turn_data[key], err_msg=key)
    assert len(np.unique(in_turn_data["action"][100:], axis=0)) > 100  # the trained policy acted, sampling
    for group in ("world_model", "actor_critic"):
        for name, tensor in in_turn_weights[group].items():
            assert torch.equal(beside_weights[group][name], tensor), f"{group}.{name}"


class OverlapProbe(ProbeAgent):
    """Each update waits (up to 5 s) for the agent to act after it started, and records whether it did."""

    def __init__(self) -> None:
        super().__init__(2)
        self.acted = threading.Event()
        self.overlapped: list[bool] = []
        self.threads: set[str] = set()

    def policy(self, *args: Any, **kwargs: Any):
        self.acted.set()
        return super().policy(*args, **kwargs)

    def train(self, batch: dict[str, np.ndarray]) -> dict[str, float]:
        self.threads.add(threading.current_thread().name)
        self.acted.clear()
        self.overlapped.append(self.acted.wait(timeout=5))
        return super().train(batch)


def test_updates_beside_acting_run_while_the_agent_steps_at_the_same_ratio(tmp_path: Path) -> None:
    agent = OverlapProbe()
    overrides = ["train.background_updates=true", "train.prefill=50", "train.pretrain_updates=0", "train.train_every=5"]
    with open_writer(tmp_path / "d.h5") as writer, Logger(tmp_path, outputs=()) as logger:
        loop = trainer(tmp_path, agent, [*overrides, f"train.checkpoint_every={NEVER}"], writer, logger)
        try:
            loop.run(max_steps=200, progress=False, cut_episodes=False)
        finally:
            loop.close()
    assert agent.threads == {"coworld-update"}  # never on the acting thread
    assert agent.trained == loop.updates == loop.updates_due(loop.steps) == 1 + 150 // 5  # each ended, at the ratio
    assert all(agent.overlapped[:-1])  # the agent acted during every update but the last, which the run's end awaits


class CountingProbe(ProbeAgent):
    """Its update's metric is the number of updates made so far."""

    def train(self, batch: dict[str, np.ndarray]) -> dict[str, float]:
        super().train(batch)
        return {"probe/updates": float(self.trained)}


def test_beside_acting_the_update_a_checkpoint_waits_for_is_logged(tmp_path: Path) -> None:
    agent = CountingProbe(2)
    overrides = ["train.background_updates=true", "train.prefill=50", "train.pretrain_updates=0", "train.train_every=5"]
    overrides += ["train.checkpoint_every=50", f"train.log_every={NEVER}"]  # one record, at the end of the run
    with open_writer(tmp_path / "d.h5") as writer, Logger(tmp_path, outputs=("jsonl",)) as logger:
        loop = trainer(tmp_path, agent, overrides, writer, logger)
        try:
            loop.run(max_steps=200, progress=False, cut_episodes=False)  # the last update starts at the last step,
        finally:  # which ends an episode: the checkpoint there waits for it
            loop.close()
    records = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    logged = [record["probe/updates"] for record in records if "probe/updates" in record]
    assert loop.updates == 1 + 150 // 5
    assert logged == [loop.updates]  # the last update's metrics, not the one's before it


def test_a_checkpoint_from_before_this_release_is_refused_in_one_line(tmp_path: Path) -> None:
    """An online run's checkpoint without acting's generator (written before acting had one) is not resumed with a
    fresh one: one line says to train again or to resume it with the coworld that wrote it."""
    import torch

    from coworld.errors import CheckpointError

    overrides = ["train.prefill=50", "train.pretrain_updates=0", "train.train_every=5"]
    with open_writer(tmp_path / "d.h5") as writer, Logger(tmp_path, outputs=()) as logger:
        loop = trainer(tmp_path, ProbeAgent(2), overrides, writer, logger)
        try:
            loop.run(max_steps=60, progress=False)
        finally:
            loop.close()
    path = tmp_path / "checkpoint.pt"
    state = torch.load(path, weights_only=True)
    del state["act_rng"]
    torch.save(state, path)
    with open_writer(tmp_path / "d.h5", resume=True) as writer, Logger(tmp_path, outputs=()) as logger:
        with pytest.raises(CheckpointError, match=r"was written by an earlier coworld \(no 'act_rng' entry\)"):
            trainer(tmp_path, ProbeAgent(2), overrides, writer, logger).restore()
