"""Eq. 6 at work: where the source critic is lower, the max-min term pulls the target critic down.

The source critic is fixed at 0 everywhere (its weights zeroed), so ``max(zeta * v_T, sg(v_S))`` is active wherever
the target critic is positive. The target agent then learns toy_reach offline from a small random-policy dataset,
twice from the same initial weights and the same batches: with and without the term. Its critic's estimates in the
target environment must be clearly lower with the term, and the term must have been active.

An earlier version of this test relied on the offline critic overestimating on this setup (7.1 against a true 0.2).
Once the loop followed DreamerV2 (no discount head, windows starting from a fresh latent, the slow critic copied
after its step) the same setup underestimated instead (-5.5 below the true value), so the premise no longer held;
the term's effect is now tested where it is known to apply.
"""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
import torch

from coworld.agents.coworld import CoWorld
from coworld.config import make_config
from coworld.data import open_dataset
from coworld.training.evaluate import evaluate


@pytest.mark.long
def test_max_min_term_pulls_the_target_critic_down_to_a_lower_source_critic(toy_dataset_writer, tmp_path):
    torch.manual_seed(0)
    config = make_config(
        "tiny",
        ["device=cpu", "coworld.align=false", "coworld.reward_relabel=false", "coworld.alpha=1.0"],
    )
    agent = CoWorld(config=config, action_size=2, device="cpu")
    with torch.no_grad():
        for param in agent.source.actor_critic.critic.parameters():
            param.zero_()
    data_path = toy_dataset_writer(tmp_path / "target.h5", "toy_reach", episodes=10)
    init = copy.deepcopy(agent.target.state_dict())  # both runs start from these weights
    estimate, active = {}, {}
    with open_dataset(data_path) as data:
        for value_reg in (False, True):
            agent.config = dataclasses.replace(config, coworld=dataclasses.replace(config.coworld, value_reg=value_reg))
            agent.target.load_state_dict(init)
            torch.manual_seed(1)
            batches = data.sampler(config.train.batch_size, config.train.seq_len, seed=1)
            for _ in range(75):
                metrics = agent.train_target(next(batches))
            active[value_reg] = metrics.get("target/coworld/maxmin_active")
            result, _ = evaluate(agent, "toy_reach", episodes=4, seed=7, discount=0.99)
            estimate[value_reg] = float(np.mean(result.value_estimate))
    assert active[True] is not None and active[True] > 0.0  # the term was in play
    assert estimate[False] > 1.0  # rewards are positive: an unregularised critic learns positive values
    assert estimate[True] < 0.5 * estimate[False], estimate
