"""DrQ+BC, V-D4RL's model-free baseline, trained offline on the same datasets as CoWorld.

DrQ+BC (Lu et al., 2022, "Challenges and Opportunities in Offline Reinforcement Learning from Visual
Observations") is DrQ-v2 (Yarats et al., 2021) with TD3+BC's behaviour-cloning term (Fujimoto & Gu, 2021) in
the actor loss. One update (:meth:`DrqBc.train`, V-D4RL ``drqbc/drqv2.py`` ``update``):

1. random-shift both frame stacks (pad ``drqbc.pad`` replicated pixels, crop back);
2. critic and encoder: squared errors of both Q-functions to ``r + gamma * (1 - done) * min(Q1', Q2')(s', a')``,
   ``a'`` the actor's mean plus clipped noise of the scheduled std; ``s'`` encoded by the online encoder without
   gradient and scored by the target critic;
3. actor on the detached conv features: ``- lambda * min(Q1, Q2)(s, a) + mse(a, a_data)``, ``lambda = alpha /
   mean|Q|`` (:mod:`coworld.losses.drqbc`);
4. Polyak averaging of the target critic (``drqbc.critic_tau``).

Networks: :class:`coworld.models.curl.Critic` (DrQ-v2's encoder, trunk and twin Q: the same layers as CURL's)
and :class:`coworld.models.drq.DrqActor`. Settings: :class:`coworld.config.DrqBcConfig`, V-D4RL's values.

Differences from V-D4RL's code, all deliberate: frames are 64 x 64 (V-D4RL's DrQ+BC reads its 84 x 84 datasets),
and the shift is :func:`coworld.models.curl.random_crop`'s integer shift (DrQ-v2's ``grid_sample`` shifts by
whole pixels too); TD targets are 1-step (V-D4RL's ``offline_dmc.yaml`` sets ``nstep: 1``; its README command
passes ``nstep=3``); conv inputs are scaled to ``[0, 1]`` (DrQ-v2: ``[-0.5, 0.5]``); one Adam optimiser trains
encoder and critic together (DrQ-v2 has two with the same learning rate, stepped on the same loss).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch
from torch import Tensor

from coworld.agents.curl import FrameStackAgent, polyak
from coworld.config import Config
from coworld.data.reader import Dataset
from coworld.data.transitions import TransitionSampler
from coworld.losses.curl import sac_critic_target, twin_q_loss
from coworld.losses.drqbc import actor_terms, clipped_noise_action, exploration_std
from coworld.models.curl import random_crop
from coworld.models.drq import DrqActor

__all__ = ["CHECKPOINT_KIND", "DrqBc", "make_sampler"]

CHECKPOINT_KIND = "drq-bc"


def make_sampler(dataset: Dataset, config: Config, seed: int) -> TransitionSampler:
    """A seeded transition sampler over ``dataset`` with ``drqbc.batch_size`` and ``drqbc.frame_stack``."""
    cfg = config.drqbc
    return TransitionSampler.from_dataset(dataset, batch_size=cfg.batch_size, frame_stack=cfg.frame_stack, seed=seed)


class DrqBc(FrameStackAgent):
    """DrQ+BC agent for offline training from pixels.

    API: :meth:`train` (one update from a :class:`~coworld.data.transitions.TransitionSampler` batch),
    :meth:`policy` (actions from single frames; the frame stacks are the state), :meth:`value`,
    :meth:`state_dict` / :meth:`load_state_dict` (``weights_only``-loadable).
    """

    name = "DrQ+BC"
    config_section = "drqbc"
    actor_class = DrqActor
    kind = CHECKPOINT_KIND

    def _add_parts(self) -> None:
        """One Adam optimiser for the critic (with the encoder), one for the actor; the target critic's conv trunk
        is unused (s' goes through the online one)."""
        self.optimizers = {
            "critic": torch.optim.Adam(self.critic.parameters(), lr=self.cfg.lr),
            "actor": torch.optim.Adam(self.actor.parameters(), lr=self.cfg.lr),
        }

    def std(self) -> float:
        """The exploration std at this update (:func:`coworld.losses.drqbc.exploration_std`)."""
        cfg = self.cfg
        return exploration_std(self.updates, init=cfg.std_init, final=cfg.std_final, duration=cfg.std_updates)

    # -- training ----------------------------------------------------------------------------------------------------
    def train(self, batch: Mapping[str, np.ndarray]) -> dict[str, float]:
        """One critic (and encoder) update, one actor update and the target update.

        ``batch``: ``obs (B, k*C, H, W) uint8``, ``action (B, A)``, ``reward (B,)``, ``next_obs``, ``not_done
        (B,)``. Returns ``critic/*``, ``actor/*`` and ``drqbc/std`` scalars.
        """
        cfg = self.cfg
        data = {key: torch.as_tensor(np.asarray(value), device=self.device) for key, value in batch.items()}
        action, reward, not_done = (data[key].float() for key in ("action", "reward", "not_done"))
        B = reward.shape[0]
        obs = random_crop(data["obs"], pad=cfg.pad, crop=self.image_shape[0])
        next_obs = random_crop(data["next_obs"], pad=cfg.pad, crop=self.image_shape[0])
        std = self.std()

        conv = self.critic.encoder.trunk(obs)
        with torch.no_grad():
            next_conv = self.critic.encoder.trunk(next_obs)
            next_action = clipped_noise_action(self.actor(next_conv), std, cfg.std_clip)
            next_q1, next_q2 = self.critic_target(self.critic_target.encoder.head(next_conv), next_action)
            target = sac_critic_target(reward, not_done, next_q1, next_q2, torch.zeros_like(reward), 0.0, cfg.discount)
        q1, q2 = self.critic(self.critic.encoder.head(conv), action)
        critic_loss = twin_q_loss(q1, q2, target).mean()
        self.optimizers["critic"].zero_grad(set_to_none=True)
        critic_loss.backward()
        self.optimizers["critic"].step()

        conv = conv.detach()
        pi = clipped_noise_action(self.actor(conv), std, cfg.std_clip)
        with torch.no_grad():
            features = self.critic.encoder.head(conv)
        pi_q1, pi_q2 = self.critic(features, pi)
        terms = actor_terms(torch.minimum(pi_q1, pi_q2), pi, action, cfg.bc_weight)
        assert terms["rl"].shape == terms["bc"].shape == (B,)
        actor_loss = (terms["rl"] + terms["bc"]).mean()
        self.optimizers["actor"].zero_grad(set_to_none=True)
        actor_loss.backward()
        self.optimizers["actor"].step()

        polyak(self.critic_target.encoder.head, self.critic.encoder.head, cfg.critic_tau)
        polyak(self.critic_target.q1, self.critic.q1, cfg.critic_tau)
        polyak(self.critic_target.q2, self.critic.q2, cfg.critic_tau)
        self.updates += 1
        values = {
            "critic/loss": critic_loss,
            "critic/q": q1.mean(),
            "critic/target": target.mean(),
            "actor/loss": actor_loss,
            "actor/bc": terms["bc"].mean(),
            "actor/lambda": terms["lambda"],
            "drqbc/std": torch.tensor(std),
        }
        return {key: float(value.detach()) for key, value in values.items()}

    # -- acting ------------------------------------------------------------------------------------------------------
    def eval_action(self, conv: Tensor) -> Tensor:
        """The actor's mean action."""
        return self.actor(conv)

    def train_action(self, conv: Tensor) -> Tensor:
        """The mean action plus the clipped noise of the current std."""
        return clipped_noise_action(self.actor(conv), self.std(), self.cfg.std_clip)
