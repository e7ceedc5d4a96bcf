"""The DrQ+BC actor: DrQ-v2's deterministic policy head on the critic's (detached) conv features.

DrQ-v2's encoder and twin critic are those of :mod:`coworld.models.curl` (4 conv layers of 32 filters, the first
with stride 2; ``Linear -> LayerNorm -> tanh`` trunks; two hidden layers per MLP); only the actor differs: it
outputs the mean ``tanh(mu(s))`` and the exploration std comes from a schedule
(:func:`coworld.losses.drqbc.exploration_std`).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from coworld.models.curl import Projection, _mlp

__all__ = ["DrqActor"]


class DrqActor(nn.Module):
    """``conv features (B, trunk_dim) -> mean action (B, A)`` in ``(-1, 1)``."""

    def __init__(self, *, trunk_dim: int, feature_dim: int, hidden: int, action_size: int) -> None:
        super().__init__()
        self.head = Projection(trunk_dim, feature_dim)
        self.mlp = _mlp(feature_dim, hidden, action_size)

    def forward(self, conv_features: Tensor) -> Tensor:
        return torch.tanh(self.mlp(self.head(conv_features)))
