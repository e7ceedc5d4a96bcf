"""A critic of another agent's policy in this agent's world model: CoWorld's target-policy cap
(``coworld.cap_critic='target_policy'``, an option beyond both papers; docs/algorithms.md, "When the cap binds").

In the papers and the release the source critic that caps the target critic in Eq. 6 learns the value of the
*source* policy on source imagination, while the paper's text calls the source domain "a test bed to evaluate
target domain policies". :class:`PolicyValue` learns what that phrase asks for: the value of the *target* actor's
behaviour imagined in the source world model, started from source posteriors and scored by the source reward
head (which Eqs. 4-5 also train on target sequences). It is DreamerV2's critic step (lambda-returns bootstrapped
from its own slow critic, :meth:`coworld.models.actor_critic.ActorCritic.losses`) on trajectories the target actor
imagines; neither the actor nor the world model learns from it.

Its imagination draws its random numbers from a generator seeded by ``(seed, the source agent's updates)``, inside a
fork of torch's global state, so the source agent's own updates draw exactly what they draw without it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor

from coworld.agents.dreamerv2 import make_optimizer
from coworld.config import Config
from coworld.models.actor_critic import Actor, ActorCritic, flatten_states
from coworld.models.networks import frozen_parameters
from coworld.models.rssm import State
from coworld.models.world_model import ScalarHead, WorldModel

__all__ = ["PolicyValue"]

SEED_STRIDE = 1_000_003
"""Imagination of update ``u`` is seeded with ``seed * SEED_STRIDE + u``."""


class PolicyValue:
    """The value ``v_pi(z)`` of a policy ``pi`` (another agent's actor) in a world model: a critic and its slow
    target, trained on trajectories ``pi`` imagines there.

    Args:
        config: the run's config (``actor_critic`` sizes the critic and its imagination, as the agents' own).
        feat_size: the world model's feature size.
        action_size: the size of the actions ``pi`` takes.
    """

    def __init__(self, *, config: Config, feat_size: int, action_size: int, device: torch.device) -> None:
        self.config = config
        ac = config.actor_critic
        # an ActorCritic for its imagination and its critic's loss; its own actor never acts and never learns
        self.values = ActorCritic(config=ac, feat_size=feat_size, action_size=action_size).to(device)
        self.optimizer = make_optimizer(
            self.values.critic.parameters(), lr=ac.critic_lr, eps=ac.eps, decay=ac.weight_decay
        )
        self.device = device

    @property
    def critic(self) -> ScalarHead:
        return self.values.critic

    def train(
        self, world_model: WorldModel, actor: Actor, post: State, *, is_terminal: Tensor, step: int
    ) -> dict[str, float]:
        """One critic step on ``actor``'s imagination in ``world_model`` from the posterior states ``post`` (batch
        ``(B, T)``), its random numbers seeded by ``step``; returns its metrics."""
        devices = [self.device] if self.device.type == "cuda" else []
        with frozen_parameters(world_model), frozen_parameters(actor), torch.random.fork_rng(devices=devices):
            torch.manual_seed(self.config.seed * SEED_STRIDE + step)
            traj = self.values.imagine(
                world_model, flatten_states(post), is_terminal=is_terminal.reshape(-1), actor=actor
            )
            terms, metrics = self.values.losses(world_model, traj)
        self.optimizer.zero_grad(set_to_none=True)
        terms["critic"].backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(self.values.critic.parameters(), self.config.actor_critic.grad_clip)
        self.optimizer.step()
        self.values.update_slow_target()
        return {
            "policy_value/loss": float(terms["critic"].detach()),
            "policy_value/value": float(metrics["critic/value"]),
            "policy_value/imag_return": float(metrics["imag/return"]),
            "policy_value/grad_norm": float(grad_norm),
        }

    def state_dict(self) -> dict[str, Any]:
        """The critic, its slow target and the optimiser (the unused actor is left out)."""
        return {
            "critic": self.values.critic.state_dict(),
            "slow_critic": self.values.slow_critic.state_dict(),
            "updates": self.values.updates.clone(),
            "optimizer": self.optimizer.state_dict(),
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.values.critic.load_state_dict(state["critic"])
        self.values.slow_critic.load_state_dict(state["slow_critic"])
        self.values.updates.copy_(state["updates"])
        self.optimizer.load_state_dict(state["optimizer"])
