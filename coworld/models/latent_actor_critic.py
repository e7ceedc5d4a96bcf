"""LOMPO's actor-critic on latent features: a deterministic tanh actor and twin Q-functions with Polyak targets.

The networks are this project's :class:`~coworld.models.networks.MLP` (ELU, no norm, as V-D4RL's LOMPO
``DenseNetwork`` and ``ActorNetwork``). The actor returns a :class:`~coworld.distributions.Normal` centred on
its action with LOMPO's exploration noise as the spread, so the DreamerV2 agent's ``policy`` acts with it unchanged:
the mode in evaluation, a noisy sample (clipped to ``[-1, 1]``) when acting to train.
"""

from __future__ import annotations

import copy

import torch
from torch import Tensor, nn

from coworld.config import LompoConfig
from coworld.distributions import Normal
from coworld.models.networks import MLP

__all__ = ["LatentActor", "LatentActorCritic"]


class LatentActor(nn.Module):
    """``feat (..., F) -> Normal(tanh(MLP(feat)), noise)`` over actions ``(..., A)``."""

    def __init__(self, *, feat_size: int, action_size: int, units: int, layers: int, noise: float) -> None:
        super().__init__()
        self.mlp = MLP(in_size=feat_size, out_size=action_size, units=units, layers=layers)
        self.noise = noise

    def action(self, feat: Tensor) -> Tensor:
        """The deterministic action ``tanh(MLP(feat))``, ``(..., A)``."""
        return torch.tanh(self.mlp(feat))

    def forward(self, feat: Tensor) -> Normal:
        mean = self.action(feat)
        return Normal(mean, torch.full_like(mean, self.noise))


class LatentActorCritic(nn.Module):
    """The actor, two Q-functions ``(feat, action) -> Q`` and their targets (copies updated by Polyak averaging)."""

    def __init__(self, *, config: LompoConfig, feat_size: int, action_size: int) -> None:
        super().__init__()
        self.actor = LatentActor(
            feat_size=feat_size,
            action_size=action_size,
            units=config.units,
            layers=config.actor_layers,
            noise=config.expl_noise,
        )

        def q_function() -> MLP:
            return MLP(in_size=feat_size + action_size, out_size=1, units=config.units, layers=config.critic_layers)

        self.critic = nn.ModuleList([q_function(), q_function()])
        self.target_critic = copy.deepcopy(self.critic)
        self.target_critic.requires_grad_(False)

    @staticmethod
    def _q(pair: nn.ModuleList, feat: Tensor, action: Tensor) -> tuple[Tensor, Tensor]:
        x = torch.cat([feat, action.to(feat.dtype)], dim=-1)
        return pair[0](x).squeeze(-1), pair[1](x).squeeze(-1)

    def q(self, feat: Tensor, action: Tensor) -> tuple[Tensor, Tensor]:
        """``(Q1, Q2)`` each ``(...)`` of features ``(..., F)`` and actions ``(..., A)``."""
        return self._q(self.critic, feat, action)

    def target_q(self, feat: Tensor, action: Tensor) -> tuple[Tensor, Tensor]:
        """The target Q-functions' ``(Q1', Q2')``."""
        return self._q(self.target_critic, feat, action)

    def critic_value(self, feat: Tensor) -> Tensor:
        """``min(Q1, Q2)(s, pi(s))``, ``(...)``: the return the critic expects from ``s`` under the actor."""
        return torch.minimum(*self.q(feat, self.actor.action(feat)))

    @torch.no_grad()
    def update_target(self, tau: float) -> None:
        """``Q' <- tau * Q + (1 - tau) * Q'``."""
        for target, online in zip(self.target_critic.parameters(), self.critic.parameters(), strict=True):
            target.lerp_(online, tau)
