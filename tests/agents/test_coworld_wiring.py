"""CoWorld's wiring, through the agents' real update methods: every coefficient and every batch in its place.

The pure functions of Eqs. 3-6 have known-answer tests (tests/losses/test_coworld_losses.py); these pin how
:class:`coworld.agents.coworld.CoWorld` calls them. Each coefficient differs from 1 and from the others (``beta2``
0.7, ``k`` 0.3, ``alpha`` 0.4, ``zeta`` 0.6), so a dropped scale or a swapped ``k`` and ``1 - k`` changes a value.
Each test spies on the update as it runs (the term it adds, the world-model aux it read, the random state it drew
from) and recomputes the term from the paper's formula, written out here rather than taken from the loss module.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from torch import Tensor

from coworld.agents import coworld as coworld_module
from coworld.agents.coworld import ALIGN_SOURCE, CoWorld, TargetBatches
from coworld.agents.dreamerv2 import DreamerV2
from coworld.config import make_config
from coworld.data import open_dataset
from coworld.errors import ConfigError
from coworld.training.train import run_job

pytestmark = pytest.mark.usefixtures("one_torch_thread")

BETA2, K, ALPHA, ZETA = 0.7, 0.3, 0.4, 0.6
COEFFICIENTS = [f"coworld.beta2={BETA2}", f"coworld.k={K}", f"coworld.alpha={ALPHA}", f"coworld.zeta={ZETA}"]


def _agent(*overrides: str) -> CoWorld:
    torch.manual_seed(0)
    config = make_config("tiny", ["device=cpu", *COEFFICIENTS, *overrides])
    return CoWorld(config=config, action_size=2, device="cpu")


def _snapshot(*modules: torch.nn.Module) -> list[Tensor]:
    return [tensor.detach().clone() for module in modules for tensor in module.state_dict().values()]


def _unchanged(before: list[Tensor], *modules: torch.nn.Module) -> bool:
    after = _snapshot(*modules)
    return len(before) == len(after) and all(torch.equal(a, b) for a, b in zip(before, after, strict=True))


def _spy_world_model_step(agent: Any, captured: dict[str, Any], check: Callable[..., None] | None = None) -> None:
    """Wrap ``agent.train_world_model`` so that the extra-loss hook it is given records the aux it read, the terms
    it returned and torch's random state before it ran, and calls ``check(terms, aux)`` while the graph is alive."""
    original = agent.train_world_model

    def spy(batch: Any, extra_loss: Any = None) -> Any:
        if extra_loss is None:
            captured["extra"] = None
            return original(batch, None)

        def recording(batch_t: dict[str, Tensor], aux: dict[str, Any]) -> dict[str, Tensor]:
            captured["rng"] = torch.get_rng_state()
            terms = extra_loss(batch_t, aux)
            captured.update(extra=terms, aux_loss=aux["loss"].detach(), post_logits=aux["post"]["logits"].detach())
            captured["embed"] = aux["embed"].detach()
            if check is not None:
                after = torch.get_rng_state()
                check(terms, aux)
                torch.set_rng_state(after)
            return terms

        return original(batch, recording)

    agent.train_world_model = spy


# -- Eq. 3 ------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("align_on", ["latent", "embedding"])
def test_eq3_adds_beta2_times_the_kl_to_the_source_models_reading_of_the_target_frames(
    align_on: str, target_batch
) -> None:
    """Eq. 3 in the target world-model step: ``beta2 * KL[sg(e_S(o_T)) || e_T(o_T)]``, where ``e_S(o_T)`` is the
    source model's posterior (or softmaxed embedding) on the *target* batch's frames, made without gradient, and the
    term is added once to the loss the target model's optimiser steps on. The source model does not move."""
    agent = _agent(f"coworld.align_on={align_on}", "coworld.value_reg=false")
    batch = target_batch(b=3, t=5)
    prepared = agent.target.prepare(batch)
    captured: dict[str, Any] = {}
    _spy_world_model_step(agent.target, captured)
    source_before = _snapshot(agent.source.world_model, agent.source.actor_critic)
    target_before = _snapshot(agent.target.world_model)
    torch.manual_seed(3)
    start = torch.get_rng_state()  # the update's own source pass draws its latent samples first
    metrics = agent.train_target(batch)

    assert _unchanged(source_before, agent.source.world_model, agent.source.actor_critic)
    assert not _unchanged(target_before, agent.target.world_model)
    assert all(p.grad is None for p in agent.source.world_model.parameters())
    torch.set_rng_state(start)
    with torch.no_grad():  # the source model, unchanged, over the same target frames, from the same random state
        source_post, _, source_embed = agent.source.world_model.observe(prepared)
    term = captured["extra"]["align"].detach()
    if align_on == "latent":
        log_p = torch.log_softmax(source_post["logits"], -1)
        log_q = torch.log_softmax(captured["post_logits"], -1)
        kl = (log_p.exp() * (log_p - log_q)).sum((-2, -1)).mean()  # summed over the latents, mean over (B, T)
    else:
        log_p, log_q = torch.log_softmax(source_embed, -1), torch.log_softmax(captured["embed"], -1)
        kl = (log_p.exp() * (log_p - log_q)).sum(-1).sum(1).mean()  # the release's batchmean: summed over T
    assert float(kl) > 0.01
    assert float(term) == pytest.approx(BETA2 * float(kl), rel=1e-4)
    assert metrics["target/coworld/align_kl"] == pytest.approx(float(kl), rel=1e-4)
    assert metrics["target/wm/loss"] == pytest.approx(float(captured["aux_loss"]) + BETA2 * float(kl), rel=1e-5)


def test_eq3_gives_the_target_model_beta2_times_the_kls_gradient_and_the_source_model_none(target_batch) -> None:
    """The alignment term's gradient, checked while the update runs: ``beta2`` times the gradient of the KL with
    respect to the target posterior's logits, ``beta2 * (softmax(q) - softmax(p_S)) / (B T)``, and nothing
    flows to the source side (its logits come detached)."""
    agent = _agent("coworld.value_reg=false")
    batch = target_batch(b=2, t=4)
    seen: dict[str, Tensor] = {}

    def check(terms: dict[str, Tensor], aux: dict[str, Any]) -> None:
        logits = aux["post"]["logits"]
        (grad,) = torch.autograd.grad(terms["align"], logits, retain_graph=True)
        seen.update(grad=grad, logits=logits.detach())

    captured: dict[str, Any] = {}
    _spy_world_model_step(agent.target, captured, check)
    torch.manual_seed(4)
    start = torch.get_rng_state()
    agent.train_target(batch)
    torch.set_rng_state(start)
    with torch.no_grad():
        source_post, _, _ = agent.source.world_model.observe(agent.target.prepare(batch))
    b, t = batch["reward"].shape
    expected = BETA2 * (torch.softmax(seen["logits"], -1) - torch.softmax(source_post["logits"], -1)) / (b * t)
    torch.testing.assert_close(seen["grad"], expected, rtol=1e-4, atol=1e-8)


# -- Eqs. 4-5 ---------------------------------------------------------------------------------------------------


def test_eq4_relabels_target_frames_through_the_source_model_with_k_on_its_prediction(target_batch) -> None:
    """Eqs. 4-5 in the source world-model step: the source model reads the *target* batch, its reward head
    predicts ``r_S``, and the head regresses ``k * sg(r_S) + (1 - k) * r_T`` (``r_T`` the target batch's rewards)
    with a unit-Gaussian NLL, averaged over ``(B, T)`` and added with weight 1 to the ordinary world-model loss on
    the source batch (Eq. 5's two expectations). The label carries no gradient, so the head's gradient is
    ``(1 - k) * (r_S - r_T) / (B T)``, not ``(1 - k)^2 * ...``. The target agent does not move."""
    agent = _agent("coworld.value_reg=false", "coworld.align=false")
    source_batch, relabel_batch = target_batch(b=3, t=5), target_batch(b=3, t=5)
    relabel_batch["reward"] = relabel_batch["reward"] * 4.0 - 2.0  # far from the untrained head's ~0 predictions
    prepared = agent.target.prepare(relabel_batch)
    wm = agent.source.world_model
    head_params = list(wm.reward_head.parameters())
    seen: dict[str, Any] = {}

    def check(terms: dict[str, Tensor], aux: dict[str, Any]) -> None:
        torch.set_rng_state(captured["rng"])  # the latent samples the hook's own pass drew
        post, _, _ = wm.observe(prepared)
        pred = wm.reward_head(wm.features(post)).mean
        label = K * pred.detach() + (1.0 - K) * relabel_batch["reward"]
        expected = (0.5 * (pred - label).square()).mean()
        got = torch.autograd.grad(terms["relabel"], head_params, retain_graph=True)
        want = torch.autograd.grad(expected, head_params)
        seen.update(term=terms["relabel"].detach(), expected=expected.detach(), got=got, want=want)
        seen["pred_grad"] = torch.autograd.grad(0.5 * (pred - label).square().mean(), pred)[0]
        seen["pred_minus_reward"] = (pred - relabel_batch["reward"]).detach()

    captured: dict[str, Any] = {}
    _spy_world_model_step(agent.source, captured, check)
    target_before = _snapshot(agent.target.world_model, agent.target.actor_critic)
    torch.manual_seed(5)
    metrics = agent.train_source(source_batch, prepared)

    assert _unchanged(target_before, agent.target.world_model, agent.target.actor_critic)
    assert float(seen["expected"]) > 0.1
    assert float(seen["term"]) == pytest.approx(float(seen["expected"]), rel=1e-5)
    for got, want in zip(seen["got"], seen["want"], strict=True):
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-7)
    b, t = relabel_batch["reward"].shape
    torch.testing.assert_close(seen["pred_grad"], (1.0 - K) * seen["pred_minus_reward"] / (b * t))
    assert metrics["coworld/relabel_reward_loss"] == pytest.approx(float(seen["expected"]), rel=1e-5)
    # Eq. 5's first expectation stays in: the source batch's own loss (its reward term included) plus the second
    assert metrics["wm/loss"] == pytest.approx(float(captured["aux_loss"]) + float(seen["expected"]), rel=1e-5)
    assert metrics["wm/reward"] > 0.0


def test_eq4_relabels_the_target_batch_it_is_given_and_none_when_off(target_batch) -> None:
    """A source update relabels the target batch passed with its source batch, and counts it for Eq. 5's ``eta``;
    with ``coworld.reward_relabel=false`` (or no target batch, as in the pretraining) the source step is plain
    DreamerV2 and adds no term."""
    agent = _agent("coworld.value_reg=false", "coworld.align=false")
    given = agent.target.prepare(target_batch(b=2, t=3))
    assert "coworld/relabel_reward_loss" in agent.train_source(target_batch(b=2, t=3), given)
    assert "coworld/relabel_reward_loss" not in agent.train_source(target_batch(b=2, t=3))
    assert agent.relabelled == 1 and agent.source.updates == 2
    off = _agent("coworld.reward_relabel=false")
    assert "coworld/relabel_reward_loss" not in off.train_source(target_batch(b=2, t=3), given)
    assert off.relabelled == 0


# -- Eq. 6 ------------------------------------------------------------------------------------------------------


def test_eq6_adds_alpha_times_the_max_of_zeta_v_target_and_the_frozen_source_value(target_batch) -> None:
    """Eq. 6 in the target critic step: ``alpha * max(zeta * v_T(z), sg(v_S(z)))`` on the target agent's
    imagined states, ``v_S`` the source critic fed the same features. Its gradient with respect to ``v_T`` is
    ``alpha * zeta`` where ``zeta * v_T > v_S`` and 0 where the source side wins; the source critic gets none."""
    agent = _agent("coworld.align=false")
    with torch.no_grad():  # a source critic of 0 everywhere: the max switches sides where v_T changes sign
        for param in agent.source.actor_critic.critic.parameters():
            param.zero_()
    calls: list[dict[str, Tensor]] = []
    original = agent.target.train_actor_critic

    def spy(post: Any, objective: Any = None, **kwargs: Any) -> Any:
        assert objective is not None

        def recording(feat: Tensor, value: Any, target: Tensor, weight: Tensor) -> Any:
            out, metrics = objective(feat, value, target, weight)
            (grad,) = torch.autograd.grad(out.sum(), value.mean, retain_graph=True)
            calls.append(
                {
                    "feat": feat.detach(),
                    "value": value.mean.detach(),
                    "target": target.detach(),
                    "weight": weight.detach(),
                    "out": out.detach(),
                    "grad": grad,
                }
            )
            return out, metrics

        return original(post, recording, **kwargs)

    agent.target.train_actor_critic = spy
    source_critic = _snapshot(agent.source.actor_critic)
    metrics = agent.train_target(target_batch(b=2, t=4))

    assert len(calls) == 1
    call = calls[0]
    with torch.no_grad():
        source_value = agent.source.actor_critic.critic(call["feat"]).mean
    assert torch.equal(source_value, torch.zeros_like(source_value))
    value, returns, weight = call["value"], call["target"], call["weight"]
    active = ZETA * value > source_value
    assert 0 < int(active.sum()) < active.numel()  # both sides of the max are in play
    max_min = ALPHA * torch.where(active, ZETA * value, source_value)
    # the critic's own regression (a unit Gaussian's NLL) plus the max-min term, both weighted by the discount
    torch.testing.assert_close(call["out"], weight * (0.5 * (value - returns).square() + max_min))
    torch.testing.assert_close(call["grad"], weight * ((value - returns) + ALPHA * ZETA * active.float()))
    assert metrics["target/coworld/maxmin_active"] == pytest.approx(float(active.float().mean()))
    assert metrics["target/critic/regulariser"] == pytest.approx(float(max_min.mean()), rel=1e-5)
    assert _unchanged(source_critic, agent.source.actor_critic)
    assert all(p.grad is None for p in agent.source.actor_critic.parameters())


# -- Algorithm 1's schedule --------------------------------------------------------------------------------------


def test_actor_warmup_holds_the_actor_and_critic_of_both_agents(target_batch) -> None:
    """``train.actor_warmup`` updates train the world model alone, in CoWorld's target and source steps as in
    DreamerV2's ``train``: the actor, critic and slow critic stay as they were, and no actor-critic metric is
    logged; the update after them trains them (Eq. 6's term with them, on the target side)."""
    agent = _agent("train.actor_warmup=2")
    relabelled = agent.target.prepare(target_batch(b=2, t=3))
    updates = (
        ("target", "target/", agent.train_target),
        ("source", "", lambda batch: agent.train_source(batch, relabelled)),  # logged as source/ by its trainer
    )
    for side, prefix, train in updates:
        learner = getattr(agent, side)
        for update in range(3):
            before = _snapshot(learner.actor_critic)
            metrics = train(target_batch(b=2, t=3))
            warming = update < 2
            assert _unchanged(before, learner.actor_critic) == warming, (side, update)
            assert (f"{prefix}critic/loss" in metrics) != warming, (side, update)
            assert (f"{prefix}coworld/maxmin_active" in metrics) == (side == "target" and not warming)
            assert f"{prefix}wm/loss" in metrics
        assert learner.updates == 3


SCHEDULE = [
    "device=cpu",
    "train.prefill=50",
    "train.pretrain_updates=1",
    "train.train_every=5",
    "train.eval_episodes=1",
    "train.prefetch=false",  # batches made as the updates draw them, so the record below is in draw order
    "coworld.pretrain_steps=60",
    "coworld.target_updates=2",
    "coworld.source_updates=3",
    "coworld.eval_every=100",  # the last iteration's evaluation only
    *COEFFICIENTS,
]
K1, K2 = 2, 3


def _fingerprint(agent: Any) -> float:
    """A number that changes when any weight of the agent's world model or actor-critic changes."""
    modules = (agent.world_model, agent.actor_critic)
    return float(sum(p.detach().double().sum() * (i + 1) for m in modules for i, p in enumerate(m.parameters())))


def _record_schedule(monkeypatch: pytest.MonkeyPatch, crash_at_first_relabelled_update: bool = False) -> list[Any]:
    """Patch CoWorld's two updates and Eq. 4's relabelling to append, in call order, ``(kind, detail, source and
    target fingerprints before and after)`` for each update and ``("relabel", target_reward, k)`` for each
    relabelling."""
    events: list[Any] = []
    train_target, train_source = CoWorld.train_target, CoWorld.train_source
    relabel_reward = coworld_module.relabel_reward

    def target(self: CoWorld, batch: Any) -> Any:
        before = (_fingerprint(self.source), _fingerprint(self.target))
        out = train_target(self, batch)
        aligned = ALIGN_SOURCE in batch
        events.append(
            (
                "target",
                (aligned, batch["reward"].clone()),
                before,
                (_fingerprint(self.source), _fingerprint(self.target)),
            )
        )
        return out

    def source(self: CoWorld, batch: Any, target_batch: Any = None) -> Any:
        if crash_at_first_relabelled_update and target_batch is not None:
            raise RuntimeError("simulated crash")
        before = (_fingerprint(self.source), _fingerprint(self.target))
        out = train_source(self, batch, target_batch)
        events.append(
            ("source", target_batch is not None, before, (_fingerprint(self.source), _fingerprint(self.target)))
        )
        return out

    def relabel(pred: Tensor, reward: Tensor, k: float, form: str = "table3") -> Tensor:
        events.append(("relabel", reward.detach().clone(), k))
        return relabel_reward(pred, reward, k, form)

    monkeypatch.setattr(CoWorld, "train_target", target)
    monkeypatch.setattr(CoWorld, "train_source", source)
    monkeypatch.setattr(coworld_module, "relabel_reward", relabel)
    return events


def _stream(dataset: Any, config: Any, iteration: int, n: int) -> list[Tensor]:
    """The rewards of the first ``n`` batches of an iteration's target stream: the sampler seeded by (seed,
    iteration) as the schedule seeds it."""
    sampler = dataset.sampler(config.train.batch_size, config.train.seq_len, seed=config.seed + 1000 * (iteration + 1))
    return [torch.as_tensor(next(sampler)["reward"]) for _ in range(n)]


def test_algorithm_1_freezes_each_agent_while_the_other_learns_and_feeds_each_phase_its_batches(
    tmp_path: Path, toy_dataset_writer, coworld_toy_job, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Algorithm 1 on the toy pair, 2 iterations of K1 = 2 target and K2 = 3 source updates after the source
    pretraining. Pinned: the order (source updates alone, then K1 target, K2 source per iteration); nothing moves
    between updates; a target update moves the target agent only and a source update the source agent only; the
    pretraining relabels nothing; each target update's batch is the iteration's stream's next one and carries the
    source model's pass; each source update relabels exactly one target batch, with ``k``, the stream's next one
    after the target phase's (so the two phases never share a batch)."""
    dataset = toy_dataset_writer(tmp_path / "target.h5", "toy_reach_shifted", episodes=3)
    job = coworld_toy_job(dataset, tmp_path / "run", [*SCHEDULE, "coworld.iterations=2"])
    events = _record_schedule(monkeypatch)
    assert run_job(job, progress=False)["iterations"] == 2

    updates = [e for e in events if e[0] != "relabel"]
    kinds = "".join(e[0][0] for e in updates)
    pretrain = kinds.index("t")
    assert pretrain > 0 and kinds == "s" * pretrain + ("t" * K1 + "s" * K2) * 2
    for previous, update in zip(updates, updates[1:], strict=False):
        assert update[2] == previous[3]  # nothing changes either agent between two updates
    for kind, _, (source_before, target_before), (source_after, target_after) in updates:
        if kind == "target":
            assert source_after == source_before and target_after != target_before
        else:
            assert target_after == target_before and source_after != source_before
    assert not any(e[1] for e in updates[:pretrain])  # no target batches while the source agent pretrains
    assert all(e[1] for e in updates[pretrain:] if e[0] == "source")

    relabelled = [e for e in events if e[0] == "relabel"]
    assert len(relabelled) == 2 * K2 and all(e[2] == K for e in relabelled)
    with open_dataset(dataset) as data:
        for iteration in range(2):
            stream = _stream(data, job.config, iteration, K1 + K2)
            targets = updates[pretrain + iteration * (K1 + K2) :][:K1]
            assert all(aligned for _, (aligned, _), _, _ in targets)
            for (_, (_, reward), _, _), want in zip(targets, stream[:K1], strict=True):
                assert torch.equal(reward, want)
            for (_, reward, _), want in zip(relabelled[iteration * K2 :][:K2], stream[K1:], strict=True):
                assert torch.equal(reward, want)


def test_a_source_phase_resumed_after_a_crash_relabels_the_batches_an_uninterrupted_one_would(
    tmp_path: Path, toy_dataset_writer, coworld_toy_job, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A run killed at its first source update after the target phase resumes in the source phase; its relabelling
    batches continue the iteration's stream after the target phase's K1 batches, as an uninterrupted run's do,
    rather than starting the stream again (and relabelling the batches the target phase trained on)."""
    dataset = toy_dataset_writer(tmp_path / "target.h5", "toy_reach_shifted", episodes=3)
    job = coworld_toy_job(dataset, tmp_path / "run", [*SCHEDULE, "coworld.iterations=1"])
    _record_schedule(monkeypatch, crash_at_first_relabelled_update=True)
    with pytest.raises(RuntimeError, match="simulated crash"):
        run_job(job, progress=False)
    assert torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=True)["progress"]["phase"] == "source"

    monkeypatch.undo()
    events = _record_schedule(monkeypatch)
    run_job(job, progress=False)
    assert [e[0] for e in events if e[0] != "relabel"] == ["source"] * K2
    relabelled = [e[1] for e in events if e[0] == "relabel"]
    with open_dataset(dataset) as data:
        stream = _stream(data, job.config, 0, K1 + K2)
    assert len(relabelled) == K2
    for reward, want in zip(relabelled, stream[K1:], strict=True):
        assert torch.equal(reward, want)


# -- acting, checkpoints, the source update -----------------------------------------------------------------------


def _observations(n: int = 2) -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, (n, 64, 64, 3), dtype=np.uint8)


def _act(policy: Callable[..., Any], *args: Any, **kwargs: Any) -> tuple[np.ndarray, Any]:
    """``policy(*args, **kwargs)`` with torch's default generator seeded: acting draws the latent samples (and in
    'train' mode the actions) from it."""
    torch.manual_seed(7)
    return policy(*args, **kwargs)


def _same_actions(a: tuple[np.ndarray, Any], b: tuple[np.ndarray, Any]) -> bool:
    return bool(np.array_equal(a[0], b[0]))


def test_coworld_acts_with_the_target_agent_in_eval_mode_by_default() -> None:
    """CoWorld's policy is the target agent's (it acts in the target domain), in 'eval' mode unless told,
    passing the state and the rows' ``is_first`` through; its value is the target critic's."""
    agent = _agent()
    obs = _observations()
    first = _act(agent.policy, obs)
    assert _same_actions(first, _act(agent.target.policy, obs, None, "eval"))
    assert not _same_actions(first, _act(agent.target.policy, obs, None, "train"))
    assert not _same_actions(first, _act(agent.source.policy, obs, None, "eval"))
    is_first = np.array([True, False])
    later = _act(agent.policy, obs, first[1], "eval", is_first=is_first)
    assert _same_actions(later, _act(agent.target.policy, obs, first[1], "eval", is_first=is_first))
    assert not np.array_equal(later[0][1], _act(agent.target.policy, obs, None, "eval")[0][1])  # row 1 kept its state
    assert not np.array_equal(later[0][0], _act(agent.target.policy, obs, first[1], "eval")[0][0])  # row 0 restarted
    sampled = _act(agent.policy, obs, None, "train")
    assert _same_actions(sampled, _act(agent.target.policy, obs, None, "train"))
    assert not _same_actions(sampled, first)
    np.testing.assert_array_equal(agent.value(later[1]), agent.target.value(later[1]))


def test_the_source_update_is_named_as_dreamerv2s_and_trains_the_source_agent_alone(target_batch) -> None:
    """CoWorld's source update names its metrics as DreamerV2's update does (the source agent's online trainer,
    which acts with the source agent itself, logs them under ``source/``) and moves the source agent only."""
    agent = _agent("coworld.reward_relabel=false")
    target_before = _snapshot(agent.target.world_model, agent.target.actor_critic)
    metrics = agent.train_source(target_batch(b=2, t=3))
    assert "wm/loss" in metrics and "critic/loss" in metrics
    assert not [key for key in metrics if key.startswith(("source/", "target/"))]
    assert agent.source.updates == 1 and agent.target.updates == 0
    assert _unchanged(target_before, agent.target.world_model, agent.target.actor_critic)


def test_a_coworld_state_dict_round_trips_both_agents() -> None:
    """``state_dict``/``load_state_dict`` carry the target and the source agent, each to its own side."""
    saved = _agent()
    torch.manual_seed(1)
    other = CoWorld(config=saved.config, action_size=2, device="cpu")
    state = saved.state_dict()
    assert set(state) == {"target", "source"}
    other.load_state_dict(state)
    for side in ("target", "source"):
        want, have = getattr(saved, side), getattr(other, side)
        for module in ("world_model", "actor_critic"):
            assert _unchanged(_snapshot(getattr(want, module)), getattr(have, module)), (side, module)


def test_target_batches_carry_no_source_pass_when_alignment_is_off(target_batch) -> None:
    """With ``coworld.align=false`` no batch is made with the source model's pass, however many were asked for."""
    agent = _agent("coworld.align=false")
    made = TargetBatches(agent, aligned=2, seed=0)
    assert not any(ALIGN_SOURCE in made(target_batch(b=2, t=3)) for _ in range(3))


def test_with_eqs_3_and_6_off_a_target_update_is_offline_dreamerv2s(target_batch) -> None:
    """With alignment and the value cap off, CoWorld's target update is offline DreamerV2's: from the same weights,
    optimiser states, batches and random state, the same metrics at every update and the same weights after them,
    the world model alone first (``train.actor_warmup``) and then both. So the cap study's arm without alignment
    differs from offline DreamerV2 in Eq. 6 alone, and CoWorld with both off in nothing."""
    agent = _agent("coworld.align=false", "coworld.value_reg=false", "train.actor_warmup=1")
    plain = DreamerV2(config=agent.config, action_size=2, device="cpu")
    plain.load_state_dict(agent.target.state_dict())
    for step in range(3):
        batch = target_batch(b=2, t=4)
        torch.manual_seed(step)
        got = agent.train_target(batch)
        torch.manual_seed(step)
        want = plain.train(batch)
        assert got == {f"target/{key}": value for key, value in want.items()}, step
        assert ("target/critic/value" in got) == (step >= 1), step
    for module in ("world_model", "actor_critic"):
        assert _unchanged(_snapshot(getattr(plain, module)), getattr(agent.target, module)), module


def test_both_updates_imagine_from_the_batchs_true_terminal_flags(target_batch) -> None:
    """The target and the source actor-critic steps start imagination with the batch's ``is_terminal`` (its true
    continuation), not the predicted one."""
    agent = _agent("coworld.reward_relabel=false")
    seen: dict[str, Any] = {}
    for side in ("target", "source"):
        learner = getattr(agent, side)
        original = learner.train_actor_critic

        def spy(post: Any, *args: Any, _side: str = side, _original: Any = original, **kwargs: Any) -> Any:
            seen[_side] = kwargs.get("is_terminal")
            return _original(post, *args, **kwargs)

        learner.train_actor_critic = spy
    batch = target_batch(b=2, t=3)
    batch["is_terminal"][1, 2] = True
    agent.train_target(batch)
    agent.train_source(batch)
    for side in ("target", "source"):
        assert seen[side] is not None and torch.equal(torch.as_tensor(seen[side]).cpu(), batch["is_terminal"]), side


def test_coworld_builds_both_agents_on_the_device_it_is_given_and_refuses_an_unknown_alignment() -> None:
    """The ``device`` argument, not ``config.device``, places both agents (a config saved on a GPU machine resumes
    on a CPU), and CoWorld's device is theirs; an ``align_on`` that slipped past the config's check (a config built
    by hand) is refused naming the choices."""
    config = make_config("tiny", ["device=cuda"])
    agent = CoWorld(config=config, action_size=2, device="cpu")
    assert agent.device == agent.target.device == agent.source.device == torch.device("cpu")
    bad = dataclasses.replace(config, coworld=dataclasses.replace(config.coworld, align_on="encoder"))
    with pytest.raises(ConfigError, match=r"^coworld.align_on must be one of latent, embedding, not 'encoder'$"):
        CoWorld(config=bad, action_size=2, device="cpu")
