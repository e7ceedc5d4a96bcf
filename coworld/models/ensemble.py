"""An ensemble of dynamics heads beside the RSSM's prior (V-D4RL's offline DreamerV2 penalty).

Each head maps the deterministic state ``h (..., D)`` to logits of the categorical latent ``(..., S, C)``, the
shape of the RSSM's prior head (``Linear -> ELU -> Linear``, as V-D4RL's ``EnsembleRSSM`` heads). The heads read
``h`` detached: they learn to predict the latent without changing the world model, whose own prior stays the one
of DreamerV2.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from coworld.models.networks import MLP

__all__ = ["DynamicsEnsemble"]


class DynamicsEnsemble(nn.Module):
    """``size`` heads ``deter (..., D) -> logits (size, ..., S, C)`` (log-softmax normalised)."""

    def __init__(self, *, size: int, deter: int, hidden: int, stoch: int, classes: int) -> None:
        super().__init__()
        self.size, self.stoch, self.classes = size, stoch, classes
        self.heads = nn.ModuleList(
            MLP(in_size=deter, out_size=stoch * classes, units=hidden, layers=1) for _ in range(size)
        )

    def forward(self, deter: Tensor) -> Tensor:
        """``(..., D)`` -> ``(K, ..., S, C)`` log-probabilities; ``deter`` is detached here."""
        x = deter.detach()
        raw = torch.stack([head(x) for head in self.heads]).float()
        return raw.reshape(*raw.shape[:-1], self.stoch, self.classes).log_softmax(dim=-1)
