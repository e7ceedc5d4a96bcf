"""Losses of DrQ+BC (V-D4RL's model-free baseline) as pure functions.

DrQ+BC is DrQ-v2 (Yarats et al., 2021: DDPG from augmented pixels with twin critics and a scheduled exploration
std) whose actor also regresses the dataset's actions, weighted as TD3+BC does (Fujimoto & Gu, 2021, Eq. 5).
V-D4RL (Lu et al., 2022) runs it offline; its ``drqbc/drqv2.py`` is the reference for every term here:

* critic: ``y = r + gamma * (1 - done) * min(Q1', Q2')(s', a')`` with ``a' = clip_noise(pi(s'))``, the squared
  errors of both critics (:func:`coworld.losses.curl.sac_critic_target` with no entropy term and
  :func:`coworld.losses.curl.twin_q_loss` compute exactly these);
* actor: :func:`actor_terms`, ``- lambda * min(Q1, Q2)(s, a_pi) + ||a_pi - a_data||^2 / A`` with
  ``lambda = alpha / mean_batch |Q|`` (detached);
* :func:`exploration_std`: the linear std schedule; :func:`clipped_noise_action`: DrQ-v2's clipped-noise sample.

Functions return one value per batch element ``(B,)``; the caller takes the means.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["actor_terms", "clipped_noise_action", "exploration_std"]


def exploration_std(update: int, *, init: float, final: float, duration: int) -> float:
    """DrQ-v2's ``linear(init, final, duration)`` schedule: ``init`` at update 0, ``final`` from ``duration`` on."""
    mix = min(max(update / duration, 0.0), 1.0)
    return (1.0 - mix) * init + mix * final


def clipped_noise_action(mean: Tensor, std: float, clip: float, noise: Tensor | None = None) -> Tensor:
    """``a = clamp(mean + clip(std * eps, -clip, clip), -1 + 1e-6, 1 - 1e-6)``, ``eps ~ N(0, 1)``.

    DrQ-v2's ``TruncatedNormal.sample(clip)``: the clamp to the action box passes the gradient straight through
    (the sample's gradient with respect to ``mean`` is 1 everywhere). ``mean (B, A)`` in ``[-1, 1]``; ``noise``
    (``(B, A)`` standard normal) is drawn when None. Returns ``(B, A)``.
    """
    if noise is None:
        noise = torch.randn_like(mean)
    if noise.shape != mean.shape:
        raise ValueError(f"noise must have the shape of mean {tuple(mean.shape)}, got {tuple(noise.shape)}")
    x = mean + (std * noise).clamp(-clip, clip)
    eps = 1e-6
    return x + (x.clamp(-1.0 + eps, 1.0 - eps) - x).detach()


def actor_terms(q: Tensor, action: Tensor, data_action: Tensor, bc_weight: float) -> dict[str, Tensor]:
    """TD3+BC's actor objective on a batch, as two named terms (their sum is the loss to minimise)::

        lambda = alpha / mean_i |Q(s_i, pi(s_i))|          (detached)
        L_i = - lambda * Q(s_i, pi(s_i))  +  mean_a (pi(s_i)_a - a_data_{i,a})^2

    ``mean_i |Q|`` is a batch statistic (Eq. 5 of Fujimoto & Gu, 2021), so ``rl`` is not a per-element quantity:
    the whole batch sets its scale. The squared error is averaged over action dimensions as V-D4RL's
    ``F.mse_loss(action, behavioural_action)``, whose batch mean is the mean of ``bc``.

    Args:
        q: ``(B,)`` ``min(Q1, Q2)`` at the actor's (noisy) action, with gradient to the actor.
        action: ``(B, A)`` the actor's action.
        data_action: ``(B, A)`` the dataset's action.
        bc_weight: alpha.

    Returns:
        ``{"rl": (B,), "bc": (B,), "lambda": ()}`` (``lambda`` for logging).
    """
    (B,) = q.shape
    if action.shape != data_action.shape or action.shape[0] != B:
        raise ValueError(
            f"action {tuple(action.shape)} and data_action {tuple(data_action.shape)} must both be (B, A), B = {B}"
        )
    lam = bc_weight / q.detach().abs().mean().clamp_min(1e-8)
    bc = (action - data_action.detach()).pow(2).mean(dim=-1)
    return {"rl": -lam * q, "bc": bc, "lambda": lam}
