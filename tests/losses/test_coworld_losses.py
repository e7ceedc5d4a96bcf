"""CoWorld's domain-collaborative losses (Eqs. 3-6): hand-computed values and where gradient flows."""

from __future__ import annotations

import math
import re

import pytest
import torch
import torch.nn.functional as F

from coworld.distributions import TWOHOT_BINS, TwoHotSymlog
from coworld.losses.coworld import (
    alignment_loss,
    embedding_alignment_loss,
    max_min_active,
    regularised_critic_loss,
    relabel_reward,
    source_reward_loss_on_target,
    value_regulariser,
)


def _logits(*probs: float) -> list[float]:
    """Logits of a categorical with the given probabilities (log-probabilities are valid logits)."""
    return [math.log(p) for p in probs]


# --------------------------------------------------------------------------------------------------------------
# Eq. 3
# --------------------------------------------------------------------------------------------------------------


def _two_class_latents() -> tuple[torch.Tensor, torch.Tensor]:
    """(B=1, T=2, S=2, K=2) source/target logits.

    t=0: variable 0 has p_S=(0.25, 0.75), p_T=(0.5, 0.5); variable 1 has p_S=(0.9, 0.1), p_T=(0.6, 0.4).
    t=1: both models agree. Source logits of t=0 var 0 are shifted by +2 to check the softmax normalisation.
    """
    source = torch.tensor(
        [
            [
                [[2.0 + math.log(0.25), 2.0 + math.log(0.75)], _logits(0.9, 0.1)],
                [_logits(0.3, 0.7), _logits(0.5, 0.5)],
            ]
        ]
    )
    target = torch.tensor(
        [
            [
                [_logits(0.5, 0.5), _logits(0.6, 0.4)],
                [_logits(0.3, 0.7), _logits(0.5, 0.5)],
            ]
        ]
    )
    return source, target


def test_alignment_loss_matches_hand_kl_summed_over_variables() -> None:
    source, target = _two_class_latents()
    loss = alignment_loss(source, target)
    var0 = 0.25 * math.log(0.25 / 0.5) + 0.75 * math.log(0.75 / 0.5)
    var1 = 0.9 * math.log(0.9 / 0.6) + 0.1 * math.log(0.1 / 0.4)
    assert loss.shape == (1, 2)
    torch.testing.assert_close(loss, torch.tensor([[var0 + var1, 0.0]]))


def test_alignment_loss_is_kl_source_to_target_not_reverse() -> None:
    source, target = _two_class_latents()
    reverse_var0 = 0.5 * math.log(0.5 / 0.25) + 0.5 * math.log(0.5 / 0.75)
    reverse_var1 = 0.6 * math.log(0.6 / 0.9) + 0.4 * math.log(0.4 / 0.1)
    swapped = alignment_loss(target, source)
    torch.testing.assert_close(swapped, torch.tensor([[reverse_var0 + reverse_var1, 0.0]]))


def test_alignment_loss_gradient_reaches_only_target_and_equals_q_minus_p() -> None:
    source, target = _two_class_latents()
    source.requires_grad_(True)
    target.requires_grad_(True)
    alignment_loss(source, target).sum().backward()
    assert source.grad is None
    assert target.grad is not None
    # d KL(p || softmax(l)) / d l = softmax(l) - p, per variable.
    expected = torch.tensor(
        [
            [
                [[0.5 - 0.25, 0.5 - 0.75], [0.6 - 0.9, 0.4 - 0.1]],
                [[0.0, 0.0], [0.0, 0.0]],
            ]
        ]
    )
    torch.testing.assert_close(target.grad, expected)


def test_alignment_loss_gradient_step_on_target_reduces_kl() -> None:
    source, target = _two_class_latents()
    target.requires_grad_(True)
    before = alignment_loss(source, target).sum()
    before.backward()
    assert target.grad is not None
    with torch.no_grad():
        stepped = target - 0.5 * target.grad
    after = alignment_loss(source, stepped).sum()
    assert after.item() < before.item()


def test_alignment_loss_rejects_mismatched_or_flat_shapes() -> None:
    source, target = _two_class_latents()
    with pytest.raises(ValueError, match="one shape"):
        alignment_loss(source, target[..., :1])
    with pytest.raises(ValueError, match=r"\(B, T, S, K\)"):
        alignment_loss(source[0], target[0])


def test_embedding_alignment_loss_hand_value_and_release_equivalence() -> None:
    # Row (0, 0): softmax(0, 0, ln 2) = (1/4, 1/4, 1/2) against softmax(0, 0, 0) = 1/3 each.
    # Row (0, 1): identical embeddings (up to a shift), KL 0.
    source = torch.tensor([[[0.0, 0.0, math.log(2.0)], [1.0, 2.0, 3.0]]], requires_grad=True)
    target = torch.tensor([[[0.0, 0.0, 0.0], [0.0, 1.0, 2.0]]], requires_grad=True)
    loss = embedding_alignment_loss(source, target)
    row0 = 2 * 0.25 * math.log(0.25 / (1 / 3)) + 0.5 * math.log(0.5 / (1 / 3))
    torch.testing.assert_close(loss, torch.tensor([[row0, 0.0]]))
    # The release: KLDivLoss(batchmean)(log_softmax(e_T), softmax(e_S)) = sum over T and E, mean over B.
    release = F.kl_div(F.log_softmax(target, dim=-1), F.softmax(source.detach(), dim=-1), reduction="batchmean")
    torch.testing.assert_close(loss.sum(dim=1).mean(), release)
    loss.sum().backward()
    assert source.grad is None
    assert target.grad is not None and target.grad.abs().sum() > 0


# --------------------------------------------------------------------------------------------------------------
# Eqs. 4-5
# --------------------------------------------------------------------------------------------------------------


def test_relabel_reward_endpoints_and_k_point_two() -> None:
    pred = torch.tensor([[2.0, -1.0]])
    reward = torch.tensor([[1.0, 0.5]])
    torch.testing.assert_close(relabel_reward(pred, reward, k=0.0), reward)
    torch.testing.assert_close(relabel_reward(pred, reward, k=1.0), pred)
    # 0.2 * 2 + 0.8 * 1 = 1.2;  0.2 * -1 + 0.8 * 0.5 = 0.2
    torch.testing.assert_close(relabel_reward(pred, reward, k=0.2), torch.tensor([[1.2, 0.2]]))


def test_relabel_reward_has_no_gradient_into_source_prediction() -> None:
    pred = torch.tensor([[2.0, -1.0]], requires_grad=True)
    reward = torch.tensor([[1.0, 0.5]])
    assert not relabel_reward(pred, reward, k=0.2).requires_grad
    # Even with a target reward that carries gradient, none flows into the prediction.
    reward_with_grad = reward.clone().requires_grad_(True)
    relabel_reward(pred, reward_with_grad, k=0.2).sum().backward()
    assert pred.grad is None
    torch.testing.assert_close(reward_with_grad.grad, torch.tensor([[0.8, 0.8]]))


def test_relabel_reward_rejects_bad_k_and_broadcasting_shapes() -> None:
    pred = torch.zeros(2, 3)
    with pytest.raises(ValueError, match="k must be"):
        relabel_reward(pred, pred, k=1.5)
    with pytest.raises(ValueError, match="one shape"):
        relabel_reward(pred.unsqueeze(-1), pred, k=0.2)  # (B, T, 1) with (B, T) would broadcast to (B, T, T)


def test_source_reward_loss_on_target_hand_values_and_gradient() -> None:
    pred = torch.tensor([[2.0, 0.0]], requires_grad=True)
    relabelled = torch.tensor([[1.2, 0.5]], requires_grad=True)
    loss = source_reward_loss_on_target(pred, relabelled)
    torch.testing.assert_close(loss, torch.tensor([[0.5 * 0.8**2, 0.5 * 0.5**2]]))
    loss.sum().backward()
    torch.testing.assert_close(pred.grad, torch.tensor([[0.8, -0.5]]))
    assert relabelled.grad is None


def test_source_reward_loss_is_unit_gaussian_nll_up_to_constant() -> None:
    pred = torch.tensor([[2.0, -0.3, 1.0]])
    label = torch.tensor([[1.2, 0.4, 1.0]])
    nll = -torch.distributions.Normal(pred, 1.0).log_prob(label)
    torch.testing.assert_close(source_reward_loss_on_target(pred, label), nll - 0.5 * math.log(2 * math.pi))


def test_relabelled_loss_with_same_head_prediction_is_damped_by_one_minus_k() -> None:
    # pred 2, r_T 1, k 0.2: label 1.2, loss 0.5 * 0.8^2 = 0.5 * (1 - k)^2 * (pred - r_T)^2 = 0.32.
    pred = torch.tensor([[2.0]], requires_grad=True)
    label = relabel_reward(pred, torch.tensor([[1.0]]), k=0.2)
    loss = source_reward_loss_on_target(pred, label)
    torch.testing.assert_close(loss, torch.tensor([[0.32]]))
    loss.sum().backward()
    torch.testing.assert_close(pred.grad, torch.tensor([[0.8]]))


# --------------------------------------------------------------------------------------------------------------
# Eq. 6
# --------------------------------------------------------------------------------------------------------------


def test_value_regulariser_hand_values_for_several_zeta() -> None:
    v_t = torch.tensor([[3.0, 1.0]])
    v_s = torch.tensor([[2.0, 2.5]])
    torch.testing.assert_close(value_regulariser(v_t, v_s, zeta=1.0), torch.tensor([[3.0, 2.5]]))
    torch.testing.assert_close(value_regulariser(v_t, v_s, zeta=0.5), torch.tensor([[2.0, 2.5]]))
    torch.testing.assert_close(value_regulariser(v_t, v_s, zeta=2.0), torch.tensor([[6.0, 2.5]]))
    assert max_min_active(v_t, v_s, zeta=1.0).tolist() == [[True, False]]
    assert max_min_active(v_t, v_s, zeta=0.5).tolist() == [[False, False]]
    assert max_min_active(v_t, v_s, zeta=2.5).tolist() == [[True, False]]
    assert max_min_active(v_t, v_s, zeta=2.6).tolist() == [[True, True]]  # 2.6 * 1 > 2.5


def test_value_regulariser_gradient_is_alpha_zeta_where_target_higher_and_zero_elsewhere() -> None:
    alpha, zeta = 0.2, 1.5
    v_t = torch.tensor([[3.0, 1.0], [2.0, -1.0]], requires_grad=True)
    v_s = torch.tensor([[2.0, 2.5], [2.9, -2.0]], requires_grad=True)
    # zeta * v_t = [[4.5, 1.5], [3.0, -1.5]] against [[2.0, 2.5], [2.9, -2.0]].
    (alpha * value_regulariser(v_t, v_s, zeta)).sum().backward()
    torch.testing.assert_close(v_t.grad, torch.tensor([[0.3, 0.0], [0.3, 0.3]]))
    assert v_s.grad is None


def test_gradient_descent_lowers_a_value_above_the_source_and_leaves_one_below() -> None:
    # Regulariser alone, alpha = zeta = 1, step 0.25: 3.0 -> 2.75 -> 2.5 -> 2.25 -> 2.0 and then stays at the
    # source value 2.0 (a tie counts as inactive); 1.0 is below its source value 2.5 and never moves.
    value = torch.tensor([[3.0, 1.0]], requires_grad=True)
    source = torch.tensor([[2.0, 2.5]])
    for _ in range(6):
        value.grad = None
        value_regulariser(value, source, zeta=1.0).sum().backward()
        assert value.grad is not None
        with torch.no_grad():
            value -= 0.25 * value.grad
    torch.testing.assert_close(value.detach(), torch.tensor([[2.0, 1.0]]), rtol=0.0, atol=0.0)


def test_regularised_critic_loss_term_by_term() -> None:
    value = torch.tensor([[3.0, 1.0]], requires_grad=True)
    returns = torch.tensor([[2.0, 1.5]], requires_grad=True)
    source = torch.tensor([[2.0, 2.5]], requires_grad=True)
    weight = torch.tensor([[1.0, 0.5]], requires_grad=True)
    alpha, zeta = 0.2, 1.5
    # fit: 0.5 * 1^2 = 0.5, 0.5 * 0.5^2 = 0.125; max: max(4.5, 2) = 4.5, max(1.5, 2.5) = 2.5.
    # loss: 1.0 * (0.5 + 0.2 * 4.5) = 1.4;  0.5 * (0.125 + 0.2 * 2.5) = 0.3125.
    loss = regularised_critic_loss(value, returns, weight, source, alpha=alpha, zeta=zeta)
    torch.testing.assert_close(loss, torch.tensor([[1.4, 0.3125]]))
    loss.sum().backward()
    # d/dv: weight * ((v - V) + alpha * zeta * active) = [1.0 * (1 + 0.3), 0.5 * (-0.5 + 0)].
    torch.testing.assert_close(value.grad, torch.tensor([[1.3, -0.25]]))
    assert returns.grad is None and source.grad is None and weight.grad is None
    unweighted = regularised_critic_loss(value, returns, torch.ones_like(weight), source, alpha=alpha, zeta=zeta)
    torch.testing.assert_close(unweighted, torch.tensor([[1.4, 0.625]]))


def test_the_on_mean_form_on_a_twohot_critic_is_its_cross_entropy_plus_the_max_min_term() -> None:
    """Eq. 6 read on a two-hot critic's mean (``cap_form='on_mean'``): the regression term is the critic's own
    negative log-likelihood of the lambda-return, the max-min term reads the critic's mean."""
    logits = torch.randn(2, 3, TWOHOT_BINS, generator=torch.Generator().manual_seed(0))
    value = TwoHotSymlog(logits)
    returns, source, weight = torch.full((2, 3), 0.5), torch.zeros(2, 3), torch.full((2, 3), 0.8)
    loss = regularised_critic_loss(value, returns, weight, source, alpha=0.3, zeta=2.0, form="on_mean")
    expected = weight * (-value.log_prob(returns) + 0.3 * torch.maximum(2.0 * value.mean, source))
    torch.testing.assert_close(loss, expected)


def test_regularised_critic_loss_with_alpha_zero_is_plain_dreamer_critic() -> None:
    value = torch.tensor([[3.0, 1.0]])
    returns = torch.tensor([[2.0, 1.5]])
    loss = regularised_critic_loss(value, returns, torch.ones(1, 2), torch.tensor([[9.0, 9.0]]), alpha=0.0, zeta=1.0)
    torch.testing.assert_close(loss, torch.tensor([[0.5, 0.125]]))


def test_eq6_rejects_bad_scales_and_shapes() -> None:
    v = torch.zeros(3, 4)
    with pytest.raises(ValueError, match="zeta"):
        value_regulariser(v, v, zeta=0.0)
    with pytest.raises(ValueError, match="zeta"):
        max_min_active(v, v, zeta=-1.0)
    with pytest.raises(ValueError, match="alpha"):
        regularised_critic_loss(v, v, v, v, alpha=-0.1, zeta=1.0)
    with pytest.raises(ValueError, match="one shape"):
        regularised_critic_loss(v, v, v, v[:, :1], alpha=0.2, zeta=1.0)
    with pytest.raises(ValueError, match="one shape"):
        regularised_critic_loss(v, v, v[:1], v, alpha=0.2, zeta=1.0)


def test_source_reward_loss_of_a_twohot_head_is_its_cross_entropy_of_the_label() -> None:
    from coworld.distributions import TWOHOT_BINS, TwoHotSymlog

    torch.manual_seed(0)
    logits = torch.randn(2, 3, TWOHOT_BINS, requires_grad=True)
    head = TwoHotSymlog(logits)
    label = relabel_reward(head.mean, torch.rand(2, 3), 0.3)
    loss = source_reward_loss_on_target(head, label)
    torch.testing.assert_close(loss, -head.log_prob(label))
    assert loss.shape == (2, 3) and float(loss.detach().min()) > 0
    loss.sum().backward()
    assert logits.grad is not None and float(logits.grad.abs().sum()) > 0
    with pytest.raises(ValueError):
        source_reward_loss_on_target(head, torch.zeros(2, 4))


def test_shape_checks_name_every_tensor_and_refuse_broadcasting() -> None:
    """Each equation refuses inputs that would broadcast (a silent wrong answer) and names every input and its
    shape, so the message says which tensor is off; a flat embedding names the shape it needs."""
    e = torch.zeros(2, 3, 4)
    with pytest.raises(ValueError, match=r"source_embed=\(2, 3, 4\), target_embed=\(1, 3, 4\)"):
        embedding_alignment_loss(e, e[:1])
    with pytest.raises(ValueError, match=r"source_embed=\(1, 3, 4\), target_embed=\(2, 3, 4\)"):
        embedding_alignment_loss(e[:1], e)
    with pytest.raises(ValueError, match=r"^source_embed must have shape \(B, T, E\), got \(3, 4\)$"):
        embedding_alignment_loss(e[0], e[0])
    logits = torch.zeros(2, 3, 4, 5)
    with pytest.raises(ValueError, match=r"^source_logits must have shape \(B, T, S, K\), got \(3, 4, 5\)$"):
        alignment_loss(logits[0], logits[0])
    v = torch.zeros(3, 4)
    for fn in (max_min_active, value_regulariser):
        with pytest.raises(ValueError, match=r"target_value=\(3, 4\), source_value=\(1, 4\)"):
            fn(v, v[:1], zeta=1.0)
        with pytest.raises(ValueError, match=r"target_value=\(1, 4\), source_value=\(3, 4\)"):
            fn(v[:1], v, zeta=1.0)
    names = ("value", "target", "weight", "source_value")
    for i in range(4):
        args = [v, v, v, v]
        args[i] = v[:1]
        shapes = [f"{name}={(1, 4) if j == i else (3, 4)}" for j, name in enumerate(names)]
        shapes = ", ".join([shapes[0], shapes[1], shapes[3], shapes[2]])  # checked in the order value, target, source
        with pytest.raises(ValueError, match=re.escape(f"got {shapes}")):
            regularised_critic_loss(*args, alpha=0.2, zeta=1.0)
