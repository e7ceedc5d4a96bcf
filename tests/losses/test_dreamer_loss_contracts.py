"""DreamerV2's loss functions (coworld/losses/dreamer.py) at their edges: the errors they raise say what is wrong.
(Their values are tested in tests/models/test_dreamer_losses.py; these came from the mutation run of issue 52,
docs/testing.md.)"""

from __future__ import annotations

import pytest
import torch

from coworld.distributions import UnitGaussian
from coworld.losses.dreamer import actor_loss, critic_loss, image_loss, reward_loss


def test_critic_loss_names_the_value_and_the_target_when_their_shapes_differ() -> None:
    value, target = torch.zeros(3, 4), torch.zeros(3, 1)
    with pytest.raises(ValueError, match=r"^value \(3, 4\) and target \(3, 1\) differ in shape$"):
        critic_loss(value, target, torch.ones(3, 4))


def test_the_reinforce_actor_loss_without_a_baseline_says_so() -> None:
    x = torch.zeros(2, 3)
    with pytest.raises(ValueError, match=r"^the 'reinforce' actor loss needs a baseline$"):
        actor_loss(target=x, weight=x, entropy=x, entropy_scale=0.1, log_prob=x)


def test_reward_loss_names_the_reward_prediction_when_shapes_differ() -> None:
    with pytest.raises(ValueError, match=r"^reward prediction \(2, 3\) and target \(2, 2\) differ in shape$"):
        reward_loss(torch.zeros(2, 3), torch.zeros(2, 2))


def test_image_loss_is_half_the_squared_error_summed_over_each_image_in_float32() -> None:
    """``0.5 * sum_{C,H,W} (pred - target)^2`` per ``(B, T)``, from a mean or its :class:`UnitGaussian`, computed in
    float32 whatever the inputs' float dtype."""
    pred, target = torch.randn(2, 3, 3, 4, 5, dtype=torch.float64), torch.rand(2, 3, 3, 4, 5, dtype=torch.float64)
    expected = 0.5 * (pred.float() - target.float()).square().sum((2, 3, 4))
    for prediction in (pred, UnitGaussian(pred, event_dims=3)):
        got = image_loss(prediction, target)
        assert got.dtype == torch.float32 and got.shape == (2, 3)
        torch.testing.assert_close(got, expected)
