"""Algorithm 1's schedule on the toy pair: a run killed inside a source phase resumes at the train ratio, and the
two alignment readings of Eq. 3 are reduced as the paper and the release do."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from coworld.agents import coworld as coworld_module
from coworld.agents.coworld import CoWorld
from coworld.config import make_config
from coworld.data import open_dataset
from coworld.training.online import OnlineTrainer
from coworld.training.train import check_job, run_job

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SCHEDULE = [
    "device=cpu",
    "train.prefill=50",
    "train.pretrain_updates=2",
    "train.train_every=5",
    "train.eval_episodes=1",
    "coworld.pretrain_steps=100",
    "coworld.iterations=2",
    "coworld.target_updates=2",
    "coworld.source_updates=15",
]


def test_a_run_killed_inside_a_source_phase_resumes_without_a_burst_of_updates(
    tmp_path: Path, toy_dataset_writer, monkeypatch: pytest.MonkeyPatch
) -> None:
    dataset = toy_dataset_writer(tmp_path / "target.h5", "toy_reach_shifted", episodes=3)
    job = check_job(
        algo="coworld",
        source="toy_reach",
        target="toy_reach_shifted",
        dataset=dataset,
        preset="tiny",
        logdir=tmp_path / "run",
        seed=0,
        device="cpu",
        overrides=SCHEDULE,
    )
    original_train_source = CoWorld.train_source
    calls = {"n": 0}

    def crashing_train_source(self, batch):
        calls["n"] += 1
        # pretraining makes 2 + (100 - 50) / 5 + 1 = 13 source updates; crash 10 updates into the first phase
        if calls["n"] > 13 + 10:
            raise RuntimeError("simulated crash")
        return original_train_source(self, batch)

    monkeypatch.setattr(CoWorld, "train_source", crashing_train_source)
    with pytest.raises(RuntimeError, match="simulated crash"):
        run_job(job, progress=False)
    state = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=True)
    assert state["progress"]["phase"] == "source"  # killed inside the first source phase
    with open_dataset(tmp_path / "run" / "source_replay.h5") as replay:
        rows_at_crash = replay.num_steps
    assert rows_at_crash > 100  # the source phase had stepped the environment before the crash

    monkeypatch.setattr(CoWorld, "train_source", original_train_source)
    updates_per_call: list[int] = []
    original_due = OnlineTrainer._train_due

    def counting(self):
        before = self.updates
        original_due(self)
        updates_per_call.append(self.updates - before)

    monkeypatch.setattr(OnlineTrainer, "_train_due", counting)
    summary = run_job(job, progress=False)
    assert summary["iterations"] == 2
    assert max(updates_per_call) == 1  # never two source updates without an environment step between them
    final = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=True)
    assert final["source_updates"] == 13 + 2 * 15  # pretraining, then exactly K2 per iteration


@pytest.mark.parametrize("align_on", ["latent", "embedding"])
def test_alignment_term_reduction_matches_the_paper_and_the_release(align_on: str) -> None:
    config = make_config("tiny", ["device=cpu", "coworld.beta2=1.0", f"coworld.align_on={align_on}"])
    torch.manual_seed(0)
    agent = CoWorld(config=config, action_size=2, device="cpu")
    b, t = 3, 4
    batch = {
        "image": torch.randint(0, 256, (b, t, 64, 64, 3), dtype=torch.uint8),
        "action": torch.rand(b, t, 2) * 2 - 1,
        "reward": torch.rand(b, t),
        "is_first": torch.zeros(b, t, dtype=torch.bool),
        "is_last": torch.zeros(b, t, dtype=torch.bool),
        "is_terminal": torch.zeros(b, t, dtype=torch.bool),
    }
    batch["is_first"][:, 0] = True
    # The update runs the source model, then the target model, over the batch: the same order and seed draw
    # the same latent samples here.
    torch.manual_seed(1)
    with torch.no_grad():
        source_post, _, source_embed = agent.source.world_model.observe(agent.source.to_batch(batch))
        target_post, _, target_embed = agent.target.world_model.observe(agent.target.to_batch(batch))
    if align_on == "embedding":  # the release: KLDivLoss(reduction="batchmean") on (B, T, E) sums over T
        expected = torch.nn.KLDivLoss(reduction="batchmean")(
            torch.log_softmax(target_embed, -1), torch.softmax(source_embed, -1)
        )
    else:  # the paper's posteriors, averaged over (B, T) like DreamerV2's other world-model terms
        expected = coworld_module.alignment_loss(source_post["logits"], target_post["logits"]).mean()
    torch.manual_seed(1)
    metrics = agent.train_target(batch)
    assert metrics["target/coworld/align_kl"] == pytest.approx(float(expected), rel=1e-4)
