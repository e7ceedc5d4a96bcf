"""Losses of V-D4RL's offline DreamerV2 (Lu et al., 2022) as pure functions: the ensemble-disagreement penalty.

An ensemble of ``K`` dynamics heads each predicts the categorical latent ``z_t`` from the deterministic state
``h_t``. Where the world model has seen data, the heads agree; off the data, they disagree, and the agent's
imagined reward is lowered by that disagreement (V-D4RL ``offlinedv2/dreamerv2/agent.py``, ``penalized_reward``
with ``offline_penalty_type='meandis'``)::

    p_k = softmax(head_k(h))          (S, C) class probabilities of head k
    u(h) = 1/K sum_k || p_k - 1/K sum_j p_j ||_F
    r~ = r - lambda * u(h)

* :func:`mean_disagreement`: ``u``;
* :func:`penalised_reward`: ``r~``;
* :func:`head_loss`: what trains each head: ``KL[sg(posterior) || head_k(sg(h))]`` on the time steps assigned to it.
"""

from __future__ import annotations

from torch import Tensor

from coworld.distributions import categorical_kl

__all__ = ["head_loss", "mean_disagreement", "penalised_reward"]


def mean_disagreement(logits: Tensor) -> Tensor:
    """``1/K sum_k ||p_k - p_mean||_F`` of ``K`` heads' categoricals.

    Args:
        logits: ``(K, ..., S, C)`` (log-)probabilities of each head (normalised by a softmax here).

    Returns:
        ``(...)``: the mean Frobenius distance of the heads' ``(S, C)`` probability tables to their average.
    """
    probs = logits.float().softmax(dim=-1)
    spread = probs - probs.mean(dim=0, keepdim=True)
    return spread.pow(2).sum(dim=(-2, -1)).sqrt().mean(dim=0)


def penalised_reward(reward: Tensor, disagreement: Tensor, weight: float) -> Tensor:
    """``r - weight * u``, elementwise; ``reward`` and ``disagreement`` of the same shape."""
    if reward.shape != disagreement.shape:
        raise ValueError(f"reward {tuple(reward.shape)} and disagreement {tuple(disagreement.shape)} must match")
    return reward - weight * disagreement.to(reward.dtype)


def head_loss(post_logits: Tensor, head_logits: Tensor, mask: Tensor) -> Tensor:
    """Each head's KL to the (detached) posterior, on the steps assigned to it.

    V-D4RL's ensemble heads are the prior: each world-model step draws one head at random and that head's KL term
    trains it, so each head fits a random share of the data. Here the heads sit beside the prior and learn its
    target, ``KL[sg(q(z | h, o)) || p_k(z | h)]``, only where ``mask`` assigns the step to head ``k``.

    Args:
        post_logits: ``(..., S, C)`` posterior logits.
        head_logits: ``(K, ..., S, C)`` the heads' logits.
        mask: ``(K, ...)`` 1 where the step trains head ``k`` (one head per step), else 0.

    Returns:
        ``(K, ...)``: the masked KL, in nats.
    """
    if head_logits.shape[1:] != post_logits.shape or mask.shape != head_logits.shape[:-2]:
        raise ValueError(
            f"head_logits {tuple(head_logits.shape)} must be (K, *post_logits {tuple(post_logits.shape)}) and mask"
            f" {tuple(mask.shape)} (K, ...)"
        )
    kl = categorical_kl(post_logits.detach().expand_as(head_logits), head_logits)
    return mask.to(kl.dtype) * kl
