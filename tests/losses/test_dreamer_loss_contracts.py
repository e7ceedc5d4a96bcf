"""DreamerV2's loss functions (coworld/losses/dreamer.py) at their edges: the errors they raise say what is wrong.
(Their values are tested in tests/models/test_dreamer_losses.py; these came from the mutation run of issue 52,
docs/testing.md.)"""

from __future__ import annotations

import pytest
import torch

from coworld.losses.dreamer import actor_loss, critic_loss


def test_critic_loss_names_the_value_and_the_target_when_their_shapes_differ() -> None:
    value, target = torch.zeros(3, 4), torch.zeros(3, 1)
    with pytest.raises(ValueError, match=r"^value \(3, 4\) and target \(3, 1\) differ in shape$"):
        critic_loss(value, target, torch.ones(3, 4))


def test_the_reinforce_actor_loss_without_a_baseline_says_so() -> None:
    x = torch.zeros(2, 3)
    with pytest.raises(ValueError, match=r"^the 'reinforce' actor loss needs a baseline$"):
        actor_loss(target=x, weight=x, entropy=x, entropy_scale=0.1, log_prob=x)
