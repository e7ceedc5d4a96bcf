"""CURL and CURL+CQL losses: hand-computed values, signs, and where gradient flows."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from coworld.losses.curl import (
    actor_loss,
    cql_penalty,
    info_nce,
    sac_critic_target,
    temperature_loss,
    twin_q_loss,
    uniform_log_prob,
)

# --------------------------------------------------------------------------------------------------------------
# InfoNCE
# --------------------------------------------------------------------------------------------------------------


def test_info_nce_two_by_two_by_hand() -> None:
    # q = k = I, W = I: logits [[1, 0], [0, 1]] -> shifted [[0, -1], [-1, 0]];
    # each row's loss = -log(e^0 / (e^0 + e^-1)) = log(1 + e^-1).
    eye = torch.eye(2)
    loss, logits = info_nce(eye, eye, eye)
    assert torch.allclose(logits, torch.tensor([[0.0, -1.0], [-1.0, 0.0]]))
    assert loss.item() == pytest.approx(math.log(1 + math.exp(-1)), abs=1e-6)


def test_info_nce_bilinear_w_enters_the_logits() -> None:
    # W = [[0, 2], [1, 0]]: q_0 W k_1 = e0^T W e1 = W[0, 1] = 2, q_1 W k_0 = W[1, 0] = 1, diagonal W[i, i] = 0.
    # Row 0: [0, 2] -> shifted [-2, 0]: loss -log(e^-2 / (e^-2 + 1)) = log(1 + e^2).
    # Row 1: [1, 0] -> shifted [0, -1], label 1: loss -log(e^-1 / (1 + e^-1)) = log(1 + e).
    W = torch.tensor([[0.0, 2.0], [1.0, 0.0]])
    loss, logits = info_nce(torch.eye(2), torch.eye(2), W)
    assert torch.allclose(logits, torch.tensor([[-2.0, 0.0], [0.0, -1.0]]))
    expected = 0.5 * (math.log(1 + math.exp(2)) + math.log(1 + math.e))
    assert loss.item() == pytest.approx(expected, abs=1e-6)


def test_info_nce_positive_pair_scores_highest_and_shuffled_keys_cost_more() -> None:
    torch.manual_seed(0)
    queries = F.normalize(torch.randn(8, 16), dim=1) * 3
    W = torch.eye(16)
    matched, logits = info_nce(queries, queries.clone(), W)
    # Distinct vectors of one norm: the dot product with itself is the strict maximum of each row (Cauchy-Schwarz).
    assert torch.equal(logits.argmax(dim=1), torch.arange(8))
    assert torch.allclose(logits.diagonal(), torch.zeros(8))
    shuffled, _ = info_nce(queries, queries.roll(1, dims=0), W)
    assert matched.item() < shuffled.item()
    assert matched.item() < math.log(8) < shuffled.item()  # log B: the loss of uninformative logits


def test_info_nce_gradient_reaches_queries_and_w_not_keys() -> None:
    queries = torch.randn(4, 3, requires_grad=True)
    keys = torch.randn(4, 3, requires_grad=True)
    W = torch.rand(3, 3, requires_grad=True)
    loss, _ = info_nce(queries, keys, W)
    loss.backward()
    assert queries.grad is not None and queries.grad.abs().sum() > 0
    assert W.grad is not None and W.grad.abs().sum() > 0
    assert keys.grad is None


def test_info_nce_rejects_mismatched_shapes() -> None:
    with pytest.raises(ValueError, match="keys"):
        info_nce(torch.zeros(4, 3), torch.zeros(5, 3), torch.eye(3))


# --------------------------------------------------------------------------------------------------------------
# SAC
# --------------------------------------------------------------------------------------------------------------


def test_sac_critic_target_by_hand() -> None:
    # Row 0: 1 + 0.9 * (min(2, 1.5) - 0.1 * (-1)) = 1 + 0.9 * 1.6 = 2.44.
    # Row 1 terminated: the target is the reward alone, 0.5.
    target = sac_critic_target(
        reward=torch.tensor([1.0, 0.5]),
        not_done=torch.tensor([1.0, 0.0]),
        next_q1=torch.tensor([2.0, 3.0]),
        next_q2=torch.tensor([1.5, 4.0]),
        next_log_prob=torch.tensor([-1.0, 2.0]),
        alpha=0.1,
        discount=0.9,
    )
    assert torch.allclose(target, torch.tensor([2.44, 0.5]))


def test_sac_critic_target_carries_no_gradient() -> None:
    next_q1 = torch.tensor([1.0, 2.0], requires_grad=True)
    alpha = torch.tensor(0.3, requires_grad=True)
    target = sac_critic_target(torch.ones(2), torch.ones(2), next_q1, next_q1 + 1, torch.zeros(2), alpha, 0.99)
    assert not target.requires_grad


def test_sac_critic_target_rejects_broadcasting() -> None:
    with pytest.raises(ValueError, match="next_q1"):
        sac_critic_target(torch.ones(2), torch.ones(2), torch.ones(2, 1), torch.ones(2), torch.ones(2), 0.1, 0.99)


def test_twin_q_loss_by_hand() -> None:
    # (1-1)^2 + (0-1)^2 = 1;  (2-1)^2 + (2-1)^2 = 2.
    loss = twin_q_loss(torch.tensor([1.0, 2.0]), torch.tensor([0.0, 2.0]), torch.tensor([1.0, 1.0]))
    assert torch.allclose(loss, torch.tensor([1.0, 2.0]))


def test_actor_loss_by_hand_uses_the_smaller_q() -> None:
    # 0.2 * (-1) - min(1, 2) = -1.2;  0.2 * 0.5 - min(3, 0) = 0.1.
    loss = actor_loss(torch.tensor([1.0, 3.0]), torch.tensor([2.0, 0.0]), torch.tensor([-1.0, 0.5]), 0.2)
    assert torch.allclose(loss, torch.tensor([-1.2, 0.1]))


def test_temperature_loss_value_and_gradient_sign() -> None:
    # alpha = 0.5, H_target = -2: 0.5 * (1 + 2) = 1.5 and 0.5 * (-3 + 2) = -0.5.
    log_alpha = torch.tensor(math.log(0.5), requires_grad=True)
    log_prob = torch.tensor([-1.0, 3.0], requires_grad=True)
    loss = temperature_loss(log_alpha, log_prob, target_entropy=-2.0)
    assert torch.allclose(loss, torch.tensor([1.5, -0.5]))
    loss.mean().backward()
    # d/dlog_alpha of mean(alpha * x) = mean(alpha * x) = 0.5 > 0: the mean entropy (-1) is above the target
    # (-2), so gradient descent lowers the temperature.
    assert log_alpha.grad.item() == pytest.approx(0.5)
    assert log_prob.grad is None


def test_temperature_loss_rises_alpha_when_entropy_is_below_target() -> None:
    log_alpha = torch.tensor(0.0, requires_grad=True)
    temperature_loss(log_alpha, torch.tensor([5.0]), target_entropy=-1.0).sum().backward()
    assert log_alpha.grad.item() < 0  # entropy -5 < -1: descent raises alpha


# --------------------------------------------------------------------------------------------------------------
# CQL(H)
# --------------------------------------------------------------------------------------------------------------


def test_uniform_log_prob() -> None:
    assert uniform_log_prob(3) == pytest.approx(-3 * math.log(2))
    assert uniform_log_prob(2, 0.0, 0.5) == pytest.approx(-2 * math.log(0.5))


def test_cql_penalty_small_case_by_hand() -> None:
    # Importance-weighted values: [0, ln 3] (random, log-density 0) and [ln 2] (policy, log-density 0):
    # log(1/3 * (1 + 3 + 2)) = ln 2;  minus Q(s, a_data) = 0.5.
    penalty = cql_penalty(
        q_random=torch.tensor([[0.0, math.log(3)]]),
        log_prob_random=0.0,
        q_policy=torch.tensor([[math.log(2)]]),
        log_prob_policy=torch.tensor([[0.0]]),
        q_data=torch.tensor([0.5]),
    )
    assert penalty.shape == (1,)
    assert penalty.item() == pytest.approx(math.log(2) - 0.5, abs=1e-6)


def test_cql_penalty_importance_weights_divide_by_the_proposal_density() -> None:
    # One random action scored Q = 1 under density 1/4 (log -ln 4), one policy action scored Q = 1 under
    # density 4 (log ln 4): log(1/2 * (e^1 * 4 + e^1 / 4)) - 0 = 1 + log(17 / 8).
    penalty = cql_penalty(
        torch.tensor([[1.0]]), torch.tensor([[-math.log(4)]]), torch.tensor([[1.0]]), torch.tensor([[math.log(4)]]),
        torch.tensor([0.0]),
    )  # fmt: skip
    assert penalty.item() == pytest.approx(1 + math.log(17 / 8), abs=1e-6)


def test_cql_penalty_constant_q_estimates_the_box_volume() -> None:
    # A constant Q = c on [-1, 1]^A: log integral exp(c) da = c + A log 2, whatever the proposals, if each
    # log-density is exact. Policy proposals here are uniform too.
    A, c = 3, 1.7
    q_random = torch.full((2, 5), c)
    q_policy = torch.full((2, 4), c)
    penalty = cql_penalty(
        q_random, uniform_log_prob(A), q_policy, torch.full((2, 4), uniform_log_prob(A)), q_random[:, 0]
    )
    assert torch.allclose(penalty, torch.full((2,), A * math.log(2)))


def test_cql_penalty_is_smaller_when_q_peaks_on_the_data_action() -> None:
    # Toy Q on A = 1: a bump of height 3 at one action. Data action 0.5. Bump on the data action vs bump at -0.5.
    torch.manual_seed(0)
    random_actions = torch.rand(1, 2000) * 2 - 1
    data_action = torch.tensor([0.5])

    def q(actions: torch.Tensor, peak: float) -> torch.Tensor:
        return 3.0 * torch.exp(-((actions - peak) ** 2) / 0.02)

    policy = torch.zeros(1, 0)
    on_data = cql_penalty(q(random_actions, 0.5), uniform_log_prob(1), policy, policy, q(data_action, 0.5))
    elsewhere = cql_penalty(q(random_actions, -0.5), uniform_log_prob(1), policy, policy, q(data_action, -0.5))
    assert on_data.item() < elsewhere.item()
    # Monte-Carlo vs the integral: exp(Q) - 1 integrates to ~ (e^3 - 1) * 0.25 over the bump (a Gaussian of
    # sd 0.1 has integral sqrt(2 pi) * 0.1 = 0.2507), plus 2 for the 1 of the whole box.
    bump = sum((math.exp(3 * math.exp(-(x**2) / 0.02)) - 1) * 0.001 for x in [i * 0.001 - 1 for i in range(2001)])
    assert elsewhere.item() == pytest.approx(math.log(2 + bump), abs=0.15)
    assert on_data.item() == pytest.approx(math.log(2 + bump) - 3.0, abs=0.15)


def test_cql_penalty_gradient_pushes_ood_q_down_and_data_q_up() -> None:
    q_random = torch.tensor([[0.0, 2.0]], requires_grad=True)
    q_policy = torch.tensor([[1.0]], requires_grad=True)
    q_data = torch.tensor([1.0], requires_grad=True)
    log_prob_policy = torch.tensor([[0.5]], requires_grad=True)
    cql_penalty(q_random, 0.0, q_policy, log_prob_policy, q_data).sum().backward()
    # d/dQ_i of logsumexp = softmax weight > 0 (descent lowers them); d/dQ_data = -1 (descent raises it).
    weights = torch.softmax(torch.tensor([0.0, 2.0, 0.5]), dim=0)
    assert torch.allclose(q_random.grad, weights[:2][None])
    assert torch.allclose(q_policy.grad, weights[2:][None])
    assert q_data.grad.item() == pytest.approx(-1.0)
    assert log_prob_policy.grad is None


def test_cql_penalty_rejects_mismatched_shapes() -> None:
    with pytest.raises(ValueError, match="log_prob_policy"):
        cql_penalty(torch.zeros(2, 3), 0.0, torch.zeros(2, 4), torch.zeros(2, 3), torch.zeros(2))
