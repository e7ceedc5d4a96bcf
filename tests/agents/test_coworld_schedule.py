"""Algorithm 1's schedule on the toy pair: a run killed inside a source phase resumes exactly, the two
alignment readings of Eq. 3 are reduced as the paper and the release do, and the source model's pass made ahead
with a target batch trains as the update's own pass does."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from coworld.agents.coworld import ALIGN_SOURCE, CoWorld, TargetBatches
from coworld.config import make_config
from coworld.data import open_dataset
from coworld.errors import CheckpointError
from coworld.losses.coworld import alignment_loss
from coworld.training.online import OnlineTrainer
from coworld.training.train import run_job

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_a_run_killed_inside_a_source_phase_resumes_to_the_weights_of_an_uninterrupted_run(
    tmp_path: Path, toy_dataset_writer, coworld_toy_job, toy_schedule, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Killed mid-episode in its first source phase, the rerun cuts the source replay back to the phase's checkpoint,
    makes the running source episodes again from their seeds and actions, and ends with the very weights, source steps
    and source replay of a run never stopped, never making two source updates without a step between them."""
    dataset = toy_dataset_writer(tmp_path / "target.h5", "toy_reach_shifted", episodes=3)
    run_job(coworld_toy_job(dataset, tmp_path / "whole", toy_schedule), progress=False)
    whole = torch.load(tmp_path / "whole" / "checkpoint.pt", weights_only=True)
    job = coworld_toy_job(dataset, tmp_path / "run", toy_schedule)
    original_train_source = CoWorld.train_source
    calls = {"n": 0}

    def crashing_train_source(self, *args):
        calls["n"] += 1
        # pretraining makes 2 + (100 - 50) / 5 + 1 = 13 source updates; crash 10 updates into the first phase
        if calls["n"] > 13 + 10:
            raise RuntimeError("simulated crash")
        return original_train_source(self, *args)

    monkeypatch.setattr(CoWorld, "train_source", crashing_train_source)
    with pytest.raises(RuntimeError, match="simulated crash"):
        run_job(job, progress=False)
    state = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=True)
    assert state["progress"]["phase"] == "source"  # killed inside the first source phase
    with open_dataset(tmp_path / "run" / "source_replay.h5") as replay:
        rows_at_crash = replay.num_steps
    assert rows_at_crash > 100  # the source phase had stepped the environment before the crash

    monkeypatch.setattr(CoWorld, "train_source", original_train_source)
    updates_per_step = [0]
    original_step, original_update = OnlineTrainer.step, OnlineTrainer.update

    def stepping(self, *args):
        updates_per_step.append(0)
        original_step(self, *args)

    def updating(self, *args):
        updates_per_step[-1] += 1
        original_update(self, *args)

    monkeypatch.setattr(OnlineTrainer, "step", stepping)
    monkeypatch.setattr(OnlineTrainer, "update", updating)
    summary = run_job(job, progress=False)
    assert summary["iterations"] == 2
    assert sum(updates_per_step) == 15 + 15  # the rest of the first source phase from its start, and the second
    assert max(updates_per_step) == 1  # never two source updates without an environment step between them
    final = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=True)
    assert final["source_updates"] == 13 + 2 * 15  # pretraining, then exactly K2 per iteration
    _assert_same_tensors(
        {"target": whole["agent"], "source": whole["source"]}, {"target": final["agent"], "source": final["source"]}
    )
    assert final["source_online"]["steps"] == whole["source_online"]["steps"]
    with (
        open_dataset(tmp_path / "run" / "source_replay.h5") as a,
        open_dataset(tmp_path / "whole" / "source_replay.h5") as b,
    ):
        assert a.num_episodes == b.num_episodes > 0
        for i in range(a.num_episodes):
            assert all(np.array_equal(x, y) for x, y in zip(a.episode(i).values(), b.episode(i).values(), strict=True))


@pytest.mark.parametrize("align_on", ["latent", "embedding"])
def test_alignment_term_reduction_matches_the_paper_and_the_release(align_on: str, target_batch) -> None:
    config = make_config("tiny", ["device=cpu", "coworld.beta2=1.0", f"coworld.align_on={align_on}"])
    torch.manual_seed(0)
    agent = CoWorld(config=config, action_size=2, device="cpu")
    batch = target_batch()
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
        expected = alignment_loss(source_post["logits"], target_post["logits"]).mean()
    torch.manual_seed(1)
    metrics = agent.train_target(batch)
    assert metrics["target/coworld/align_kl"] == pytest.approx(float(expected), rel=1e-4)


def _tensors(tree: Any, prefix: str = "") -> dict[str, torch.Tensor]:
    """The tensors of a nested state dict by their path."""
    if isinstance(tree, torch.Tensor):
        return {prefix: tree}
    items = tree.items() if isinstance(tree, dict) else enumerate(tree) if isinstance(tree, list | tuple) else ()
    return {k: v for key, value in items for k, v in _tensors(value, f"{prefix}/{key}").items()}


def _assert_same_tensors(want: Any, have: Any) -> None:
    """Two nested state dicts hold the same tensors at the same paths, equal element for element."""
    want, have = _tensors(want), _tensors(have)
    assert want.keys() == have.keys()
    changed = [key for key in want if not torch.equal(want[key], have[key])]
    assert not changed, changed


@pytest.mark.parametrize("align_on", ["latent", "embedding"])
def test_a_target_batch_made_with_the_source_pass_trains_as_the_updates_own_pass_does(
    align_on: str, target_batch, monkeypatch: pytest.MonkeyPatch
) -> None:
    config = make_config("tiny", ["device=cpu", "coworld.beta2=1.0", f"coworld.align_on={align_on}"])
    torch.manual_seed(0)
    inline = CoWorld(config=config, action_size=2, device="cpu")
    ahead = copy.deepcopy(inline)
    batch = target_batch(b=4, t=6)

    torch.manual_seed(1)
    expected = inline.train_target(batch)  # the source pass inside the update, on torch's default generator

    made = TargetBatches(ahead, aligned=1, seed=1)  # a generator of its own, seeded as the default was
    made_batch = made(batch)
    assert made_batch[ALIGN_SOURCE].shape == ((4, 6, 8, 8) if align_on == "latent" else (4, 6, 256))
    assert ALIGN_SOURCE not in made(batch)  # past the batches it was asked to align
    torch.set_rng_state(made.generator.get_state())  # where the update's own pass left the default generator

    def no_source_pass(*_: Any, **__: Any) -> None:
        raise AssertionError("the update ran the source model over a batch that carried its pass")

    monkeypatch.setattr(ahead.source.model_path, "embed", no_source_pass)
    monkeypatch.setattr(ahead.source.model_path, "observe", no_source_pass)
    got = ahead.train_target(made_batch)
    assert got == expected
    assert expected["target/coworld/align_kl"] > 0.0
    _assert_same_tensors(inline.target.state_dict(), ahead.target.state_dict())


def test_prefetching_leaves_a_coworld_run_unchanged(tmp_path: Path, toy_dataset_writer, coworld_toy_job) -> None:
    dataset = toy_dataset_writer(tmp_path / "target.h5", "toy_reach_shifted", episodes=3)
    schedule = [
        "device=cpu",
        "train.prefill=50",
        "train.pretrain_updates=1",
        "train.train_every=5",
        "train.eval_episodes=1",
        "coworld.pretrain_steps=60",
        "coworld.iterations=2",
        "coworld.target_updates=3",
        "coworld.source_updates=2",
    ]
    states = {}
    for prefetch in (False, True):
        logdir = tmp_path / f"prefetch_{prefetch}"
        overrides = [*schedule, f"train.prefetch={str(prefetch).lower()}"]
        assert run_job(coworld_toy_job(dataset, logdir, overrides), progress=False)["target_updates"] == 6
        states[prefetch] = torch.load(logdir / "checkpoint.pt", weights_only=True)
    plain, ahead = ({"target": s["agent"], "source": s["source"]} for s in (states[False], states[True]))
    _assert_same_tensors(plain, ahead)
    assert states[False]["progress"]["iteration"] == states[True]["progress"]["iteration"] == 2


PRETRAINING = [
    "device=cpu",
    "train.prefill=50",
    "train.pretrain_updates=2",
    "train.train_every=5",
    "train.eval_episodes=1",
    "train.checkpoint_every=100",
    "coworld.pretrain_steps=200",
    "coworld.iterations=1",
    "coworld.target_updates=2",
    "coworld.source_updates=5",
]


@pytest.mark.parametrize(
    ("stop_at", "cap_critic", "acting"),
    [
        (70, "source", []),
        pytest.param(160, "source", [], marks=pytest.mark.slow),
        (160, "target_policy", []),
        pytest.param(160, "source", ["train.envs=2", "train.background_updates=true"], marks=pytest.mark.slow),
    ],
    ids=[
        "before-its-first-checkpoint",
        "after-a-checkpoint",
        "target-policy-cap-after-a-checkpoint",
        "two-envs-beside-learning-after-a-checkpoint",
    ],
)
def test_a_run_stopped_while_it_pretrains_ends_with_an_uninterrupted_runs_counts(
    stop_at: int,
    cap_critic: str,
    acting: list[str],
    tmp_path: Path,
    toy_dataset_writer,
    coworld_toy_job,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Stopped while its source agent pretrains (Ctrl-C, SIGTERM, a kill, a full disk), the rerun continues from the
    last source checkpoint with the source replay cut back to what that checkpoint had seen, so it ends with the
    source updates, steps and weights an uninterrupted run ends with (the episodes running at the checkpoint made
    again from their seeds and actions), and the target-policy critic (which learns beside the source agent) with its
    updates; stopped before the first checkpoint it starts the pretraining over."""
    overrides = [*PRETRAINING, f"coworld.cap_critic={cap_critic}", *acting]
    dataset = toy_dataset_writer(tmp_path / "target.h5", "toy_reach_shifted", episodes=3)
    run_job(coworld_toy_job(dataset, tmp_path / "whole", overrides), progress=False)
    whole = torch.load(tmp_path / "whole" / "checkpoint.pt", weights_only=True)

    job = coworld_toy_job(dataset, tmp_path / "run", overrides)
    original_due = OnlineTrainer._train_due

    def stopping(self):
        if self.steps >= stop_at:
            raise KeyboardInterrupt
        original_due(self)

    monkeypatch.setattr(OnlineTrainer, "_train_due", stopping)
    with pytest.raises(KeyboardInterrupt):
        run_job(job, progress=False)
    assert not (tmp_path / "run" / "checkpoint.pt").exists()  # stopped inside the pretraining
    assert (tmp_path / "run" / "source" / "checkpoint.pt").exists() == (stop_at > 100)
    with open_dataset(tmp_path / "run" / "source_replay.h5") as replay:
        # one env: an episode ended after the last checkpoint; two: theirs were running, 60 steps past it
        assert replay.num_steps > (100 if stop_at > 100 else 0) or replay.num_steps == 100 < stop_at
    monkeypatch.undo()
    run_job(job, progress=False)
    resumed = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=True)
    assert resumed["source_updates"] == whole["source_updates"] == 2 + (200 - 50) // 5 + 1 + 5
    with (
        open_dataset(tmp_path / "run" / "source_replay.h5") as a,
        open_dataset(tmp_path / "whole" / "source_replay.h5") as b,
    ):
        assert a.num_steps == b.num_steps
    _assert_same_tensors(whole["source"], resumed["source"])
    if cap_critic == "target_policy":
        assert int(resumed["policy_value"]["updates"]) == int(whole["policy_value"]["updates"]) > 0
        _assert_same_tensors(whole["policy_value"], resumed["policy_value"])


@pytest.mark.parametrize("entry", ["relabelled", "source_online"])
def test_a_checkpoint_from_before_this_release_is_refused_in_one_line(
    entry: str, tmp_path: Path, toy_dataset_writer, coworld_toy_job
) -> None:
    """A CoWorld checkpoint without an entry this release writes (the source updates that relabelled a target batch,
    the source agent's online state) is not resumed from what it does hold: one line says to train again or to
    resume it with the coworld that wrote it, and the checkpoint is left as it was."""
    dataset = toy_dataset_writer(tmp_path / "target.h5", "toy_reach_shifted", episodes=3)
    schedule = ("coworld.pretrain_steps=60", "coworld.target_updates=1", "coworld.source_updates=1")
    overrides = [o for o in PRETRAINING if o.split("=")[0] not in {s.split("=")[0] for s in schedule}] + list(schedule)
    run_job(coworld_toy_job(dataset, tmp_path / "run", overrides), progress=False)
    path = tmp_path / "run" / "checkpoint.pt"
    state = torch.load(path, weights_only=True)
    assert state["relabelled"] == 1  # the one source update of the one iteration relabelled its target batch
    del state[entry]
    torch.save(state, path)
    written = path.read_bytes()
    folder = {p.name: p.read_bytes() for p in (tmp_path / "run").iterdir() if p.is_file()}
    with pytest.raises(CheckpointError) as refused:  # refused as the request is checked, before the folder is touched
        run_job(coworld_toy_job(dataset, tmp_path / "run", overrides), progress=False)
    assert {p.name: p.read_bytes() for p in (tmp_path / "run").iterdir() if p.is_file()} == folder
    message = str(refused.value)
    assert "\n" not in message and message.startswith(f"{path} was written by an earlier coworld (no {entry!r} entry)")
    assert "train the run again (--force), or resume it with coworld 0.1.0 at commit" in message
    assert path.read_bytes() == written
