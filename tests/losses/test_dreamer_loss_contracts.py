"""DreamerV2's loss functions (coworld/losses/dreamer.py) at their edges: the errors they raise say what is wrong.
(Their values are tested in tests/models/test_dreamer_losses.py; these came from the mutation run of issue 52,
docs/testing.md.)"""

from __future__ import annotations

import pytest
import torch

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


@pytest.mark.parametrize("offset", [1.0, 1.5, -0.75])
def test_image_loss_takes_any_offset_off_the_prediction_for_pixels_and_scaled_images(offset: float) -> None:
    """``image_loss(pred, target, offset)`` is ``0.5 * sum((pred - offset - target)^2)`` for every offset, not only
    the 0, 0.5 and 0.25 the world model and the other tests use; a float64 target gives the float32 loss."""
    pred = torch.randn(2, 3, 3, 8, 8)
    pixels = torch.randint(0, 256, pred.shape, dtype=torch.uint8)
    scaled = pixels.double() / 255.0 - 0.5
    expected = 0.5 * (pred.double() - offset - scaled).square().sum((2, 3, 4))
    for target in (pixels, scaled, scaled.float()):
        got = image_loss(pred, target, offset=offset)
        assert got.dtype == torch.float32
        torch.testing.assert_close(got.double(), expected, rtol=1e-5, atol=1e-4)
