"""V-D4RL's offline DreamerV2: its two phases, the penalised imagined reward, and checkpoints."""

from __future__ import annotations

import io
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import torch

from coworld.agents.dreamerv2_penalty import PenaltyDreamerV2
from coworld.config import make_config

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_world_model_phase_then_actor_critic_phase_on_the_penalised_reward(
    numpy_batch: Callable[..., Any], flat_params: Callable[..., Any]
) -> None:
    config = make_config("tiny", ["device=cpu", "penalty.model_updates=2", "penalty.weight=3.0"])
    torch.manual_seed(0)
    agent = PenaltyDreamerV2(config=config, action_size=2)
    rng = np.random.default_rng(0)
    wm, actor, heads = (
        flat_params(agent.world_model),
        flat_params(agent.actor_critic.actor),
        flat_params(agent.ensemble),
    )
    for _ in range(2):
        metrics = agent.train(numpy_batch(rng))
        assert "penalty/head_kl" in metrics and not any(key.startswith("actor/") for key in metrics)
    assert not torch.equal(flat_params(agent.world_model), wm) and not torch.equal(flat_params(agent.ensemble), heads)
    assert torch.equal(flat_params(agent.actor_critic.actor), actor)  # phase 1 leaves the actor alone
    wm, heads = flat_params(agent.world_model), flat_params(agent.ensemble)
    metrics = agent.train(numpy_batch(rng))
    assert torch.equal(flat_params(agent.world_model), wm) and torch.equal(flat_params(agent.ensemble), heads)  # frozen
    assert not torch.equal(flat_params(agent.actor_critic.actor), actor)
    # The actor-critic learnt from r - 3 * u: the imagined reward it logs is the head's reward less the penalty.
    assert metrics["penalty/disagreement"] > 0.0
    expected = metrics["penalty/raw"] - 3.0 * metrics["penalty/disagreement"]
    assert metrics["imag/reward"] == pytest.approx(expected, rel=1e-4, abs=1e-5)


def test_state_dict_round_trip_keeps_the_heads_through_weights_only_load(
    numpy_batch: Callable[..., Any], flat_params: Callable[..., Any]
) -> None:
    config = make_config("tiny", ["device=cpu", "penalty.model_updates=1"])
    torch.manual_seed(0)
    agent = PenaltyDreamerV2(config=config, action_size=2)
    agent.train(numpy_batch(np.random.default_rng(0)))
    buffer = io.BytesIO()
    torch.save(agent.state_dict(), buffer)
    buffer.seek(0)
    clone = PenaltyDreamerV2(config=config, action_size=2)
    clone.load_state_dict(torch.load(buffer, weights_only=True))
    assert clone.updates == 1 and torch.equal(flat_params(clone.ensemble), flat_params(agent.ensemble))
    batch = numpy_batch(np.random.default_rng(1))
    torch.manual_seed(3)
    expected = agent.train(batch)
    torch.manual_seed(3)
    assert clone.train(batch) == pytest.approx(expected)


TINY_COLLAPSES = pytest.mark.xfail(
    strict=True,
    reason="known failure (issue 18): on the tiny preset the offline agent's actor collapses to a constant action; "
    "learned 4.1 against random 15.0 at 8db5422 (measured 2026-11-24), 4.5 at c521e33 where this test was merged",
)


CPU_TOO_FEW_UPDATES = pytest.mark.xfail(
    strict=False,
    reason="known failure (issue 21): the cpu preset's actor-critic does not learn reliably in these 600 updates "
    "on this data; learned 14.2 against random 15.0 at 5ce5863, and 0.7 with penalty.weight=0 (measured "
    "2026-11-24). Its outcome turns on float rounding: the same function with the decoder's backward summed in "
    "another order (1c1ac30) learned 28.9; at 4a122f8 seeds 0-4 learned 30.8, 0.6, 1.9, 31.1, 0.6 (random 15.0; "
    "benchmarks/RESULTS.md), so this seed can pass",
)


@pytest.mark.slow
@pytest.mark.parametrize(
    "preset", [pytest.param("tiny", marks=TINY_COLLAPSES), pytest.param("cpu", marks=CPU_TOO_FEW_UPDATES)]
)
def test_dreamerv2_penalty_learns_toy_reach_offline(tmp_path, toy_expert, preset):
    """V-D4RL's penalised DreamerV2 on 30 noisy-expert toy_reach episodes: 400 world-model updates, then 600
    actor-critic updates on the penalised reward, must beat a uniform random policy clearly.

    Measured at a9da0c3 (before the lead's actor fix): random 15.0, learned 2.5 (the actor's entropy falls to -2.4
    and the policy collapses to a constant action, the known DreamerV2 problem), so this test fails there. The
    ``tiny`` preset keeps DreamerV2's actor and still collapses. The ``cpu`` preset, whose DreamerV2 learns online
    (issue 18), does not learn here either, with or without the penalty: its imagined reward is about 1 everywhere on
    this near-expert data, and its actor learns online over 1,500 updates, not 600."""
    from coworld.agents.dreamerv2_penalty import PenaltyDreamerV2
    from coworld.data import open_dataset

    path = tmp_path / "toy_reach-expert.h5"
    toy_expert.write_dataset(path, episodes=30, noise=0.3, seed=0)
    config = make_config(preset, ["device=cpu", "penalty.model_updates=400", "train.batch_size=16"])
    torch.manual_seed(0)
    agent = PenaltyDreamerV2(config=config, action_size=2, device="cpu")
    with open_dataset(path) as dataset:
        batches = iter(dataset.sampler(16, 16, seed=0))
        for _ in range(1000):
            agent.train(next(batches))
    rng = np.random.default_rng(0)
    random = toy_expert.mean_return(
        lambda obs, state, first: (rng.uniform(-1, 1, (len(obs), 2)).astype(np.float32), state), episodes=5, seed=100
    )
    learned = toy_expert.mean_return(
        lambda obs, state, first: agent.policy(obs, state, "eval", is_first=first), episodes=5, seed=100
    )
    print(f"{preset}: learned {learned:.1f}, random {random:.1f}")
    assert learned > random + 10.0, (learned, random)
