"""CoWorld across action sizes: a source and a target whose action spaces differ train together.

The source world model's action input is the wider of the two spaces and reads each zero-padded; the target
agent and both actors keep their own task's size (coworld.agents.coworld.source_model_action_size). The fast pair
is toy_reach (2-d actions) -> toy_reach_shifted_act3 (3-d: the shifted toy with a third, ignored component).
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from coworld.agents.coworld import CoWorld, source_model_action_size
from coworld.cli import main
from coworld.config import make_config
from coworld.errors import CoworldError
from coworld.models.rssm import pad_action
from coworld.training.train import check_job, run_job
from coworld.viz.runs import load_run_models

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_pad_action_zero_pads_at_the_end_and_refuses_a_wider_action() -> None:
    action = torch.tensor([[0.5, -1.0]])
    assert torch.equal(pad_action(action, 4), torch.tensor([[0.5, -1.0, 0.0, 0.0]]))
    assert pad_action(action, 2) is action
    with pytest.raises(ValueError, match="size 2 do not fit"):
        pad_action(action, 1)
    assert source_model_action_size(4, 5) == 5 and source_model_action_size(6, 2) == 6


@pytest.mark.parametrize(("source", "target"), [(2, 3), (5, 3)])
def test_each_network_keeps_its_own_tasks_size_and_the_source_model_reads_the_wider(source: int, target: int) -> None:
    config = make_config("tiny", ["device=cpu"])
    agent = CoWorld(config=config, action_size=target, source_action_size=source, device="cpu")
    stoch = config.world_model.stoch * config.world_model.classes
    assert agent.source.action_size == source and agent.target.action_size == target
    assert agent.source.world_model.rssm.img_in[0].in_features == stoch + max(source, target)
    assert agent.target.world_model.rssm.img_in[0].in_features == stoch + target
    assert agent.source.actor_critic.actor.mlp.net[-1].out_features == 2 * source
    assert agent.target.actor_critic.actor.mlp.net[-1].out_features == 2 * target
    action, _ = agent.source.policy(torch.zeros(1, 64, 64, 3, dtype=torch.uint8).numpy(), None, "eval")
    assert action.shape == (1, source)  # the source acts in its own task


def test_the_source_model_reads_every_target_action_component_and_its_own_actions_padded(target_batch) -> None:
    torch.manual_seed(0)
    agent = CoWorld(config=make_config("tiny", ["device=cpu"]), action_size=3, source_action_size=2, device="cpu")
    batch = agent.target.prepare(target_batch(2, 5, 3))

    def logits(b):
        return agent.source_alignment(b, torch.Generator().manual_seed(1))

    changed = dict(batch, action=batch["action"].clone())
    changed["action"][..., 2] = -changed["action"][..., 2]  # only the component the source task lacks
    assert not torch.allclose(logits(batch), logits(changed))  # nothing of the target's actions is dropped
    own = dict(batch, action=batch["action"][..., :2].contiguous())
    padded = dict(batch, action=torch.cat([own["action"], torch.zeros_like(own["action"][..., :1])], dim=-1))
    torch.testing.assert_close(logits(own), logits(padded), rtol=0, atol=0)  # its own 2-d actions: a zero 3rd


def test_a_run_across_action_sizes_trains_resumes_and_evaluates(
    tmp_path: Path, toy_dataset_writer, coworld_toy_job, toy_schedule, monkeypatch: pytest.MonkeyPatch
) -> None:
    dataset = toy_dataset_writer(tmp_path / "target.h5", "toy_reach_shifted_act3", episodes=3)
    job = coworld_toy_job(dataset, tmp_path / "run", toy_schedule, target="toy_reach_shifted_act3")
    original = CoWorld.train_source
    calls = {"n": 0}

    def crashing(self, *args):
        calls["n"] += 1
        if calls["n"] > 13 + 10:  # 13 pretraining updates, then 10 into the first source phase
            raise RuntimeError("simulated crash")
        return original(self, *args)

    monkeypatch.setattr(CoWorld, "train_source", crashing)
    with pytest.raises(RuntimeError, match="simulated crash"):
        run_job(job, progress=False)
    assert torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=True)["progress"]["phase"] == "source"
    monkeypatch.setattr(CoWorld, "train_source", original)
    resumed = coworld_toy_job(dataset, tmp_path / "run", toy_schedule, target="toy_reach_shifted_act3")
    assert resumed.resume
    summary = run_job(resumed, progress=False)
    assert summary["iterations"] == 2
    final = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=True)
    assert final["source_updates"] == 13 + 2 * 15
    assert final["source"]["actor_critic"]["actor.mlp.net.4.weight"].shape[0] == 2 * 2  # the source acts in 2-d
    assert final["agent"]["actor_critic"]["actor.mlp.net.4.weight"].shape[0] == 2 * 3  # the target in 3-d
    out = CliRunner().invoke(main, ["eval", "--ckpt", str(tmp_path / "run"), "--episodes", "1", "--device", "cpu"])
    assert out.exit_code == 0, out.output
    assert "toy_reach_shifted_act3" in out.output and "return" in out.output
    models = load_run_models(tmp_path / "run", device="cpu")  # what `coworld viz` looks inside
    assert models.agents["source"].action_size == 2 and models.agents["source"].world_model.action_size == 3
    assert models.agents["target"].action_size == 3


def test_fine_tuning_still_refuses_a_source_of_another_action_size(tmp_path: Path, toy_dataset_writer) -> None:
    dataset = toy_dataset_writer(tmp_path / "target.h5", "toy_reach_shifted_act3", episodes=1)
    with pytest.raises(CoworldError, match="dreamerv2-finetune carries the source agent's networks") as err:
        check_job(
            algo="dreamerv2-finetune",
            source="toy_reach",
            target="toy_reach_shifted_act3",
            dataset=dataset,
            preset="tiny",
            logdir=tmp_path / "run",
            seed=0,
            device="cpu",
            overrides=["device=cpu"],
        )
    assert "\n" not in str(err.value)
    assert not (tmp_path / "run").exists()
