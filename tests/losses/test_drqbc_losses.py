"""DrQ+BC's loss terms on hand-worked numbers (coworld.losses.drqbc)."""

from __future__ import annotations

import pytest
import torch

from coworld.losses.curl import sac_critic_target, twin_q_loss
from coworld.losses.drqbc import actor_terms, clipped_noise_action, exploration_std


def test_exploration_std_is_linear_then_flat() -> None:
    kw = dict(init=1.0, final=0.1, duration=100)
    assert exploration_std(0, **kw) == pytest.approx(1.0)
    assert exploration_std(50, **kw) == pytest.approx(0.55)
    assert exploration_std(100, **kw) == pytest.approx(0.1)
    assert exploration_std(10_000, **kw) == pytest.approx(0.1)


def test_clipped_noise_action_clips_the_noise_then_the_action_with_a_straight_through_gradient() -> None:
    mean = torch.tensor([[0.5, 0.9, -0.2, 0.0]], requires_grad=True)
    noise = torch.tensor([[0.1, 1.0, -2.0, 0.2]])
    action = clipped_noise_action(mean, std=1.0, clip=0.3, noise=noise)
    # noise * std = 0.1, 1.0 -> 0.3, -2.0 -> -0.3, 0.2; then the action box [-1 + 1e-6, 1 - 1e-6]
    torch.testing.assert_close(action.detach(), torch.tensor([[0.6, 1.0 - 1e-6, -0.5, 0.2]]))
    action.sum().backward()
    torch.testing.assert_close(mean.grad, torch.ones_like(mean))


def test_actor_terms_scale_q_by_alpha_over_mean_abs_q_and_add_the_action_mse() -> None:
    q = torch.tensor([1.0, -3.0], requires_grad=True)
    action = torch.tensor([[0.0, 0.0], [1.0, 1.0]])
    data = torch.tensor([[1.0, 1.0], [1.0, -1.0]])
    terms = actor_terms(q, action, data, bc_weight=2.5)
    # lambda = 2.5 / mean(|1|, |-3|) = 1.25
    assert float(terms["lambda"]) == pytest.approx(1.25)
    torch.testing.assert_close(terms["rl"].detach(), torch.tensor([-1.25, 3.75]))
    torch.testing.assert_close(terms["bc"], torch.tensor([1.0, 2.0]))  # mean over A: (1 + 1) / 2, (0 + 4) / 2
    terms["rl"].sum().backward()
    torch.testing.assert_close(q.grad, torch.tensor([-1.25, -1.25]))  # lambda itself carries no gradient


def test_actor_terms_refuse_mismatched_actions() -> None:
    with pytest.raises(ValueError, match="must both be"):
        actor_terms(torch.zeros(2), torch.zeros(2, 3), torch.zeros(2, 2), bc_weight=2.5)


def test_drq_critic_target_is_the_sac_target_without_entropy() -> None:
    """DrQ-v2's ``y = r + gamma * not_done * min(Q1', Q2')`` (the agent calls SAC's target with alpha 0)."""
    reward, not_done = torch.tensor([1.0, 2.0]), torch.tensor([1.0, 0.0])
    next_q1, next_q2 = torch.tensor([3.0, 5.0]), torch.tensor([4.0, 1.0])
    y = sac_critic_target(reward, not_done, next_q1, next_q2, torch.zeros(2), 0.0, 0.5)
    torch.testing.assert_close(y, torch.tensor([2.5, 2.0]))
    torch.testing.assert_close(
        twin_q_loss(torch.tensor([2.0, 2.0]), torch.tensor([3.0, 0.0]), y), torch.tensor([0.5, 4.0])
    )
