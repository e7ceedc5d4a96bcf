"""LOMPO (Rafailov et al., 2021): offline RL from images with a latent world model whose ensemble of latent
dynamics penalises the imagined reward by its uncertainty (``baselines/lompo`` of github.com/conglu1997/v-d4rl).

The agent is :class:`coworld.agents.dreamerv2_penalty.PenaltyDreamerV2` (this project's DreamerV2 world model with
an ensemble of ``lompo.ensemble`` dynamics heads ``h -> z`` beside its prior) whose actor-critic is LOMPO's: a
deterministic actor and twin Q-functions on latent features (:class:`coworld.models.latent_actor_critic.
LatentActorCritic`). Two phases, counted in updates of one run:

* the first ``lompo.model_updates`` updates train the world model and the heads, as the penalised DreamerV2 does;
* every later update trains the actor-critic alone on ``lompo.batch_size`` real latent transitions
  ``(s_t, a_{t+1}, s_{t+1}, r_{t+1})`` (posterior features of the dataset batch under the frozen world model) and as
  many imagined ones: rollouts of ``lompo.horizon`` steps from posterior states, actions from the actor plus
  Gaussian noise, each next latent drawn from one head chosen at random, the reward head's reward lowered by
  ``lompo.weight * std_k log p_k(z')`` (:mod:`coworld.losses.lompo`).

Differences from V-D4RL's code, deliberate (docs/algorithms.md, "lompo"): the world model is DreamerV2's
(categorical latents, its prior trained as DreamerV2 trains it) with the heads beside the prior rather than being
it; and the rollouts are made afresh from each update's batch by the current actor, where LOMPO fills a buffer of
real and imagined transitions (50,000 imagined ones before the first agent update, one more batch of rollouts every
200 updates) and samples from it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from torch import Tensor

from coworld.agents.dreamerv2 import _to_floats, make_optimizer
from coworld.agents.dreamerv2_penalty import PenaltyDreamerV2
from coworld.distributions import OneHotCategorical
from coworld.losses.curl import twin_q_loss
from coworld.losses.lompo import deterministic_actor_loss, log_prob_spread, td_target
from coworld.losses.penalty import penalised_reward
from coworld.models.actor_critic import flatten_states
from coworld.models.latent_actor_critic import LatentActorCritic
from coworld.models.networks import frozen_parameters
from coworld.models.rssm import State

__all__ = ["Lompo", "Transitions"]

Transitions = dict[str, Tensor]
"""Latent transitions of batch ``(N,)``: ``feat (N, F)``, ``action (N, A)``, ``next_feat (N, F)``, ``reward (N,)``,
``not_done (N,)``."""

ADAM_EPS = 1e-7
"""The actor's and Q-functions' Adam epsilon (LOMPO's ``tf.optimizers.Adam`` default)."""


class Lompo(PenaltyDreamerV2):
    """LOMPO on this project's DreamerV2 world model (reads ``config.lompo``)."""

    section = "lompo"

    def _add_parts(self) -> None:
        """The ensemble (as the penalised DreamerV2's), then LOMPO's actor-critic and its optimisers in place of
        DreamerV2's."""
        super()._add_parts()
        c = self.config.lompo
        self.actor_critic = LatentActorCritic(
            config=c, feat_size=self.world_model.feat_size, action_size=self.action_size
        ).to(self.device)
        self.actor_opt = make_optimizer(self.actor_critic.actor.parameters(), lr=c.actor_lr, eps=ADAM_EPS, decay=0.0)
        self.critic_opt = make_optimizer(self.actor_critic.critic.parameters(), lr=c.critic_lr, eps=ADAM_EPS, decay=0.0)

    def train_policy(self, post: State, batch: Mapping[str, Tensor]) -> dict[str, float]:
        """The policy phase's step: :meth:`train_latent_actor_critic` on the posterior states in float32."""
        return self.train_latent_actor_critic({key: value.float() for key, value in post.items()}, batch)

    @torch.no_grad()
    def real_transitions(self, post: State, batch: Mapping[str, Tensor]) -> Transitions:
        """``lompo.batch_size`` transitions drawn uniformly (with replacement) from the batch's consecutive
        posterior states ``(B, T)`` of one episode: ``(s_t, a_{t+1}, s_{t+1}, r_{t+1}, 1 - terminal_{t+1})``."""
        feat = self.world_model.features(post).float()
        same_episode = ~batch["is_first"][:, 1:].bool()  # (B, T-1)
        rows, cols = same_episode.nonzero(as_tuple=True)
        if rows.numel() == 0:
            raise ValueError("the batch holds no two consecutive steps of one episode")
        pick = torch.randint(rows.numel(), (self.config.lompo.batch_size,), device=self.device)
        b, t = rows[pick], cols[pick]
        return {
            "feat": feat[b, t],
            "action": batch["action"][b, t + 1].float(),
            "next_feat": feat[b, t + 1],
            "reward": batch["reward"][b, t + 1].float(),
            "not_done": 1.0 - batch["is_terminal"][b, t + 1].float(),
        }

    @torch.no_grad()
    def imagined_transitions(self, post: State) -> tuple[Transitions, dict[str, Tensor]]:
        """``lompo.batch_size`` transitions of rollouts from posterior states drawn uniformly (``ceil(batch_size /
        horizon)`` rollouts of ``horizon`` steps), their rewards penalised; and the raw reward and penalty."""
        c, wm = self.config.lompo, self.world_model
        start = flatten_states(post)
        n = math.ceil(c.batch_size / c.horizon)
        pick = torch.randint(start["deter"].shape[0], (n,), device=self.device)
        state = {key: value[pick] for key, value in start.items()}
        rows = torch.arange(n, device=self.device)
        steps: list[dict[str, Tensor]] = []
        for _ in range(c.horizon):
            feat = wm.features(state).float()
            action = self.actor_critic.actor(feat).sample().clamp(-1.0, 1.0)
            deter = wm.rssm.recurrent(state, action)
            heads = self.ensemble(deter)  # (K, n, S, C)
            logits = heads[torch.randint(heads.shape[0], (n,), device=self.device), rows]
            stoch = OneHotCategorical(logits, normalised=True).rsample()
            state = {"deter": deter, "logits": logits, "stoch": stoch}
            next_feat = wm.features(state).float()
            reward = wm.reward_head(next_feat).mean.float()
            spread = log_prob_spread(heads, stoch)
            steps.append({"feat": feat, "action": action, "next_feat": next_feat, "raw": reward, "spread": spread})
        flat = {key: torch.cat([step[key] for step in steps])[: c.batch_size] for key in steps[0]}
        reward = penalised_reward(flat["raw"], flat["spread"], c.weight)
        imagined = {
            "feat": flat["feat"],
            "action": flat["action"],
            "next_feat": flat["next_feat"],
            "reward": reward,
            "not_done": torch.ones_like(reward),
        }
        return imagined, {"raw": flat["raw"], "spread": flat["spread"]}

    def train_latent_actor_critic(self, post: State, batch: Mapping[str, Tensor]) -> dict[str, float]:
        """One step of the Q-functions and the actor on real and imagined transitions, half of each; then the target
        Q-functions' Polyak step. Both losses are taken before either step, as LOMPO's two tapes are."""
        c, ac = self.config.lompo, self.actor_critic
        real = self.real_transitions(post, batch)
        imagined, seen = self.imagined_transitions(post)
        data = {key: torch.cat([real[key], imagined[key]]) for key in real}
        with torch.no_grad():
            next_q1, next_q2 = ac.target_q(data["next_feat"], ac.actor.action(data["next_feat"]))
        target = td_target(data["reward"], data["not_done"], next_q1, next_q2, c.discount)
        q1, q2 = ac.q(data["feat"], data["action"])
        critic_loss = twin_q_loss(q1, q2, target).mean()
        with frozen_parameters(ac.critic):
            actor_loss = deterministic_actor_loss(*ac.q(data["feat"], ac.actor.action(data["feat"]))).mean()
        self.actor_opt.zero_grad(set_to_none=True)
        self.critic_opt.zero_grad(set_to_none=True)
        (critic_loss + actor_loss).backward()
        metrics = {
            "actor/grad_norm": torch.nn.utils.clip_grad_norm_(ac.actor.parameters(), c.grad_clip),
            "critic/grad_norm": torch.nn.utils.clip_grad_norm_(ac.critic.parameters(), c.grad_clip),
        }
        self.actor_opt.step()
        self.critic_opt.step()
        ac.update_target(c.tau)
        metrics.update(
            {
                "actor/loss": actor_loss.detach(),
                "critic/loss": critic_loss.detach(),
                "critic/q": q1.detach().mean(),
                "critic/target": target.mean(),
                "lompo/real_reward": real["reward"].mean(),
                "lompo/imag_reward": seen["raw"].mean(),
                "lompo/spread": seen["spread"].mean(),
                "lompo/penalised_reward": imagined["reward"].mean(),
            }
        )
        return _to_floats(metrics)
