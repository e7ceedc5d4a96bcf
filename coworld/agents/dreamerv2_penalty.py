"""V-D4RL's offline DreamerV2: DreamerV2 whose imagined rewards are penalised by the disagreement of an ensemble
of dynamics heads (Lu et al., 2022, Sec. 4; ``offlinedv2`` of github.com/conglu1997/v-d4rl).

The agent is :class:`coworld.agents.dreamerv2.DreamerV2` plus :class:`coworld.models.ensemble.DynamicsEnsemble`
(``penalty.ensemble`` heads ``h -> z`` logits) and V-D4RL's two phases, counted in updates of one run:

* the first ``penalty.model_updates`` updates train the world model and the heads (each head on the steps drawn
  for it, :func:`coworld.losses.penalty.head_loss`), not the actor-critic;
* every later update trains the actor-critic alone, on states observed by the frozen world model, with the
  imagined reward ``r - penalty.weight * u(h)`` (:func:`coworld.losses.penalty.mean_disagreement`), passed in
  through :meth:`DreamerV2.train_actor_critic`'s ``imagined_reward`` hook.

Difference from V-D4RL, deliberate: V-D4RL's heads *are* the prior (each RSSM step uses one drawn at random); here
they sit beside DreamerV2's own prior, read ``h`` without gradient and learn the same target, so the world model
is DreamerV2's unchanged and the penalty measures the same thing, the heads' spread where the data is thin.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from torch import Tensor

from coworld.agents.dreamerv2 import DreamerV2, make_optimizer
from coworld.losses.penalty import head_loss, mean_disagreement, penalised_reward
from coworld.models.ensemble import DynamicsEnsemble
from coworld.models.rssm import State

__all__ = ["PenaltyDreamerV2"]


class PenaltyDreamerV2(DreamerV2):
    """DreamerV2 with V-D4RL's ensemble-disagreement reward penalty (reads ``config.penalty``)."""

    section = "penalty"
    """The config section with ``ensemble`` and ``model_updates`` (LOMPO's agent, a subclass, reads ``lompo``)."""

    def _add_parts(self) -> None:
        """The ensemble of dynamics heads and its optimiser."""
        super()._add_parts()
        wm, size = self.config.world_model, getattr(self.config, self.section).ensemble
        self.ensemble = DynamicsEnsemble(
            size=size, deter=wm.deter, hidden=wm.hidden, stoch=wm.stoch, classes=wm.classes
        ).to(self.device)
        self.ensemble_opt = make_optimizer(self.ensemble.parameters(), lr=wm.lr, eps=wm.eps, decay=wm.weight_decay)

    @property
    def model_phase(self) -> bool:
        """Whether the next update trains the world model (True) or the actor-critic (False)."""
        return self.updates < getattr(self.config, self.section).model_updates

    def train(self, batch: Mapping[str, np.ndarray | Tensor]) -> dict[str, float]:
        """One update of the current phase: world model and heads, or the policy alone (:meth:`train_policy`) on
        the states the frozen world model observes in the batch."""
        tensors = self.to_batch(batch)
        if self.model_phase:
            metrics, post = self.train_world_model(tensors)
            metrics.update(self.train_ensemble(post))
        else:
            with torch.no_grad(), self._autocast():
                post, _, _ = self.model_path.observe(tensors, priors=False)
            metrics = self.train_policy({key: value.detach() for key, value in post.items()}, tensors)
        self.updates += 1
        return metrics

    def train_policy(self, post: State, batch: Mapping[str, Tensor]) -> dict[str, float]:
        """The actor-critic's step in imagination from posterior states ``(B, T)`` of ``batch``, on the penalised
        reward."""
        seen: dict[str, Tensor] = {}

        def reward(traj: dict[str, Any]) -> Tensor:
            with torch.no_grad():
                disagreement = mean_disagreement(self.ensemble(traj["state"]["deter"]))
            seen.update(disagreement=disagreement.mean(), raw=traj["reward"].detach().mean())
            return penalised_reward(traj["reward"], disagreement, self.config.penalty.weight)

        metrics = self.train_actor_critic(post, is_terminal=batch["is_terminal"], imagined_reward=reward)
        metrics.update({f"penalty/{key}": float(value) for key, value in seen.items()})
        return metrics

    def train_ensemble(self, post: State) -> dict[str, float]:
        """One step of the heads on posterior states ``(B, T)``: each step trains one head drawn uniformly."""
        logits = self.ensemble(post["deter"])  # (K, B, T, S, C)
        k = logits.shape[0]
        drawn = torch.randint(k, post["deter"].shape[:-1], device=self.device)
        mask = torch.nn.functional.one_hot(drawn, k).movedim(-1, 0)  # (K, B, T)
        loss = head_loss(post["logits"], logits, mask).sum(dim=0).mean()
        self.ensemble_opt.zero_grad(set_to_none=True)
        loss.backward()
        self.ensemble_opt.step()
        with torch.no_grad():
            spread = mean_disagreement(logits).mean()
        return {"penalty/head_kl": float(loss.detach()), "penalty/data_disagreement": float(spread)}

    def state_dict(self) -> dict[str, Any]:
        return {
            **super().state_dict(),
            "ensemble": self.ensemble.state_dict(),
            "ensemble_opt": self.ensemble_opt.state_dict(),
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        super().load_state_dict(state)
        self.ensemble.load_state_dict(state["ensemble"])
        self.ensemble_opt.load_state_dict(state["ensemble_opt"])
