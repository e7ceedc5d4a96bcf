"""Losses of the model-free baselines, CURL and CURL+CQL, as pure functions.

CURL (Laskin, Srinivas & Abbeel, 2020) is SAC on pixels whose conv encoder also minimises a contrastive
(InfoNCE) loss between two random crops of the same observation. CURL+CQL adds the CQL(H) penalty (Kumar et
al., 2020) to each Q-function, which is what the CoWorld paper compares against in Tables 1-2.

Every function here returns one value per batch element (``(B,)``) except :func:`info_nce`, whose
cross-entropy over a ``(B, B)`` similarity matrix is a batch-level quantity. The caller reduces the terms and
applies the scales (``cql_weight``), so each function can be held side by side with its equation:

* :func:`info_nce`: CURL's contrastive loss with a bilinear similarity ``q^T W k``.
* :func:`sac_critic_target`: the soft Bellman target of SAC's twin critics.
* :func:`twin_q_loss`: the squared TD errors of both critics.
* :func:`actor_loss`: SAC's reparameterised policy loss.
* :func:`temperature_loss`: SAC's automatic entropy tuning.
* :func:`cql_penalty`: CQL(H)'s importance-sampled ``log-sum-exp Q - Q(s, a_data)``.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "actor_loss",
    "cql_penalty",
    "info_nce",
    "sac_critic_target",
    "temperature_loss",
    "twin_q_loss",
    "uniform_log_prob",
]


def _check_shape(name: str, tensor: Tensor, shape: tuple[int, ...], dims: str) -> None:
    """Raise ``ValueError`` unless ``tensor`` has exactly ``shape`` (silent broadcasting hides bugs here)."""
    if tuple(tensor.shape) != shape:
        raise ValueError(f"{name} must have shape {dims} = {shape}, got {tuple(tensor.shape)}")


def info_nce(queries: Tensor, keys: Tensor, W: Tensor) -> tuple[Tensor, Tensor]:
    """CURL's contrastive loss: each query must pick its own key among the batch's keys.

    CURL, Sec. 4 (bilinear InfoNCE with momentum keys)::

        logits[i, j] = q_i^T W k_j  -  max_j' q_i^T W k_j'
        L = - 1/B sum_i log( exp(logits[i, i]) / sum_j exp(logits[i, j]) )

    The positive for query ``i`` is key ``i`` (another random crop of the same observation); the other ``B - 1``
    keys are the negatives. Keys come from the momentum (key) encoder and carry no gradient: they are detached
    here. Subtracting each row's maximum changes no probability; it keeps ``exp`` in range.

    Args:
        queries: ``(B, F)`` anchors from the online encoder.
        keys: ``(B, F)`` positives from the momentum encoder, row ``i`` the positive of query ``i``.
        W: ``(F, F)`` learned bilinear similarity.

    Returns:
        ``(loss, logits)``: the mean cross-entropy (a scalar) and the ``(B, B)`` row-shifted logits.
    """
    B, F_ = queries.shape
    _check_shape("keys", keys, (B, F_), "(B, F)")
    _check_shape("W", W, (F_, F_), "(F, F)")
    logits = queries @ W @ keys.detach().T
    logits = logits - logits.max(dim=1, keepdim=True).values
    labels = torch.arange(B, device=logits.device)
    return F.cross_entropy(logits, labels), logits


def sac_critic_target(
    reward: Tensor,
    not_done: Tensor,
    next_q1: Tensor,
    next_q2: Tensor,
    next_log_prob: Tensor,
    alpha: Tensor | float,
    discount: float,
) -> Tensor:
    """SAC's soft Bellman target for both critics, without gradient.

    ::

        y = r + gamma * (1 - done) * ( min(Q1'(s', a'), Q2'(s', a')) - alpha * log pi(a' | s') ),   a' ~ pi(s')

    ``Q'`` are the target critics. ``done`` marks true terminations only: a time-limit cut still bootstraps.

    Args:
        reward: ``(B,)`` reward of the transition.
        not_done: ``(B,)`` 0 where the episode terminated at ``s'``, else 1.
        next_q1: ``(B,)`` first target critic at ``(s', a')``.
        next_q2: ``(B,)`` second target critic at ``(s', a')``.
        next_log_prob: ``(B,)`` ``log pi(a' | s')`` of the sampled next action.
        alpha: SAC temperature (detached).
        discount: ``gamma``.

    Returns:
        ``(B,)`` targets, detached.
    """
    (B,) = reward.shape
    for name, value in (("not_done", not_done), ("next_q1", next_q1), ("next_q2", next_q2)):
        _check_shape(name, value, (B,), "(B,)")
    _check_shape("next_log_prob", next_log_prob, (B,), "(B,)")
    alpha = alpha.detach() if isinstance(alpha, Tensor) else alpha
    soft_value = torch.minimum(next_q1, next_q2) - alpha * next_log_prob
    return (reward + discount * not_done * soft_value).detach()


def twin_q_loss(q1: Tensor, q2: Tensor, target: Tensor) -> Tensor:
    """Squared TD errors of SAC's two critics, summed: ``(Q1(s, a) - y)^2 + (Q2(s, a) - y)^2``.

    Args:
        q1: ``(B,)`` first critic at the data's ``(s, a)``.
        q2: ``(B,)`` second critic.
        target: ``(B,)`` :func:`sac_critic_target` (detached).

    Returns:
        ``(B,)`` loss per transition (CURL takes the mean of each term: the batch mean of this).
    """
    (B,) = target.shape
    _check_shape("q1", q1, (B,), "(B,)")
    _check_shape("q2", q2, (B,), "(B,)")
    target = target.detach()
    return (q1 - target) ** 2 + (q2 - target) ** 2


def actor_loss(q1: Tensor, q2: Tensor, log_prob: Tensor, alpha: Tensor | float) -> Tensor:
    """SAC's policy loss with a reparameterised action ``a ~ pi(s)``: ``alpha * log pi(a | s) - min(Q1, Q2)(s, a)``.

    Gradient reaches the actor through ``a`` (inside ``q1``, ``q2``) and ``log_prob``; the temperature is a
    constant here.

    Args:
        q1: ``(B,)`` first critic at ``(s, a)``.
        q2: ``(B,)`` second critic at ``(s, a)``.
        log_prob: ``(B,)`` ``log pi(a | s)``.
        alpha: SAC temperature (detached).

    Returns:
        ``(B,)`` loss per state.
    """
    (B,) = log_prob.shape
    _check_shape("q1", q1, (B,), "(B,)")
    _check_shape("q2", q2, (B,), "(B,)")
    alpha = alpha.detach() if isinstance(alpha, Tensor) else alpha
    return alpha * log_prob - torch.minimum(q1, q2)


def temperature_loss(log_alpha: Tensor, log_prob: Tensor, target_entropy: float) -> Tensor:
    """SAC's automatic temperature: ``alpha * (-log pi(a | s) - H_target)``, gradient to ``log_alpha`` only.

    When the policy's entropy ``-log pi`` is above the target, the loss falls as ``alpha`` falls, and the other
    way round. CURL parameterises ``alpha = exp(log_alpha)`` and uses ``H_target = -|A|``.

    Args:
        log_alpha: scalar tensor, the learned log temperature.
        log_prob: ``(B,)`` ``log pi(a | s)`` of policy samples (detached here).
        target_entropy: ``H_target``.

    Returns:
        ``(B,)`` loss per state.
    """
    if log_alpha.ndim != 0:
        raise ValueError(f"log_alpha must be a scalar tensor, got shape {tuple(log_alpha.shape)}")
    return log_alpha.exp() * (-log_prob.detach() - target_entropy)


def uniform_log_prob(action_size: int, low: float = -1.0, high: float = 1.0) -> float:
    """Log density of the uniform distribution on the box ``[low, high]^A``: ``-A * log(high - low)``."""
    return -action_size * math.log(high - low)


def cql_penalty(
    q_random: Tensor,
    log_prob_random: Tensor | float,
    q_policy: Tensor,
    log_prob_policy: Tensor,
    q_data: Tensor,
) -> Tensor:
    """CQL(H)'s conservative penalty for one Q-function, with importance-sampled log-sum-exp.

    CQL, Eq. 4 (the H variant), per state::

        log integral exp Q(s, a) da  -  Q(s, a_data)

    The integral over the action box is estimated by importance sampling from a mixture of proposals:
    ``N`` uniform actions (density ``mu_u``) and ``M`` policy actions (sampled at ``s`` and at ``s'``, density
    ``pi(a | .)``), as in the authors' code::

        log integral exp Q da  ~=  log( 1/(N+M) * sum_i exp(Q(s, a_i) - log mu_i(a_i)) )
                               =   logsumexp_i( Q(s, a_i) - log mu_i(a_i) )  -  log(N + M)

    The ``- log(N + M)`` makes the estimate consistent (a constant Q = c gives ``c + A log 2`` on
    ``[-1, 1]^A``); the authors' code omits it, which shifts the penalty by a constant and changes no gradient.
    Minimising the penalty pushes Q down on actions the data does not support and up on the data's actions.
    Log-densities are constants of the proposals: they are detached.

    Args:
        q_random: ``(B, N)`` Q at ``N`` uniform random actions per state.
        log_prob_random: log density of the random actions: a float, or ``(B, N)``
            (:func:`uniform_log_prob` for the box).
        q_policy: ``(B, M)`` Q at ``M`` policy actions per state (state ``s`` is used for Q whichever state
            the action was sampled at).
        log_prob_policy: ``(B, M)`` log density of those actions under the policy that sampled them.
        q_data: ``(B,)`` Q at the dataset's action.

    Returns:
        ``(B,)`` penalty per state, unscaled (the caller multiplies by ``cql_weight``).
    """
    B, N = q_random.shape
    M = q_policy.shape[1]
    _check_shape("q_policy", q_policy, (B, M), "(B, M)")
    _check_shape("log_prob_policy", log_prob_policy, (B, M), "(B, M)")
    _check_shape("q_data", q_data, (B,), "(B,)")
    if isinstance(log_prob_random, Tensor):
        _check_shape("log_prob_random", log_prob_random, (B, N), "(B, N)")
        log_prob_random = log_prob_random.detach()
    weighted = torch.cat([q_random - log_prob_random, q_policy - log_prob_policy.detach()], dim=1)
    return torch.logsumexp(weighted, dim=1) - math.log(N + M) - q_data
