"""DreamerV2's pure loss functions (coworld/losses/dreamer.py): hand-computed cases and autograd checks."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from coworld.distributions import Bernoulli, UnitGaussian, categorical_kl
from coworld.losses.dreamer import (
    actor_loss,
    critic_loss,
    discount_loss,
    image_loss,
    kl_balanced_loss,
    lambda_return,
    reward_loss,
)


def test_lambda_return_matches_hand_computed_recursion() -> None:
    reward = torch.tensor([[1.0], [0.0], [2.0]])
    value = torch.tensor([[0.5], [1.5], [-1.0]])
    cont = torch.tensor([[0.9], [0.8], [0.0]])
    bootstrap = torch.tensor([4.0])
    lam = 0.5
    # Backwards from R_3 = v_3 = 4, with R_t = r_t + c_t * ((1 - lam) * v_{t+1} + lam * R_{t+1}).
    r2 = 2.0 + 0.0 * (0.5 * 4.0 + 0.5 * 4.0)
    r1 = 0.0 + 0.8 * (0.5 * -1.0 + 0.5 * r2)
    r0 = 1.0 + 0.9 * (0.5 * 1.5 + 0.5 * r1)
    expected = torch.tensor([[r0], [r1], [r2]])
    torch.testing.assert_close(lambda_return(reward, value, cont, bootstrap, lam), expected)


def test_lambda_return_limits_are_td0_and_monte_carlo() -> None:
    reward, value = torch.randn(4, 3), torch.randn(4, 3)
    cont, bootstrap = torch.full((4, 3), 0.9), torch.randn(3)
    next_value = torch.cat([value[1:], bootstrap[None]])
    torch.testing.assert_close(lambda_return(reward, value, cont, bootstrap, 0.0), reward + 0.9 * next_value)
    discounts = 0.9 ** torch.arange(4.0)
    mc0 = (discounts[:, None] * reward).sum(0) + 0.9**4 * bootstrap
    torch.testing.assert_close(lambda_return(reward, value, cont, bootstrap, 1.0)[0], mc0)


def test_lambda_return_rejects_mismatched_shapes() -> None:
    with pytest.raises(ValueError, match="one shape"):
        lambda_return(torch.zeros(3, 2), torch.zeros(3, 2), torch.zeros(2, 2), torch.zeros(2), 0.95)


def test_kl_balance_splits_gradient_between_prior_and_posterior() -> None:
    post = torch.randn(2, 3, 4, 5, requires_grad=True)
    prior = torch.randn(2, 3, 4, 5, requires_grad=True)
    loss, kl = kl_balanced_loss(post, prior, balance=0.8, free_nats=0.0)
    grad_post, grad_prior = torch.autograd.grad(loss, (post, prior))
    plain = categorical_kl(post, prior).mean()
    plain_post, plain_prior = torch.autograd.grad(plain, (post, prior))
    torch.testing.assert_close(grad_prior, 0.8 * plain_prior)
    torch.testing.assert_close(grad_post, 0.2 * plain_post)
    assert kl.shape == (2, 3)
    torch.testing.assert_close(kl.detach(), categorical_kl(post, prior).detach())
    torch.testing.assert_close(loss.detach(), plain.detach())


def test_free_nats_cut_gradient_below_threshold_only() -> None:
    post = torch.randn(2, 3, 4, 5, requires_grad=True)
    prior = (post.detach() + 0.1 * torch.randn(2, 3, 4, 5)).requires_grad_()
    mean_kl = float(categorical_kl(post, prior).detach().mean())
    below, _ = kl_balanced_loss(post, prior, balance=0.8, free_nats=mean_kl + 1.0)
    assert float(below.detach()) == pytest.approx(mean_kl + 1.0)
    grads = torch.autograd.grad(below, (post, prior), allow_unused=True, materialize_grads=True)
    assert all(float(g.abs().sum()) == 0.0 for g in grads)
    above, _ = kl_balanced_loss(post, prior, balance=0.8, free_nats=mean_kl / 2)
    grads = torch.autograd.grad(above, (post, prior))
    assert all(float(g.abs().sum()) > 0.0 for g in grads)


def test_image_reward_discount_terms() -> None:
    pred, target = torch.randn(2, 3, 3, 64, 64), torch.rand(2, 3, 3, 64, 64) - 0.5
    expected = 0.5 * ((pred - target) ** 2).sum(dim=(2, 3, 4))
    torch.testing.assert_close(image_loss(pred, target), expected)
    torch.testing.assert_close(image_loss(UnitGaussian(pred, 3), target), expected)
    # The gradient of the summed squared error, to the prediction and to a target that needs one.
    pred32 = pred.clone().requires_grad_()
    target32 = target.clone().requires_grad_()
    weight = torch.randn(2, 3)
    got = torch.autograd.grad((image_loss(pred32, target32) * weight).sum(), (pred32, target32))
    want = torch.autograd.grad((0.5 * ((pred32 - target32) ** 2).sum((2, 3, 4)) * weight).sum(), (pred32, target32))
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a, b)
    mean, reward = torch.randn(2, 3), torch.randn(2, 3)
    torch.testing.assert_close(reward_loss(mean, reward), 0.5 * (mean - reward) ** 2)
    torch.testing.assert_close(reward_loss(UnitGaussian(mean), reward), 0.5 * (mean - reward) ** 2)
    with pytest.raises(ValueError, match="shape"):
        reward_loss(mean, reward[:, :2])
    logits, cont = torch.randn(2, 3), torch.tensor([[1.0, 1.0, 0.0], [1.0, 0.0, 1.0]])
    bce = F.binary_cross_entropy_with_logits(logits, cont, reduction="none")
    torch.testing.assert_close(discount_loss(logits, cont), bce)
    torch.testing.assert_close(discount_loss(Bernoulli(logits), cont), bce)


def test_critic_loss_stops_gradient_of_target() -> None:
    value = torch.randn(4, 2, requires_grad=True)
    target = torch.randn(4, 2, requires_grad=True)
    weight = torch.rand(4, 2)
    loss = critic_loss(value, target, weight)
    torch.testing.assert_close(loss, weight * 0.5 * (value - target) ** 2)
    loss.sum().backward()
    assert target.grad is None
    torch.testing.assert_close(value.grad, weight * (value - target).detach())


def test_actor_loss_dynamics_and_reinforce() -> None:
    target = torch.randn(3, 2, requires_grad=True)
    weight, entropy = torch.rand(3, 2), torch.rand(3, 2)
    dyn = actor_loss(target=target, weight=weight, entropy=entropy, entropy_scale=0.1)
    torch.testing.assert_close(dyn, -weight * (target + 0.1 * entropy))
    log_prob = torch.randn(3, 2, requires_grad=True)
    baseline = torch.randn(3, 2)
    rf = actor_loss(
        target=target, weight=weight, entropy=entropy, entropy_scale=0.1, log_prob=log_prob, baseline=baseline
    )
    rf.sum().backward()
    assert target.grad is None  # the advantage carries no gradient
    torch.testing.assert_close(log_prob.grad, -weight * (target - baseline).detach())
