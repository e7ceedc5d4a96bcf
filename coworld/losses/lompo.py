"""LOMPO's uncertainty penalty (Rafailov et al., 2021) as a pure function, and its latent actor-critic's terms.

LOMPO learns a latent world model whose transition is an ensemble of ``K`` heads, imagines short rollouts in
latent space, each step drawing the next latent ``z'`` from one head chosen at random, and lowers the imagined
reward by how differently the heads rate that draw (V-D4RL ``baselines/lompo/run.py``, ``penalty_type='log_prob'``)::

    u(h', z') = std_k log p_k(z' | h')          (population std over the K heads)
    r~ = r - lambda * u

The actor-critic is a deterministic actor with twin Q-functions on the latent features, trained on real latent
transitions of the dataset and on imagined ones, half of each::

    y = r~ + gamma * (1 - done) * min(Q1', Q2')(s', pi(s'))          (Q' the target Q-functions)
    L_Q = (Q1(s, a) - y)^2 + (Q2(s, a) - y)^2
    L_pi = - min(Q1, Q2)(s, pi(s))

* :func:`log_prob_spread`: ``u``;
* :func:`coworld.losses.penalty.penalised_reward`: ``r~``;
* the Q target and loss are SAC's without its entropy term (:func:`coworld.losses.curl.sac_critic_target` with
  ``alpha = 0``, :func:`coworld.losses.curl.twin_q_loss`), the actor's loss SAC's likewise
  (:func:`coworld.losses.curl.actor_loss` with ``alpha = 0``); :func:`td_target` and :func:`deterministic_actor_loss`
  name them.
"""

from __future__ import annotations

import torch
from torch import Tensor

from coworld.losses.curl import actor_loss, sac_critic_target

__all__ = ["deterministic_actor_loss", "log_prob_spread", "td_target"]


def log_prob_spread(head_logits: Tensor, stoch: Tensor) -> Tensor:
    """``std_k log p_k(z)``: how differently ``K`` heads rate the one-hot latent ``z``.

    Args:
        head_logits: ``(K, ..., S, C)`` normalised log-probabilities of each head's ``S`` categoricals.
        stoch: ``(..., S, C)`` one-hot sample ``z``.

    Returns:
        ``(...)``: the population standard deviation (``1/K``, as ``tf.math.reduce_std``) over the heads of
        ``log p_k(z) = sum_s log p_k(z_s)``.
    """
    if head_logits.shape[1:] != stoch.shape:
        raise ValueError(f"head_logits {tuple(head_logits.shape)} must be (K, *stoch {tuple(stoch.shape)})")
    log_prob = (head_logits.float() * stoch.float()).sum(dim=(-2, -1))  # (K, ...)
    return log_prob.std(dim=0, correction=0)


def td_target(reward: Tensor, not_done: Tensor, next_q1: Tensor, next_q2: Tensor, discount: float) -> Tensor:
    """``y = r + gamma * (1 - done) * min(Q1', Q2')(s', pi(s'))``, detached; every argument ``(B,)``."""
    return sac_critic_target(reward, not_done, next_q1, next_q2, torch.zeros_like(reward), 0.0, discount)


def deterministic_actor_loss(q1: Tensor, q2: Tensor) -> Tensor:
    """``- min(Q1, Q2)(s, pi(s))`` per state ``(B,)``, gradient to the actor through the action."""
    return actor_loss(q1, q2, torch.zeros_like(q1), 0.0)
