"""The evaluation protocol: reproducible whatever the worker count, and the value check's alignment."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from coworld import envs
from coworld.agents.dreamerv2 import DreamerV2
from coworld.config import make_config
from coworld.data.values import true_values
from coworld.training.evaluate import episode_seed, evaluate

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def tiny_agent() -> DreamerV2:
    torch.manual_seed(0)
    return DreamerV2(config=make_config("tiny", ["device=cpu"]), action_size=2)


def test_true_values_start_with_the_reward_received_on_arriving() -> None:
    # rewards[t] is earned by the action at o_t; the critic at z_t counts the reward of arriving at o_t first,
    # which is zero at the reset: arrival rewards [0, 1, 2, 3].
    values = true_values(np.array([1.0, 2.0, 3.0]), discount=0.5)
    assert values == pytest.approx([0 + 0.5 * 1 + 0.25 * 2 + 0.125 * 3, 1 + 0.5 * 2 + 0.25 * 3, 2 + 0.5 * 3])


def test_returns_depend_on_the_seed_alone_not_on_workers_or_the_global_rng() -> None:
    agent = tiny_agent()
    one, _ = evaluate(agent, "toy_reach", episodes=3, workers=1, seed=4, discount=0.99)
    torch.manual_seed(123)  # the global stream must not matter
    before = torch.get_rng_state()
    two, _ = evaluate(agent, "toy_reach", episodes=3, workers=2, seed=4, discount=0.99)
    assert torch.equal(torch.get_rng_state(), before)  # evaluation leaves torch's global state untouched
    assert one.returns == two.returns
    assert one.value_estimate == two.value_estimate
    assert one.reward_estimate is not None and one.reward_estimate == two.reward_estimate  # DreamerV2's reward head
    other, _ = evaluate(agent, "toy_reach", episodes=3, workers=1, seed=5, discount=0.99)
    assert other.returns != one.returns  # the seed does matter


class _Walker:
    """Acts with one fixed action; its critic and reward head say the step index, so each state's prediction is
    known."""

    def policy(self, obs, state, mode="eval", is_first=None):
        t = 0 if state is None else state + 1
        return np.full((1, 2), 0.7, np.float32), t

    def value(self, state):
        return np.array([0.0])

    def predicted_reward(self, state):
        return np.array([float(state)])


def test_the_reward_check_sets_each_reached_states_prediction_beside_the_reward_of_arriving_there() -> None:
    result, _ = evaluate(_Walker(), "toy_reach", episodes=1, seed=3, discount=0.99)
    env = envs.make_vector("toy_reach", 1, seed=3)
    env.reset(seed=[episode_seed(3, 0)])
    rewards = []
    for _ in range(envs.task_spec("toy_reach").episode_length):
        _, reward, terminated, truncated, _ = env.step(np.full((1, 2), 0.7, np.float32))
        rewards.append(float(reward[0]))
        if terminated[0] or truncated[0]:
            break
    env.close()
    assert len(set(rewards)) > 1  # the rewards change, so arriving and leaving differ
    assert result.reward_true == pytest.approx([np.mean([0.0, *rewards[:-1]])])  # the reset is arrived at with 0
    assert result.reward_estimate == pytest.approx([np.mean(range(len(rewards)))])  # one prediction per state
    assert result.metrics()["eval/reward_true"] == pytest.approx(result.reward_true[0])
    assert "reward a step predicted" in result.summary()
    assert evaluate(_Walker(), "toy_reach", episodes=1, seed=3)[0].reward_estimate is None  # no discount, no checks
