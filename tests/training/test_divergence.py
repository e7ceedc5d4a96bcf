"""A diverged run never leaves a damaged checkpoint, in any phase (:mod:`coworld.training.divergence`).

Each test poisons one network of a real tiny run with NaN right after a chosen update (what a learning rate far too
high does within a few updates), then checks the one line the run stops with: what became non-finite, where (the
update and the phase), what to lower, and which checkpoint is kept (or that none is); and that every checkpoint on
disk holds finite tensors only.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import torch
from click.testing import CliRunner

from coworld.agents.coworld import CoWorld
from coworld.agents.dreamerv2 import DreamerV2
from coworld.cli import main
from coworld.errors import TrainingDiverged
from coworld.training.checkpoint import save_checkpoint
from coworld.training.collect import collect_dreamerv2
from coworld.training.train import check_job, run_job

pytestmark = pytest.mark.usefixtures("one_torch_thread")

COLLECT = ("device=cpu", "train.prefill=100", "train.eval_episodes=1", "train.checkpoint_every=100")
"""Collection in seconds: 50-step toy_reach episodes, 10 updates at once after a 100-step prefill, then one every
10 steps (update n + 1 at step 100 + 10 (n - 10) for n >= 10), a checkpoint at the episode ends of steps 100 and 200."""
COWORLD = (
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
"""A two-phase run in seconds: 13 pretraining source updates, then 2 iterations of 2 target and 15 source updates."""


def tensors(state: Any, prefix: str = "") -> Iterator[tuple[str, torch.Tensor]]:
    if isinstance(state, torch.Tensor):
        yield prefix, state
    elif isinstance(state, dict):
        for key, value in state.items():
            yield from tensors(value, f"{prefix}/{key}")
    elif isinstance(state, list | tuple):
        for i, value in enumerate(state):
            yield from tensors(value, f"{prefix}/{i}")


def assert_finite_checkpoints(folder: Path) -> None:
    """Every checkpoint under ``folder`` loads and holds finite tensors only."""
    for path in folder.rglob("*.pt"):
        state = torch.load(path, weights_only=True)
        bad = [name for name, t in tensors(state) if t.is_floating_point() and not torch.isfinite(t).all()]
        assert not bad, f"{path} holds non-finite tensors: {bad[:3]}"


def poison_after(
    monkeypatch: pytest.MonkeyPatch, cls: type, method: str, calls: int, module: Callable[[Any], torch.nn.Module]
) -> None:
    """``cls.method`` as it is, except that its ``calls``-th call ends filling ``module(self)``'s weights with NaN."""
    original = getattr(cls, method)
    made = {"n": 0}

    def poisoning(self: Any, *args: Any, **kwargs: Any) -> Any:
        metrics = original(self, *args, **kwargs)
        made["n"] += 1
        if made["n"] == calls:
            with torch.no_grad():
                for parameter in module(self).parameters():
                    parameter.fill_(float("nan"))
        return metrics

    monkeypatch.setattr(cls, method, poisoning)


def reward_head(agent: DreamerV2) -> torch.nn.Module:
    return agent.world_model.reward_head


# -- the checkpoint writer ---------------------------------------------------------------------------------------------


def test_the_checkpoint_writer_refuses_a_state_holding_a_non_finite_tensor(tmp_path: Path) -> None:
    path = tmp_path / "checkpoint.pt"
    damaged = {"kind": "x", "agent": {"net": {"w": torch.tensor([1.0, float("nan")])}}, "rng": torch.zeros(3)}
    with pytest.raises(TrainingDiverged, match="^refusing to write checkpoint .*: agent/net/w holds nan") as err:
        save_checkpoint(path, damaged)
    assert "no earlier checkpoint exists" in str(err.value)
    assert list(tmp_path.iterdir()) == []  # nothing written, no temporary file
    good = {"kind": "x", "agent": {"net": {"w": torch.ones(2)}}, "ids": torch.arange(3), "bits": torch.ones(2).bool()}
    save_checkpoint(path, good)
    before = path.read_bytes()
    damaged["agent"]["net"]["w"] = torch.tensor([float("-inf")])
    with pytest.raises(TrainingDiverged, match=f"holds -inf values; the previous checkpoint {re.escape(str(path))}"):
        save_checkpoint(path, damaged)
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt"]


# -- online training: collection ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("poisoned", "expected", "kept_updates"),
    [
        # poisoned in the burst of step 100: update 6's loss is the first non-finite, before any checkpoint
        (5, r"the agent's world-model loss \(wm/loss\) became nan at update 6 \(collection\)", None),
        # update 16 (step 150) is the first non-finite loss; the checkpoint of step 100 (11 updates) is the last good
        (15, r"the agent's world-model loss \(wm/loss\) became nan at update 16 \(collection\)", 11),
        # update 21 (step 200) leaves a finite loss and NaN weights, which the checkpoint of step 200 would keep
        (21, r"the agent's weights became non-finite by update 21 \(collection\): agent/world_model/reward_head", 11),
    ],
    ids=["before-any-checkpoint", "after-a-checkpoint", "weights-at-a-checkpoint"],
)
def test_collection_stops_at_the_first_non_finite_value_and_keeps_its_last_good_checkpoint(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, poisoned: int, expected: str, kept_updates: int | None
) -> None:
    poison_after(monkeypatch, DreamerV2, "train", poisoned, reward_head)
    out = tmp_path / "toy_reach-medium_replay.h5"
    with pytest.raises(TrainingDiverged, match=f"^{expected}") as err:
        collect_dreamerv2(
            "toy_reach", out, preset="tiny", device="cpu", progress=False, overrides=COLLECT, max_steps=400
        )
    message = str(err.value)
    checkpoint = out.with_name("toy_reach-medium_replay.run") / "checkpoint.pt"
    assert "lower world_model.lr (now 0.0006)" in message and "\n" not in message
    if kept_updates is None:
        assert not checkpoint.exists() and message.endswith("no checkpoint was written before it")
    else:
        assert message.endswith(f"the last good checkpoint is kept at {checkpoint}")
        assert torch.load(checkpoint, weights_only=True)["updates"] == kept_updates
    assert_finite_checkpoints(tmp_path)


def test_collection_stops_at_the_first_non_finite_action(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An actor poisoned by update 15 (step 140) acts NaN at once: the run stops at step 141, before an episode with
    NaN actions reaches the dataset writer (which would refuse it with a line about the data)."""
    poison_after(monkeypatch, DreamerV2, "train", 15, lambda agent: agent.actor_critic.actor)
    out = tmp_path / "toy_reach-medium_replay.h5"
    expected = (
        r"^the agent's actions became nan at env step 141 \(collection\); lower world_model.lr \(now 0.0006\) or"
        r" actor_critic.actor_lr \(now 0.0002\)"
    )
    with pytest.raises(TrainingDiverged, match=expected):
        collect_dreamerv2(
            "toy_reach", out, preset="tiny", device="cpu", progress=False, overrides=COLLECT, max_steps=400
        )
    assert_finite_checkpoints(tmp_path)


def test_a_diverged_collection_exits_with_code_2_and_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    poison_after(monkeypatch, DreamerV2, "train", 15, reward_head)
    out = tmp_path / "d.h5"
    options = ["collect", "--task", "toy_reach", "--preset", "tiny", "--max-steps", "400", "--out", str(out), "--quiet"]
    result = CliRunner().invoke(main, [*options, *(f"--set={o}" for o in COLLECT)])
    assert result.exit_code == 2, result.output
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert result.stderr.strip().splitlines()[-1] == errors[0] and len(errors) == 1
    assert errors[0].startswith("error: the agent's world-model loss (wm/loss) became nan at update 16 (collection)")


# -- two-phase runs ----------------------------------------------------------------------------------------------------


def two_phase_job(dataset: Path, logdir: Path, algo: str = "coworld") -> Any:
    return check_job(
        algo=algo,
        source="toy_reach",
        target="toy_reach_shifted",
        dataset=dataset,
        preset="tiny",
        logdir=logdir,
        seed=0,
        device="cpu",
        overrides=list(COWORLD),
    )


def source_reward_head(coworld: CoWorld) -> torch.nn.Module:
    return coworld.source.world_model.reward_head


def target_reward_head(coworld: CoWorld) -> torch.nn.Module:
    return coworld.target.world_model.reward_head


@pytest.mark.parametrize(
    ("method", "poisoned", "module", "expected", "kept"),
    [
        (
            "train_source",
            5,
            source_reward_head,
            r"the source agent's world-model loss \(source/wm/loss\) became nan at source update 6 \(source "
            r"pretraining\); lower world_model.lr \(now 0.0006\)",
            None,
        ),
        (
            "train_source",
            13 + 3,
            source_reward_head,
            r"the source agent's world-model loss \(source/wm/loss\) became nan at source update 17 \(source phase "
            r"of iteration 1\)",
            "checkpoint.pt",
        ),
        (
            "train_target",
            1,
            target_reward_head,
            r"the target agent's world-model loss \(target/wm/loss\) became nan at target update 2 \(target phase "
            r"of iteration 1\); lower world_model.lr \(now 0.0006\) or coworld.beta2 \(now 1.5\)",
            "checkpoint.pt",
        ),
    ],
    ids=["pretraining", "source-phase", "target-phase"],
)
def test_coworld_stops_in_every_phase_at_the_first_non_finite_loss(
    tmp_path: Path,
    toy_dataset_writer,
    monkeypatch: pytest.MonkeyPatch,
    method: str,
    poisoned: int,
    module: Callable[[CoWorld], torch.nn.Module],
    expected: str,
    kept: str | None,
) -> None:
    dataset = toy_dataset_writer(tmp_path / "target.h5", "toy_reach_shifted", episodes=3)
    poison_after(monkeypatch, CoWorld, method, poisoned, module)
    logdir = tmp_path / "run"
    with pytest.raises(TrainingDiverged, match=f"^{expected}") as err:
        run_job(two_phase_job(dataset, logdir), progress=False)
    message = str(err.value)
    if kept is None:
        assert message.endswith("no checkpoint was written before it")
        assert not list(logdir.rglob("checkpoint.pt"))
    else:
        assert message.endswith(f"the last good checkpoint is kept at {logdir / kept}")
    assert_finite_checkpoints(tmp_path)


def test_the_fine_tuned_dreamerv2_stops_in_its_source_phase(
    tmp_path: Path, toy_dataset_writer, monkeypatch: pytest.MonkeyPatch
) -> None:
    dataset = toy_dataset_writer(tmp_path / "target.h5", "toy_reach_shifted", episodes=3)
    poison_after(monkeypatch, DreamerV2, "train", 5, reward_head)
    logdir = tmp_path / "run"
    expected = (
        r"^the agent's world-model loss \(source/wm/loss\) became nan at source update 6 \(source phase\); lower"
        r" world_model.lr \(now 0.0006\)"
    )
    with pytest.raises(TrainingDiverged, match=expected) as err:
        run_job(two_phase_job(dataset, logdir, "dreamerv2-finetune"), progress=False)
    assert str(err.value).endswith("no checkpoint was written before it")
    assert_finite_checkpoints(tmp_path)


# -- offline training --------------------------------------------------------------------------------------------------


def test_offline_dreamerv2_refuses_to_checkpoint_weights_its_last_update_made_non_finite(
    tmp_path: Path, toy_dataset_writer, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The update before a checkpoint reports a finite loss and leaves NaN weights: the checkpoint is refused, and the
    one before it kept (the offline run checkpoints every ``offline.checkpoint_every`` = 2 of its 6 updates)."""
    dataset = toy_dataset_writer(tmp_path / "target.h5", "toy_reach_shifted", episodes=3)
    poison_after(monkeypatch, DreamerV2, "train", 4, reward_head)
    logdir = tmp_path / "run"
    job = check_job(
        algo="dreamerv2",
        source=None,
        target="toy_reach_shifted",
        dataset=dataset,
        preset="tiny",
        logdir=logdir,
        seed=0,
        device="cpu",
        overrides=[*COWORLD, "offline.updates=6", "offline.checkpoint_every=2", "offline.eval_every=100"],
    )
    expected = (
        r"^the agent's weights became non-finite by update 4 \(offline training\): agent/world_model/reward_head\S* "
        r"holds nan values; lower world_model.lr \(now 0.0006\)"
    )
    with pytest.raises(TrainingDiverged, match=expected) as err:
        run_job(job, progress=False)
    checkpoint = logdir / "checkpoint.pt"
    assert str(err.value).endswith(f"the last good checkpoint is kept at {checkpoint}")
    assert torch.load(checkpoint, weights_only=True)["updates"] == 2
    assert_finite_checkpoints(tmp_path)
