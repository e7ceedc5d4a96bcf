"""Elastic weight consolidation's Fisher estimate and penalty on hand-worked numbers (coworld.losses.ewc)."""

from __future__ import annotations

import pytest
import torch

from coworld.losses.ewc import ewc_penalty, fisher_diagonal


def test_fisher_diagonal_is_the_mean_squared_gradient_times_the_steps_per_batch() -> None:
    grads = [
        {"w": torch.tensor([1.0, -2.0]), "b": torch.tensor(0.5)},
        {"w": torch.tensor([3.0, 0.0]), "b": torch.tensor(-0.5)},
    ]
    fisher = fisher_diagonal(grads)
    torch.testing.assert_close(fisher["w"], torch.tensor([5.0, 2.0]))  # (1 + 9) / 2, (4 + 0) / 2
    torch.testing.assert_close(fisher["b"], torch.tensor(0.25))
    torch.testing.assert_close(fisher_diagonal(grads, samples=4)["w"], torch.tensor([20.0, 8.0]))


def test_fisher_diagonal_refuses_no_batches_and_batches_of_other_parameters() -> None:
    with pytest.raises(ValueError, match="at least one batch"):
        fisher_diagonal([])
    with pytest.raises(ValueError, match="same parameters"):
        fisher_diagonal([{"w": torch.zeros(2)}, {"v": torch.zeros(2)}])


def test_ewc_penalty_is_half_lambda_times_the_fisher_weighted_squared_distance() -> None:
    theta = torch.tensor([1.0, 2.0], requires_grad=True)
    params = {"w": theta, "other": torch.ones(3)}  # a parameter without an anchor is free
    anchor, fisher = {"w": torch.tensor([0.0, 0.0])}, {"w": torch.tensor([2.0, 3.0])}
    penalty = ewc_penalty(params, anchor, fisher, weight=0.5)
    assert float(penalty.detach()) == pytest.approx(0.25 * (2.0 * 1.0 + 3.0 * 4.0))
    penalty.backward()
    torch.testing.assert_close(theta.grad, torch.tensor([1.0, 3.0]))  # lambda * F * (theta - theta*)
    assert float(ewc_penalty({"w": torch.zeros(2)}, anchor, fisher, weight=100.0)) == 0.0  # at the anchor
    assert float(ewc_penalty({}, {}, {}, weight=1.0)) == 0.0


def test_ewc_penalty_refuses_mismatched_names() -> None:
    with pytest.raises(ValueError, match="same parameters"):
        ewc_penalty({"w": torch.zeros(1)}, {"w": torch.zeros(1)}, {"v": torch.zeros(1)}, 1.0)
    with pytest.raises(ValueError, match="not given"):
        ewc_penalty({}, {"w": torch.zeros(1)}, {"w": torch.zeros(1)}, 1.0)
