"""DreamerV2's losses as pure functions.

World-model terms are unreduced ``(B, T)`` negative log-likelihoods; behaviour terms are unreduced ``(H, N)``
over imagined trajectories of horizon ``H`` from ``N`` start states. The callers
(:meth:`coworld.models.world_model.WorldModel.loss`, :meth:`coworld.models.actor_critic.ActorCritic.losses`)
reduce them and apply the config's scales in one place.
"""

from __future__ import annotations

import torch
from torch import Tensor

from coworld.distributions import Bernoulli, TwoHotSymlog, UnitGaussian, categorical_kl

__all__ = [
    "actor_loss",
    "critic_loss",
    "discount_loss",
    "image_loss",
    "kl_balanced_loss",
    "lambda_return",
    "reward_loss",
]


def image_loss(pred: UnitGaussian | Tensor, target: Tensor) -> Tensor:
    """Image negative log-likelihood under a unit-variance Gaussian: ``0.5 * sum_{C,H,W} (pred - target)^2``
    (``-UnitGaussian.log_prob``, its constant ``0.5 log(2 pi)`` per pixel dropped).

    ``pred`` is the decoder's mean image (or its :class:`UnitGaussian` over the last three dimensions),
    ``(B, T, C, H, W)``; ``target`` the observed image as the encoder reads it, the same shape. Returns ``(B, T)``.
    """
    mean = pred.mean if isinstance(pred, UnitGaussian) else pred
    return -UnitGaussian(mean.float(), event_dims=3).log_prob(target.float())


def reward_loss(pred: UnitGaussian | TwoHotSymlog | Tensor, target: Tensor) -> Tensor:
    """Reward negative log-likelihood under a unit-variance Gaussian: ``0.5 * (pred - target)^2`` (or, for a
    :class:`TwoHotSymlog` head, its cross-entropy against the target's two-hot encoding).

    ``pred`` is the reward head's output (a :class:`UnitGaussian` or :class:`TwoHotSymlog`) or its mean, any shape
    ``(...)`` (``(B, T)`` for sequences); ``target`` the same shape. Returns ``(...)``. Works for any features and
    any targets, e.g. CoWorld's relabelled source rewards on target features (Eqs. 4-5).
    """
    return _scalar_nll(pred, target, "reward prediction")


def _scalar_nll(pred: UnitGaussian | TwoHotSymlog | Tensor, target: Tensor, name: str) -> Tensor:
    """``-log p(target)`` under a scalar head's distribution (a bare tensor is a unit Gaussian's mean), ``(...)``;
    ``ValueError`` naming ``name`` unless prediction and target have one shape."""
    if isinstance(pred, TwoHotSymlog):
        shape, dist = pred.logits.shape[:-1], pred
    else:
        mean = pred.mean if isinstance(pred, UnitGaussian) else pred
        shape, dist = mean.shape, UnitGaussian(mean.float())
    if shape != target.shape:
        raise ValueError(f"{name} {tuple(shape)} and target {tuple(target.shape)} differ in shape")
    return -dist.log_prob(target.float())


def discount_loss(pred: Bernoulli | Tensor, continuation: Tensor) -> Tensor:
    """Continuation negative log-likelihood: ``-[c log p + (1 - c) log(1 - p)]`` with ``c = 1 - is_terminal``.

    ``pred`` is the discount head's :class:`Bernoulli` or its logits ``(B, T)``; ``continuation (B, T)`` in
    ``[0, 1]``. Returns ``(B, T)``.
    """
    dist = pred if isinstance(pred, Bernoulli) else Bernoulli(pred)
    return -dist.log_prob(continuation.float())


def kl_balanced_loss(
    post_logits: Tensor, prior_logits: Tensor, balance: float, free_nats: float, normalised: bool = False
) -> tuple[Tensor, Tensor]:
    """DreamerV2's KL balancing with batch-averaged free nats.

    With ``a = balance`` (0.8), ``KL_prior = KL[sg(post) || prior]`` and ``KL_post = KL[post || sg(prior)]``::

        loss = a * max(mean(KL_prior), free) + (1 - a) * max(mean(KL_post), free)

    so ``a`` of the gradient trains the prior towards the posterior and ``1 - a`` regularises the posterior;
    when the batch-averaged KL is below ``free_nats`` neither side gets a gradient.

    Shapes: logits ``(B, T, S, K)``. Returns ``(loss, kl)``: the scalar loss and the per-step KL ``(B, T)``
    *before* free nats, whose value is ``KL[post || prior]`` and whose gradient is already split
    ``a * KL_prior + (1 - a) * KL_post``. ``normalised``: the logits are log-probabilities already (see
    :func:`~coworld.distributions.categorical_kl`).
    """
    kl_prior = categorical_kl(post_logits.detach(), prior_logits, normalised)
    kl_post = categorical_kl(post_logits, prior_logits.detach(), normalised)
    free = torch.tensor(free_nats, dtype=kl_prior.dtype, device=kl_prior.device)
    loss = balance * torch.maximum(kl_prior.mean(), free) + (1.0 - balance) * torch.maximum(kl_post.mean(), free)
    return loss, balance * kl_prior + (1.0 - balance) * kl_post


def lambda_return(reward: Tensor, value: Tensor, continuation: Tensor, bootstrap: Tensor, lambda_: float) -> Tensor:
    """TD(lambda) returns computed backwards over the horizon (DreamerV2's ``lambda_return``).

    With ``v_H = bootstrap`` and ``R_H = bootstrap``::

        R_t = r_t + c_t * ((1 - lambda) * v_{t+1} + lambda * R_{t+1}),    t = H-1, ..., 0

    where ``c_t`` is the discounted continuation (``gamma * P(not terminal)``).
    Shapes: ``reward``, ``value``, ``continuation`` ``(H, N)``; ``bootstrap`` ``(N,)``. Returns ``(H, N)``.
    """
    if not reward.shape == value.shape == continuation.shape:
        raise ValueError(
            f"reward {tuple(reward.shape)}, value {tuple(value.shape)} and continuation "
            f"{tuple(continuation.shape)} must have one shape (H, N)"
        )
    next_value = torch.cat([value[1:], bootstrap[None]], dim=0)
    inputs = reward + continuation * next_value * (1.0 - lambda_)
    returns = []
    last = bootstrap
    for t in reversed(range(reward.shape[0])):
        last = inputs[t] + continuation[t] * lambda_ * last
        returns.append(last)
    return torch.stack(returns[::-1], dim=0)


def critic_loss(value: UnitGaussian | TwoHotSymlog | Tensor, target: Tensor, weight: Tensor) -> Tensor:
    """Weighted critic regression to the lambda-returns: ``weight * 0.5 * (v - sg(R))^2`` (for a
    :class:`TwoHotSymlog` critic, ``-weight * log p(sg(R))``).

    ``value`` is the critic's mean on imagined states (with gradient) or its distribution, ``target`` the
    lambda-return, ``weight`` the cumulative discount of reaching the state; all ``(H, N)``. Returns ``(H, N)``.
    """
    return weight.detach() * _scalar_nll(value, target.detach(), "value")


def actor_loss(
    *,
    target: Tensor,
    weight: Tensor,
    entropy: Tensor,
    entropy_scale: float,
    log_prob: Tensor | None = None,
    baseline: Tensor | None = None,
) -> Tensor:
    """Weighted actor loss ``-weight * (objective + eta * entropy)``, ``(H-1, N)``.

    'dynamics' (``log_prob`` None): ``objective = R_{t+1}``, differentiated through the imagined dynamics.
    'reinforce': ``objective = log pi(a_t | s_t) * sg(R_{t+1} - baseline_t)``.
    All inputs ``(H-1, N)``: ``target`` is the lambda-return of the state each action leads to, ``weight`` the
    cumulative discount of the acting state, ``entropy`` the policy entropy there.
    """
    if log_prob is None:
        objective = target
    else:
        if baseline is None:
            raise ValueError("the 'reinforce' actor loss needs a baseline")
        objective = log_prob * (target - baseline).detach()
    return -weight.detach() * (objective + entropy_scale * entropy)
