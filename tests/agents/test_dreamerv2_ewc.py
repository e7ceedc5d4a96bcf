"""DreamerV2 fine-tuned with EWC: the consolidation, the pull toward the source weights, and checkpoints."""

from __future__ import annotations

import io
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import torch

from coworld.agents.dreamerv2 import DreamerV2
from coworld.agents.dreamerv2_ewc import NETWORKS, EwcDreamerV2
from coworld.config import make_config
from coworld.losses.ewc import ewc_penalty
from coworld.models.actor_critic import flatten_states
from coworld.models.networks import frozen_parameters

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_consolidate_anchors_the_current_weights_and_changes_nothing(
    numpy_batch: Callable[..., Any], flat_params: Callable[..., Any]
) -> None:
    config = make_config("cpu", ["device=cpu"])
    torch.manual_seed(0)
    agent = EwcDreamerV2(config=config, action_size=2)
    rng = np.random.default_rng(0)
    for _ in range(3):
        agent.train(numpy_batch(rng))
    before = {name: flat_params(module) for name, module in agent.networks().items()}
    buffers = {k: v.clone() for k, v in agent.actor_critic.named_buffers()}
    metrics = agent.consolidate(numpy_batch(rng) for _ in range(3))
    assert agent.consolidated and set(metrics) == {f"ewc/fisher_{name}" for name in NETWORKS}
    for name, module in agent.networks().items():
        assert torch.equal(flat_params(module), before[name])  # no step was taken
        assert set(agent.anchor[name]) == {key for key, _ in module.named_parameters()}
        anchored = torch.cat([agent.anchor[name][key].reshape(-1) for key, _ in module.named_parameters()])
        assert torch.equal(anchored, before[name])
        fisher = torch.cat([f.reshape(-1) for f in agent.fisher[name].values()])
        assert (fisher >= 0).all() and fisher.sum() > 0 and metrics[f"ewc/fisher_{name}"] > 0
        assert agent.penalty(name).item() == 0.0  # at the anchor
        assert all(p.grad is None for p in module.parameters())
    assert all(torch.equal(v, buffers[k]) for k, v in agent.actor_critic.named_buffers())


def test_the_fisher_of_one_batch_is_its_squared_gradient_times_its_steps(numpy_batch: Callable[..., Any]) -> None:
    config = make_config("tiny", ["device=cpu"])
    torch.manual_seed(0)
    agent = EwcDreamerV2(config=config, action_size=2)
    batch = numpy_batch(np.random.default_rng(0), B=2, T=6)
    torch.manual_seed(5)
    agent.consolidate([batch])
    # By hand, with the same draws: the world model's loss, then the actor-critic's on the states it imagines from.
    torch.manual_seed(5)
    batch_t = agent.to_batch(batch)
    _, aux = agent.model_path.loss(batch_t)
    aux["loss"].backward()
    post = {key: value.detach() for key, value in aux["post"].items()}
    with frozen_parameters(agent.world_model):
        traj = agent.actor_critic.imagine(
            agent.world_model, flatten_states(post), is_terminal=batch_t["is_terminal"].reshape(-1)
        )
        terms, _ = agent.actor_critic.losses(agent.world_model, traj)
    (terms["actor"] + terms["critic"]).backward()
    for name, module in agent.networks().items():
        for key, p in module.named_parameters():
            expected = 12 * p.grad.square() if p.grad is not None else torch.zeros_like(p)  # 2 x 6 steps
            torch.testing.assert_close(agent.fisher[name][key], expected, rtol=1e-5, atol=1e-12)


def _trained(numpy_batch: Callable[..., Any], cls: type, *sets: str) -> DreamerV2:
    """An agent of ``cls`` after 3 seeded updates (its "source" learning), consolidated on 3 batches if it can."""
    config = make_config("cpu", ["device=cpu", *sets])  # the cpu preset: return normalisation's statistics too
    torch.manual_seed(0)
    agent = cls(config=config, action_size=2)
    rng = np.random.default_rng(0)
    for i in range(3):
        torch.manual_seed(10 + i)
        agent.train(numpy_batch(rng))
    if isinstance(agent, EwcDreamerV2):
        agent.consolidate(numpy_batch(rng) for _ in range(3))
    return agent


def test_weight_zero_trains_as_dreamerv2_and_a_large_weight_holds_the_source_weights(
    numpy_batch: Callable[..., Any], flat_params: Callable[..., Any]
) -> None:
    rng = np.random.default_rng(7)
    batches = [numpy_batch(rng) for _ in range(8)]
    plain = _trained(numpy_batch, DreamerV2)
    for i, batch in enumerate(batches):
        torch.manual_seed(20 + i)
        plain.train(batch)
    moved = {}
    for weight in (0.0, 1e8):
        agent = _trained(numpy_batch, EwcDreamerV2, f"ewc.weight={weight}")
        for i, batch in enumerate(batches):
            torch.manual_seed(20 + i)
            metrics = agent.train(batch)
        assert {"wm/ewc", "actor/ewc", "critic/ewc"} <= set(metrics)
        if weight == 0.0:  # EWC's term is zero: the updates are DreamerV2's
            assert metrics["wm/ewc"] == 0.0
            for name, module in agent.networks().items():
                torch.testing.assert_close(flat_params(module), flat_params(dict(_networks(plain))[name]))
        # How far each network went where the source's fit cares: sum_i F_i (theta_i - theta*_i)^2.
        moved[weight] = {
            name: ewc_penalty(dict(module.named_parameters()), agent.anchor[name], agent.fisher[name], 2.0).item()
            for name, module in agent.networks().items()
        }
    for name in NETWORKS:
        assert moved[1e8][name] < 0.1 * moved[0.0][name], (name, moved)


def _networks(agent: DreamerV2):
    return {
        "world_model": agent.world_model,
        "actor": agent.actor_critic.actor,
        "critic": agent.actor_critic.critic,
    }.items()


def test_state_dict_round_trip_keeps_the_anchor_and_fisher_through_weights_only_load(
    numpy_batch: Callable[..., Any],
) -> None:
    agent = _trained(numpy_batch, EwcDreamerV2)
    buffer = io.BytesIO()
    torch.save(agent.state_dict(), buffer)
    buffer.seek(0)
    clone = EwcDreamerV2(config=agent.config, action_size=2)
    clone.load_state_dict(torch.load(buffer, weights_only=True))
    assert clone.consolidated
    for name in NETWORKS:
        for key, value in agent.fisher[name].items():
            assert torch.equal(clone.fisher[name][key], value) and torch.equal(
                clone.anchor[name][key], agent.anchor[name][key]
            )
    batch = numpy_batch(np.random.default_rng(1))
    torch.manual_seed(3)
    expected = agent.train(batch)
    torch.manual_seed(3)
    assert clone.train(batch) == pytest.approx(expected)
    # A plain agent's state (no consolidation yet, as the source phase saves it) loads too: nothing anchored.
    fresh = EwcDreamerV2(config=agent.config, action_size=2)
    fresh.load_state_dict(EwcDreamerV2(config=agent.config, action_size=2).state_dict())
    assert not fresh.consolidated
