"""CoWorld's domain-collaborative losses (paper Eqs. 3-6) as pure functions.

Each function computes one equation of the paper, unreduced: it returns one value per batch element and time
step (``(B, T)`` for world-model sequences, ``(H, N)`` for imagined trajectories of horizon ``H`` started from
``N`` states). The caller reduces and applies the scales (``beta2``, ``alpha``), so the stop-gradients and the
per-element arithmetic here can be held side by side with the paper:

* Eq. 3, representation alignment: :func:`alignment_loss` (categorical posteriors, the paper's reading) and
  :func:`embedding_alignment_loss` (conv embeddings, the authors' public release), reduced by
  :func:`alignment_term`.
* Eqs. 4-5, target-modulated source reward: :func:`relabel_reward`, :func:`source_reward_loss_on_target` and
  :func:`reward_mix_eta`.
* Eq. 6, max-min value regularisation: :func:`value_regulariser`, :func:`max_min_active`, :func:`shifted_return`,
  and the critic objective the target agent trains with, :func:`regularised_critic_loss`.
* Several candidate sources (the later paper's multi-source CoWorld): :func:`domain_distance` (Eq. 3's KL as a
  distance) and :func:`closest_source` (the choice).

"The release" below means the authors' public code (qiwang067/CoWorld, a fork of jsikyoon/dreamer-torch);
every place it differs from the paper text is stated next to the option that reproduces it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
import torch.nn.functional as F
from torch import Tensor

from coworld.distributions import TwoHotSymlog, UnitGaussian
from coworld.losses.dreamer import critic_loss, reward_loss

__all__ = [
    "alignment_loss",
    "alignment_term",
    "closest_source",
    "domain_distance",
    "embedding_alignment_loss",
    "max_min_active",
    "regularised_critic_loss",
    "relabel_reward",
    "reward_mix_eta",
    "shifted_return",
    "source_reward_loss_on_target",
    "value_regulariser",
]


RELABEL_FORMS = ("table3", "later")
"""The two ways the versions of the method write Eq. 4 (:func:`relabel_reward`)."""
CAP_FORMS = ("shift", "on_mean")
"""How Eq. 6's max-min term acts on the target critic (:func:`regularised_critic_loss`)."""


def _check_same_shape(**tensors: Tensor) -> None:
    """Raise ``ValueError`` unless all tensors have one shape (silent broadcasting hides bugs here)."""
    shapes = {name: tuple(t.shape) for name, t in tensors.items()}
    if len(set(shapes.values())) > 1:
        listed = ", ".join(f"{name}={shape}" for name, shape in shapes.items())
        raise ValueError(f"expected tensors of one shape, got {listed}")


def _check_ndim(name: str, tensor: Tensor, ndim: int, dims: str) -> None:
    """Raise ``ValueError`` unless ``tensor`` has ``ndim`` dimensions, named ``dims`` in the message."""
    if tensor.ndim != ndim:
        raise ValueError(f"{name} must have shape {dims}, got {tuple(tensor.shape)}")


# --------------------------------------------------------------------------------------------------------------
# Eq. 3: representation alignment
# --------------------------------------------------------------------------------------------------------------


def alignment_loss(source_logits: Tensor, target_logits: Tensor) -> Tensor:
    """Domain KL of Eq. 3 between the source and target posteriors on the same target frames.

    Paper, Eq. 3 (the last term of the target world-model loss)::

        L_wm = E[ sum_t  ... + beta2 * KL[ sg(e^(S)_phi'(o_t)) || e^(T)_phi(o_t) ] ]

    The same target-dataset sequences go through the source world model (frozen here: ``sg``) and the target
    world model. The paper writes the encoders ``e(o_t)`` but speaks of "the latent state distributions" they
    produce; DreamerV2's conv encoder is deterministic, so here the distributions are the posteriors
    ``q(z_t | h_t, o_t)``. With discrete latents each posterior is ``S`` independent categoricals over ``K``
    classes, so the KL is the sum over the ``S`` variables of::

        KL(p_S || p_T) = sum_k p_S[k] * (log p_S[k] - log p_T[k]),   p = softmax(logits)

    The source side is detached, so only the target model receives gradient; the gradient of the KL with
    respect to ``target_logits`` is ``softmax(target_logits) - softmax(source_logits)``.

    Release difference: the release aligns the conv-encoder embeddings, not the posteriors; see
    :func:`embedding_alignment_loss`, which reproduces it.

    Args:
        source_logits: ``(B, T, S, K)`` posterior logits of the source world model on target frames.
        target_logits: ``(B, T, S, K)`` posterior logits of the target world model on the same frames.

    Returns:
        ``(B, T)`` KL per step, unscaled (the caller multiplies by ``beta2``).
    """
    _check_ndim("source_logits", source_logits, 4, "(B, T, S, K)")
    _check_same_shape(source_logits=source_logits, target_logits=target_logits)
    log_p = F.log_softmax(source_logits.detach(), dim=-1)
    log_q = F.log_softmax(target_logits, dim=-1)
    kl_per_variable = (log_p.exp() * (log_p - log_q)).sum(dim=-1)  # (B, T, S)
    return kl_per_variable.sum(dim=-1)


def embedding_alignment_loss(source_embed: Tensor, target_embed: Tensor) -> Tensor:
    """The release's reading of Eq. 3: KL between softmax-normalised encoder embeddings.

    Paper, Eq. 3: ``beta2 * KL[ sg(e^(S)(o_t)) || e^(T)(o_t) ]``. The release applies it to the conv encoder's
    output ``e(o_t)`` itself (1024-d there), treating ``softmax`` over the embedding dimension as a distribution::

        KL( softmax(sg(e_S)) || softmax(e_T) ) = sum_e p_S[e] * (log p_S[e] - log p_T[e])

    which is what ``torch.nn.KLDivLoss()(log_softmax(e_T), softmax(sg(e_S)))`` computes per row.

    Reduction, to reproduce the release: it uses ``KLDivLoss(reduction="batchmean")`` on ``(B, T, E)`` tensors,
    which divides the total by ``B`` only, i.e. ``loss.sum(dim=1).mean()`` of this function's output (a sum
    over time, ``T`` times larger than ``loss.mean()``), then multiplies by ``beta2``.

    Args:
        source_embed: ``(B, T, E)`` source-encoder embeddings of target frames.
        target_embed: ``(B, T, E)`` target-encoder embeddings of the same frames.

    Returns:
        ``(B, T)`` KL per step, unscaled; gradient reaches ``target_embed`` only.
    """
    _check_ndim("source_embed", source_embed, 3, "(B, T, E)")
    _check_same_shape(source_embed=source_embed, target_embed=target_embed)
    log_p = F.log_softmax(source_embed.detach(), dim=-1)
    log_q = F.log_softmax(target_embed, dim=-1)
    return (log_p.exp() * (log_p - log_q)).sum(dim=-1)


def alignment_term(source: Tensor, target: Tensor, align_on: str = "latent") -> Tensor:
    """Eq. 3's alignment term as the target world-model loss adds it, before ``beta2``: a 0-d tensor.

    * ``'latent'``: ``source``/``target`` are posterior logits ``(B, T, S, K)``; :func:`alignment_loss` averaged
      over ``B`` and ``T``, like every other DreamerV2 world-model term;
    * ``'embedding'``: ``(B, T, E)`` encoder embeddings; :func:`embedding_alignment_loss` summed over ``T`` and
      averaged over ``B``, as the release's ``KLDivLoss(reduction="batchmean")`` on ``(B, T, E)`` does.

    Gradient reaches ``target`` only.
    """
    if align_on == "latent":
        return alignment_loss(source, target).mean()
    if align_on == "embedding":
        return embedding_alignment_loss(source, target).sum(dim=1).mean()
    raise ValueError(f"align_on must be 'latent' or 'embedding', got {align_on!r}")


def domain_distance(source: Tensor, target: Tensor, align_on: str = "latent") -> Tensor:
    """How far a source world model's latents on target frames lie from the target model's: Eq. 3's term
    (:func:`alignment_term`) without ``beta2`` and without gradient.

    The later paper's multi-source CoWorld picks the source whose latents on the target data lie closest to the
    target's, by a KL between the world models' latents; the authors' release computes it as its Eq. 3 term
    (``_latent_distance``: ``KLDivLoss(batchmean)(log_softmax(e_T), softmax(e_S))``, i.e. ``KL[e_S || e_T]``,
    source first as in Eq. 3). Here it follows ``coworld.align_on``.

    Returns:
        a 0-d tensor, ``>= 0``; 0 where the two models put the frames at the same latent distribution.
    """
    with torch.no_grad():
        return alignment_term(source, target, align_on)


def closest_source(distances: Mapping[str, float]) -> str:
    """The candidate source with the smallest :func:`domain_distance` to the target; a tie goes to the candidate
    listed first (``distances`` keeps the order the sources were given in). A distance that is not a number (a
    diverged model) counts as infinitely far; raises ``ValueError`` when no candidate has a finite one."""
    finite = {name: d for name, d in distances.items() if math.isfinite(d)}
    if not finite:
        raise ValueError(f"no candidate source has a finite distance to the target: {dict(distances)}")
    return min(finite, key=lambda name: finite[name])  # min keeps the first of equal values


# --------------------------------------------------------------------------------------------------------------
# Eqs. 4-5: target-modulated source reward
# --------------------------------------------------------------------------------------------------------------


def relabel_reward(source_pred: Tensor, target_reward: Tensor, k: float, form: str = "table3") -> Tensor:
    """Target-modulated source reward of Eq. 4, for target-dataset sequences.

    Paper text, Eq. 4 (the target-batch case), ``form='table3'``::

        r^(S)_t = k * r^(S)_phi'(h^(T)_t, z^(T)_t) + (1 - k) * r^(T)_t

    where ``h^(T), z^(T)`` are the source world model's states on the target sequence (Table 3: ``k = 0.2``). The
    later paper (v4) and the release write it the other way round, ``form='later'``::

        r^(S)_t = (1 - k) * r^(S)_phi'(h^(T)_t, z^(T)_t) + k * r^(T)_t

    (the later paper's Table 8: ``k = 0.9`` for DMC, 0.3 for Meta-World; the release's ``reward_k``: 0.3). The
    prediction is a label, not a path for gradient, so ``source_pred`` is detached; so is the result unless the
    caller passes a ``target_reward`` that requires grad (dataset rewards never do).

    Args:
        source_pred: ``(B, T)`` reward the source reward head predicts on the target sequence (its mean/mode).
        target_reward: ``(B, T)`` rewards stored in the target dataset.
        k: the mixing weight, in ``[0, 1]``.
        form: 'table3' or 'later', as above.

    Returns:
        ``(B, T)`` relabelled rewards, the regression target of :func:`source_reward_loss_on_target`.
    """
    if not 0.0 <= k <= 1.0:
        raise ValueError(f"k must be in [0, 1], got {k}")
    if form not in RELABEL_FORMS:
        raise ValueError(f"form must be one of {', '.join(RELABEL_FORMS)}, got {form!r}")
    _check_same_shape(source_pred=source_pred, target_reward=target_reward)
    on_pred = k if form == "table3" else 1.0 - k
    return on_pred * source_pred.detach() + (1.0 - on_pred) * target_reward


def reward_mix_eta(done: int, total: int, start: float, end: float) -> float:
    """Eq. 5's ``eta`` after ``done`` of the run's ``total`` source updates (``coworld.reward_mix='eta'``)::

        L_r = eta * L_r(B^(S)) + (1 - eta) * L_r(B^(T)),    eta = start + (end - start) * min(1, done / total)

    The later paper lets ``eta`` fall from 1 to 0.1 (how fast it does not say: here linearly over the run); the
    release computes ``max(1 - step / 2e5, 0.2)`` from a step it never advances, so ``start = end`` there.
    """
    if total <= 0:
        return end
    return start + (end - start) * min(1.0, max(0, done) / total)


def source_reward_loss_on_target(pred: UnitGaussian | TwoHotSymlog | Tensor, relabelled: Tensor) -> Tensor:
    """Target-batch term of Eq. 5: the source reward head's negative log-likelihood of the relabelled reward.

    Paper, Eq. 5::

        L_r = E_{B^(S)}[ sum_t -ln r^(S)_phi'(h^(S)_t, z^(S)_t) ] + E_{B^(T)}[ sum_t -ln r^(S)_phi'(h^(T)_t, z^(T)_t) ]

    This is the second expectation, with the relabelled reward of Eq. 4 as the observed value. For a reward
    head that is a unit-variance Gaussian (DreamerV2's, and the release's), ``-ln N(r; mean, 1) =
    0.5 * (mean - r)^2 + 0.5 * ln(2 pi)``; the constant is dropped, so the term has the same form as the ordinary
    reward term on source batches (the first expectation) and an MSE reward head gives the same gradient.

    Note: when ``relabelled`` was built from the same head's prediction at the same states (as Eq. 4 does),
    the loss equals ``0.5 * (1 - k)^2 * (pred - r_T)^2``: ``k`` damps how fast the source head moves toward the
    target reward rather than fixing a blended target.

    The paper text sums the two expectations with weight 1 each; the later paper and the release weigh them by
    ``eta`` (:func:`reward_mix_eta`). The weighting is the caller's.

    It is the world model's own :func:`~coworld.losses.dreamer.reward_loss` with the label held constant, so a
    :class:`TwoHotSymlog` head (``world_model.reward_dist='twohot'``) gets its cross-entropy against the relabelled
    reward's two-hot encoding.

    Args:
        pred: ``(B, T)`` the source reward head's distribution on the target sequence, or its mean (with gradient).
        relabelled: ``(B, T)`` output of :func:`relabel_reward`; treated as a constant label.

    Returns:
        ``(B, T)`` negative log-likelihood up to its constant.
    """
    return reward_loss(pred, relabelled.detach())


# --------------------------------------------------------------------------------------------------------------
# Eq. 6: max-min value regularisation
# --------------------------------------------------------------------------------------------------------------


def _check_zeta(zeta: float) -> None:
    """``zeta`` rescales values; a non-positive one would flip or cancel the regulariser."""
    if zeta <= 0.0:
        raise ValueError(f"zeta must be positive, got {zeta}")


def max_min_active(target_value: Tensor, source_value: Tensor, zeta: float) -> Tensor:
    """Where the max-min term of Eq. 6 has gradient: ``zeta * v_T(z) > v_S(z)``.

    Log ``active.float().mean()`` to see how often the source critic caps the target critic. At a tie the term
    is taken as inactive, matching :func:`value_regulariser`.

    Args:
        target_value: ``(H, N)`` target critic values on imagined target states.
        source_value: ``(H, N)`` source critic values on the same states.
        zeta: scale of the target values, positive.

    Returns:
        ``(H, N)`` bool mask, no gradient.
    """
    _check_zeta(zeta)
    _check_same_shape(target_value=target_value, source_value=source_value)
    return zeta * target_value.detach() > source_value.detach()


def value_regulariser(target_value: Tensor, source_value: Tensor, zeta: float) -> Tensor:
    """Max-min term of Eq. 6: ``max(zeta * v_T(z), sg(v_S(z)))``.

    Paper, Eq. 6 (second term, before ``alpha``)::

        max( zeta * v^(T)_xi(z_t), sg(v^(S)_xi'(z_t)) )

    Where the source critic is higher the term is the constant ``sg(v_S)`` and gives the target critic no
    gradient; where ``zeta * v_T`` is higher its gradient with respect to ``v_T`` is ``zeta``, so minimising it
    pushes the target value down toward the source value. The paper's prose states the condition as
    ``v_T >= v_S``; this follows the equation (``zeta * v_T``). At an exact tie the term counts as inactive
    (gradient 0), where ``torch.maximum`` would split the gradient in halves.

    Release difference: the release has no ``zeta`` (``zeta = 1`` reproduces it) and feeds the source critic
    the target world model's imagined features directly.

    Args:
        target_value: ``(H, N)`` target critic values ``v_T(z)`` (with gradient).
        source_value: ``(H, N)`` source critic values ``v_S(z)`` on the same states; detached here.
        zeta: scale of the target values, positive (Table 3 gives none; 1 matches the release).

    Returns:
        ``(H, N)`` term, unscaled (the caller multiplies by ``alpha``).
    """
    _check_zeta(zeta)
    _check_same_shape(target_value=target_value, source_value=source_value)
    scaled = zeta * target_value
    capped = source_value.detach()
    return torch.where(scaled > capped, scaled, capped)


def shifted_return(target: Tensor, target_value: Tensor, source_value: Tensor, alpha: float, zeta: float) -> Tensor:
    """The lambda-return lowered by ``alpha * zeta`` where Eq. 6's max-min term binds: ``V_t - alpha * zeta * active``.

    On a unit-variance Gaussian critic ``0.5 * (v - V)^2 + alpha * zeta * v = 0.5 * (v - (V - alpha * zeta))^2 +
    const``: wherever the term binds, Eq. 6 is exactly a regression onto this target. A critic of any other
    distribution fitted to it gets the same push in value units and the same fixed point, ``alpha * zeta`` below
    its lambda-return, which the term itself on its mean does not give (:func:`regularised_critic_loss`).

    Args:
        target: ``(H, N)`` lambda-returns ``V_lambda``; detached here.
        target_value: ``(H, N)`` the target critic's mean ``v_T(z)``, which decides where the term binds.
        source_value: ``(H, N)`` source critic values ``v_S(z)``.
        alpha: scale of the max-min term, non-negative.
        zeta: scale of the target values inside the max, positive.

    Returns:
        ``(H, N)`` regression target, no gradient.
    """
    active = max_min_active(target_value, source_value, zeta)
    return target.detach() - (alpha * zeta) * active.to(target.dtype)


def regularised_critic_loss(
    value: UnitGaussian | TwoHotSymlog | Tensor,
    target: Tensor,
    weight: Tensor,
    source_value: Tensor,
    alpha: float,
    zeta: float,
    form: str = "shift",
) -> Tensor:
    """Target critic objective of Eq. 6, as the target agent's critic step computes it.

    Paper, Eq. 6::

        L(xi) = E[ sum_{t=1}^{H-1}  0.5 * (v^(T)_xi(z_t) - sg(V^(T)_t))^2
                                  + alpha * max( zeta * v^(T)_xi(z_t), sg(v^(S)_xi'(z_t)) ) ]

    The first term is DreamerV2's critic regression onto the lambda-returns ``V_t``
    (:func:`~coworld.losses.dreamer.critic_loss`: a unit-variance Gaussian's negative log-likelihood up to its
    constant, or a two-hot critic's cross-entropy). The second, on a binding state (``zeta * v_T > v_S``), has
    gradient ``alpha * zeta`` in ``v_T`` and moves the state's fixed point ``alpha * zeta`` below its lambda-return:
    a soft push, the same whatever the state's value. ``form`` says how a critic gets it:

    * ``'shift'`` (the default): the paper's loss as written on a Gaussian critic (or a plain mean); on a two-hot
      critic the cross-entropy against :func:`shifted_return`, the lambda-return lowered by ``alpha * zeta`` where
      the term binds, which has the same push and fixed point.
    * ``'on_mean'``: the paper's loss on every critic, the max-min term read on the critic's mean (the same as
      ``'shift'`` on a Gaussian). On a two-hot critic it is not the paper's term: the mean ``symexp(sum_k p_k b_k)``
      has ``d mean / d logit_j = symexp'(m) p_j (b_j - m)``, a push that grows with ``|v| + 1`` and is cheapest on the
      outer bins, so the loss has no minimum above the cap and clamps ``v_T <= v_S / zeta`` instead
      (docs/algorithms.md, "Eq. 6 on a two-hot critic"). Kept to compare with.

    Both terms are multiplied by ``weight``, DreamerV2's cumulative imagination discount (detached), as in DreamerV2
    and the release. Pass the ``H`` steps that Eq. 6 sums over (DreamerV2 fits values on all but the last imagined
    state).

    Release difference: the release uses ``zeta = 1`` and the same ``weight`` on both terms, then averages over all
    elements; Table 3 gives ``alpha = 0.2``, the release 1.5.

    Args:
        value: ``(H, N)`` the target critic's distribution over ``v_T(z)`` or its mean (with gradient).
        target: ``(H, N)`` lambda-returns ``V_lambda``; detached here.
        weight: ``(H, N)`` per-step weight; detached here.
        source_value: ``(H, N)`` source critic values ``v_S(z)`` on the same states; detached here.
        alpha: scale of the max-min term, non-negative.
        zeta: scale of the target values inside the max, positive.
        form: one of :data:`CAP_FORMS`.

    Returns:
        ``(H, N)`` per-step loss; for a Gaussian critic its gradient with respect to the mean ``v_T`` is
        ``weight * ((v_T - V_lambda) + alpha * zeta * active)``.
    """
    if alpha < 0.0:
        raise ValueError(f"alpha must be non-negative, got {alpha}")
    if form not in CAP_FORMS:
        raise ValueError(f"form must be one of {', '.join(CAP_FORMS)}, got {form!r}")
    mean = value if isinstance(value, Tensor) else value.mean
    _check_same_shape(value=mean, target=target, source_value=source_value, weight=weight)
    if form == "shift" and isinstance(value, TwoHotSymlog):
        return critic_loss(value, shifted_return(target, mean, source_value, alpha, zeta), weight)
    return critic_loss(value, target, weight) + weight.detach() * (alpha * value_regulariser(mean, source_value, zeta))
