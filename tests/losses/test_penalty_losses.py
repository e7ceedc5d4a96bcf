"""The ensemble-disagreement penalty of V-D4RL's offline DreamerV2 on hand-worked numbers (coworld.losses.penalty)."""

from __future__ import annotations

import math

import pytest
import torch

from coworld.losses.penalty import head_loss, mean_disagreement, penalised_reward


def test_identical_heads_do_not_disagree() -> None:
    logits = torch.randn(1, 4, 3, 5).expand(7, 4, 3, 5)
    torch.testing.assert_close(mean_disagreement(logits), torch.zeros(4), atol=1e-6, rtol=0)


def test_mean_disagreement_is_the_mean_frobenius_distance_to_the_mean_table() -> None:
    # Two heads, one variable of two classes: p1 = (0.9, 0.1), p2 = (0.1, 0.9), mean (0.5, 0.5).
    # ||p_k - mean||_F = sqrt(0.4^2 + 0.4^2) for both, so u = 0.4 * sqrt(2).
    probs = torch.tensor([[[0.9, 0.1]], [[0.1, 0.9]]])  # (K=2, S=1, C=2)
    assert float(mean_disagreement(probs.log())) == pytest.approx(0.4 * math.sqrt(2), rel=1e-5)
    # A third head equal to the mean: distances (0.4 sqrt 2, 0.4 sqrt 2, 0) / 3.
    three = torch.tensor([[[0.9, 0.1]], [[0.1, 0.9]], [[0.5, 0.5]]])
    assert float(mean_disagreement(three.log())) == pytest.approx(2 * 0.4 * math.sqrt(2) / 3, rel=1e-5)


def test_penalised_reward_subtracts_weight_times_disagreement() -> None:
    reward = torch.tensor([[1.0, 2.0]])
    torch.testing.assert_close(penalised_reward(reward, torch.tensor([[0.1, 0.0]]), 10.0), torch.tensor([[0.0, 2.0]]))
    with pytest.raises(ValueError, match="must match"):
        penalised_reward(reward, torch.zeros(2), 1.0)


def test_head_loss_is_the_kl_to_the_detached_posterior_on_the_assigned_steps() -> None:
    post = torch.tensor([[[0.9, 0.1]], [[0.5, 0.5]]]).log().requires_grad_(True)  # (T=2, S=1, C=2)
    heads = torch.tensor([[[[0.5, 0.5]], [[0.5, 0.5]]], [[[0.9, 0.1]], [[0.5, 0.5]]]]).log()  # (K=2, T=2, S, C)
    heads.requires_grad_(True)
    mask = torch.tensor([[1, 1], [1, 0]])
    loss = head_loss(post, heads, mask)
    kl = 0.9 * math.log(0.9 / 0.5) + 0.1 * math.log(0.1 / 0.5)  # KL[(0.9, 0.1) || (0.5, 0.5)]
    torch.testing.assert_close(loss.detach(), torch.tensor([[kl, 0.0], [0.0, 0.0]]))
    loss.sum().backward()
    assert post.grad is None or torch.all(post.grad == 0)  # the posterior is a target, not trained here
    assert heads.grad is not None and heads.grad[0, 0].abs().sum() > 0 and heads.grad[1, 1].abs().sum() == 0


def test_head_loss_refuses_mismatched_shapes() -> None:
    with pytest.raises(ValueError, match="must be"):
        head_loss(torch.zeros(2, 1, 2), torch.zeros(3, 2, 1, 2), torch.ones(3, 5))
