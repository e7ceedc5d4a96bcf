"""LOMPO's uncertainty penalty and latent actor-critic terms on hand-worked numbers (coworld.losses.lompo)."""

from __future__ import annotations

import math

import pytest
import torch

from coworld.losses.lompo import deterministic_actor_loss, log_prob_spread, td_target


def test_log_prob_spread_is_the_population_std_of_the_heads_log_probabilities_of_the_draw() -> None:
    # Two heads, one variable of two classes, z = class 1: log p = (log 0.5, log 0.75); their std (1/K) is half the gap.
    heads = torch.tensor([[[0.5, 0.5]], [[0.25, 0.75]]]).log()  # (K=2, S=1, C=2)
    z = torch.tensor([[0.0, 1.0]])
    assert float(log_prob_spread(heads, z)) == pytest.approx(math.log(1.5) / 2, rel=1e-6)
    # The draw of class 0 instead: log p = (log 0.5, log 0.25), gap log 2.
    assert float(log_prob_spread(heads, torch.tensor([[1.0, 0.0]]))) == pytest.approx(math.log(2) / 2, rel=1e-6)
    # Two variables, each drawn as above: log p(z) sums over them, so the spread doubles.
    two = torch.cat([heads, heads], dim=1)  # (K, S=2, C)
    assert float(log_prob_spread(two, z.expand(2, 2))) == pytest.approx(math.log(1.5), rel=1e-6)


def test_log_prob_spread_of_three_heads_and_of_agreeing_heads() -> None:
    # log p_k(z) = log(0.5), log(0.25), log(0.125) = -a, -2a, -3a with a = log 2: population std a * sqrt(2/3).
    heads = torch.tensor([[[0.5, 0.5]], [[0.75, 0.25]], [[0.875, 0.125]]]).log()
    assert float(log_prob_spread(heads, torch.tensor([[0.0, 1.0]]))) == pytest.approx(
        math.log(2) * math.sqrt(2 / 3), rel=1e-6
    )
    same = torch.randn(1, 4, 3, 5).log_softmax(-1).expand(7, 4, 3, 5)
    draw = torch.nn.functional.one_hot(torch.randint(5, (4, 3)), 5).float()
    torch.testing.assert_close(log_prob_spread(same, draw), torch.zeros(4), atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="must be"):
        log_prob_spread(same, draw[:, :2])


def test_td_target_bootstraps_from_the_smaller_target_q_unless_done() -> None:
    reward, not_done = torch.tensor([1.0, 1.0]), torch.tensor([1.0, 0.0])
    next_q1 = torch.tensor([2.0, 2.0], requires_grad=True)
    next_q2 = torch.tensor([3.0, -5.0])
    target = td_target(reward, not_done, next_q1, next_q2, discount=0.5)
    torch.testing.assert_close(target, torch.tensor([2.0, 1.0]))  # 1 + 0.5 * min(2, 3); 1 (terminal)
    assert not target.requires_grad


def test_deterministic_actor_loss_is_minus_the_smaller_q_with_its_gradient() -> None:
    q1 = torch.tensor([1.0, 4.0], requires_grad=True)
    q2 = torch.tensor([2.0, 3.0], requires_grad=True)
    loss = deterministic_actor_loss(q1, q2)
    torch.testing.assert_close(loss, torch.tensor([-1.0, -3.0]))
    loss.sum().backward()
    torch.testing.assert_close(q1.grad, torch.tensor([-1.0, 0.0]))
    torch.testing.assert_close(q2.grad, torch.tensor([0.0, -1.0]))
