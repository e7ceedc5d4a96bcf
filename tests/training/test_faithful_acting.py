"""DreamerV2 as its authors run it, where our loop used to differ (issue: agents that learn, smaller findings).

Each test fails on the code before the fix: the discount head halving imagination's discount from the start,
exploration noise added a second time outside the agent, the slow critic copied before the optimiser step, sampled
windows that start mid-episode with a real previous action, the prefill-to-training switch restarting the latent
mid-episode, and the collector's own agent that could not be evaluated.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from coworld.agents.dreamerv2 import DreamerV2
from coworld.cli import main
from coworld.config import make_config
from coworld.data import DatasetWriter, open_dataset
from coworld.data.collect import dataset_fields
from coworld.models.actor_critic import flatten_states
from coworld.training.logger import Logger
from coworld.training.online import OnlineTrainer
from coworld.training.replay import Replay
from coworld.training.run import load_run

pytestmark = pytest.mark.usefixtures("one_torch_thread")
NEVER = str(10**9)


def _writer(path: Path) -> DatasetWriter:
    fields = dataset_fields("toy_reach")
    return DatasetWriter(path, task="toy_reach", quality="medium-replay", collector={}, action_size=2, **fields)


@pytest.mark.parametrize("preset", ["paper", "tiny"])
def test_imagination_starts_with_the_full_discount(preset: str) -> None:
    torch.manual_seed(0)
    config = make_config(preset, ["device=cpu"] + (["world_model.cnn_depth=4"] if preset == "paper" else []))
    agent = DreamerV2(config=config, action_size=2)
    start = flatten_states(agent.world_model.rssm.initial(4))
    traj = agent.actor_critic.imagine(agent.world_model, start, horizon=3)
    assert torch.allclose(traj["continuation"], torch.full((4, 4), config.actor_critic.discount))


class NoisyProbe:
    """Returns seeded random actions (as if noise were already added) and records them."""

    def __init__(self) -> None:
        self.rng = np.random.default_rng(0)
        self.returned: list[np.ndarray] = []

    def policy(self, obs: np.ndarray, state: Any = None, mode: str = "train", is_first: Any = None, generator=None):
        action = self.rng.uniform(-1, 1, (len(obs), 2)).astype(np.float32)
        self.returned.append(action[0].copy())
        return action, state

    def policy_copy(self) -> NoisyProbe:
        return self  # acts with no weights, so the copy may be the agent itself

    def train(self, batch: dict[str, np.ndarray]) -> dict[str, float]:
        return {}

    def state_dict(self) -> dict[str, Any]:
        return {}


def test_the_loop_executes_the_agents_action_and_adds_no_noise_of_its_own(tmp_path: Path) -> None:
    agent = NoisyProbe()
    config = make_config("tiny", ["device=cpu", "train.expl_noise=0.5", "train.prefill=0", f"train.eval_every={NEVER}"])
    with _writer(tmp_path / "d.h5") as writer, Logger(tmp_path, outputs=()) as logger:
        loop = OnlineTrainer(
            agent=agent, task="toy_reach", config=config, logdir=tmp_path, writer=writer, logger=logger
        )
        try:
            loop.run(max_steps=50, progress=False)
        finally:
            loop.close()
    with open_dataset(tmp_path / "d.h5") as data:
        executed = data.episode(0)["action"][1:]
    np.testing.assert_array_equal(executed, np.stack(agent.returned[:50]))


def test_the_slow_critic_copies_the_critic_after_its_optimiser_step() -> None:
    torch.manual_seed(0)
    agent = DreamerV2(config=make_config("tiny", ["device=cpu", "actor_critic.slow_target_every=20"]), action_size=2)
    ac = agent.actor_critic
    batch = {
        "image": np.random.default_rng(0).integers(0, 255, (2, 5, 64, 64, 3), dtype=np.uint8),
        "action": np.zeros((2, 5, 2), np.float32),
        "reward": np.ones((2, 5), np.float32),
        "is_first": np.eye(1, 5, dtype=bool).repeat(2, 0),
        "is_last": np.zeros((2, 5), bool),
        "is_terminal": np.zeros((2, 5), bool),
    }
    agent.train(batch)
    for slow, fast in zip(ac.slow_critic.parameters(), ac.critic.parameters(), strict=True):
        torch.testing.assert_close(slow, fast)  # the first update copies the stepped critic whole
    copied = [p.clone() for p in ac.slow_critic.parameters()]
    agent.train(batch)
    assert any(not torch.equal(a, b) for a, b in zip(copied, ac.critic.parameters(), strict=True))
    for slow, before in zip(ac.slow_critic.parameters(), copied, strict=True):
        torch.testing.assert_close(slow, before)  # and holds still until the next copy, 20 updates on


def test_replay_windows_start_from_a_fresh_latent_even_mid_episode() -> None:
    replay = Replay(seed=0)
    length = 100
    replay.add_episode(
        {
            "image": np.zeros((length, 4, 4, 3), np.uint8),
            "action": np.ones((length, 2), np.float32),
            "reward": np.zeros(length, np.float32),
            "is_first": np.arange(length) == 0,
            "is_last": np.arange(length) == length - 1,
            "is_terminal": np.zeros(length, bool),
        }
    )
    batch = replay.sample(32, 10)
    assert batch["is_first"][:, 0].all() and not batch["is_first"][:, 1:].any()


def test_the_switch_from_prefill_to_training_keeps_the_running_episodes_latent(tmp_path: Path) -> None:
    torch.manual_seed(0)
    # updates in turn: the loop then acts with the agent's own policy, which the test records
    overrides = ["train.prefill=30", "train.pretrain_updates=0", f"train.eval_every={NEVER}"]
    config = make_config("tiny", ["device=cpu", "train.background_updates=false", *overrides])
    agent = DreamerV2(config=config, action_size=2)
    calls: list[tuple[str, bool, bool]] = []  # (mode, state given, is_first)
    policy = agent.policy

    def recording_policy(obs, state=None, mode="train", *, is_first=None, generator=None):
        calls.append((mode, state is not None, bool(np.asarray(is_first).all())))
        return policy(obs, state, mode, is_first=is_first, generator=generator)

    agent.policy = recording_policy  # type: ignore[method-assign]
    with _writer(tmp_path / "d.h5") as writer, Logger(tmp_path, outputs=()) as logger:
        loop = OnlineTrainer(
            agent=agent, task="toy_reach", config=config, logdir=tmp_path, writer=writer, logger=logger
        )
        try:
            loop.run(max_steps=40, progress=False)  # switches to 'train' at step 30 of the first 50-step episode
        finally:
            loop.close()
    assert [mode for mode, _, _ in calls].count("train") == 10
    for mode, state_given, first in calls:
        assert state_given or first, f"a {mode} step restarted the latent in the middle of an episode"


def test_the_collectors_own_agent_evaluates_as_the_dreamerv2_run_it_is(tmp_path: Path) -> None:
    out = tmp_path / "toy.h5"
    runner = CliRunner()
    args = ["collect", "--task", "toy_reach", "--policy", "dreamerv2", "--preset", "tiny", "--max-steps", "550"]
    result = runner.invoke(main, [*args, "--out", str(out), "--device", "cpu", "--set", "train.eval_every=100000"])
    assert result.exit_code == 0, result.output
    run_dir = tmp_path / "toy.run"
    result = runner.invoke(
        main, ["eval", "--ckpt", str(run_dir), "--episodes", "2", "--out", str(tmp_path / "eval.json")]
    )
    assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "eval.json").read_text())
    assert report["extra"]["algo"] == "dreamerv2" and report["task"] == "toy_reach" and len(report["returns"]) == 2
    _, read = load_run(run_dir)
    assert read["algo"] == "dreamerv2" and read["target"] == "toy_reach" and read["online"]
    # A collector's folder from before this release (its run.json named only its task) is refused in one line.
    info = json.loads((run_dir / "run.json").read_text())
    old = {key: info[key] for key in ("task", "quality", "dataset", "max_steps", "stop_return")}
    (run_dir / "run.json").write_text(json.dumps(old))
    result = runner.invoke(main, ["eval", "--ckpt", str(run_dir), "--episodes", "2"])
    assert result.exit_code == 2
    assert "was written by an earlier coworld's collector (no 'algo' entry)" in result.output
