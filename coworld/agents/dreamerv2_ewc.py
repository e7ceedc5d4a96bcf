"""DreamerV2 fine-tuned from the source with elastic weight consolidation (Kirkpatrick et al., 2017): the later
CoWorld paper's "DV2 Finetune-EWC" baseline.

The run is ``dreamerv2-finetune``'s (:mod:`coworld.training.finetune`): the agent learns online in the
source for ``coworld.pretrain_steps`` environment steps, then offline on the target dataset for
``offline.updates`` updates. Between the two,
:func:`coworld.training.finetune.consolidate_on_source` calls :meth:`EwcDreamerV2.consolidate`, which takes
the source weights ``theta*`` and estimates the diagonal Fisher information ``F`` of each network's loss on
``ewc.fisher_batches`` batches of the source experience (:func:`coworld.losses.ewc.fisher_diagonal`); from then
on every update adds ``ewc.weight / 2 * sum_i F_i (theta_i - theta*_i)^2`` (:func:`coworld.losses.ewc.ewc_penalty`)
to the loss of the network that holds ``theta_i``:

* the world model's (encoder, RSSM, decoder, reward and discount heads), ``F`` from its loss on source sequences;
* the actor's and the critic's, ``F`` from their losses on trajectories imagined from those sequences' states.

So the agent may move where the source's fit does not care and is held where it does; with ``ewc.weight = 0`` it
is ``dreamerv2-finetune``. The anchor and ``F`` are part of the agent's state (its checkpoint).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from coworld.agents.dreamerv2 import DreamerV2
from coworld.losses.ewc import ewc_penalty, fisher_diagonal
from coworld.models.actor_critic import flatten_states
from coworld.models.networks import frozen_parameters

__all__ = ["NETWORKS", "EwcDreamerV2"]

NETWORKS = ("world_model", "actor", "critic")
"""The networks EWC holds, each with its own loss, anchor and Fisher."""


class EwcDreamerV2(DreamerV2):
    """DreamerV2 whose losses gain EWC's penalty once :meth:`consolidate` has run (reads ``config.ewc``)."""

    def _add_parts(self) -> None:
        """The EWC anchor and Fisher, empty until :meth:`consolidate`."""
        super()._add_parts()
        self.anchor: dict[str, dict[str, Tensor]] = {}
        """``network -> parameter name -> theta*``; empty until :meth:`consolidate`."""
        self.fisher: dict[str, dict[str, Tensor]] = {}
        """``network -> parameter name -> F``, as :attr:`anchor`."""

    def networks(self) -> dict[str, nn.Module]:
        return {
            "world_model": self.world_model,
            "actor": self.actor_critic.actor,
            "critic": self.actor_critic.critic,
        }

    @property
    def consolidated(self) -> bool:
        return bool(self.anchor)

    def consolidate(self, batches: Iterable[Mapping[str, np.ndarray | Tensor]]) -> dict[str, float]:
        """Take the current weights as ``theta*`` and estimate ``F`` of each network on ``batches`` (source
        sequences ``(B, T)``); no weight changes. Returns ``ewc/`` metrics: each network's mean ``F``."""
        ac = self.actor_critic
        buffers = {name: value.clone() for name, value in ac.named_buffers()}  # return_norm's statistics stay
        grads: dict[str, list[dict[str, Tensor]]] = {name: [] for name in NETWORKS}
        samples = 0
        for batch in batches:
            tensors = self.to_batch(batch)
            samples = int(np.prod(tensors["reward"].shape[:2]))
            self._zero_grad()
            with self._autocast():
                _, aux = self.model_path.loss(tensors)
            aux["loss"].backward()
            grads["world_model"].append(_grads(self.world_model))
            post = {key: value.detach() for key, value in aux["post"].items()}
            with frozen_parameters(self.world_model), self._autocast():
                terminal = tensors["is_terminal"].reshape(-1)
                traj = ac.imagine(self.world_model, flatten_states(post), is_terminal=terminal)
                terms, _ = ac.losses(self.world_model, traj)
            (terms["actor"] + terms["critic"]).backward()
            grads["actor"].append(_grads(ac.actor))
            grads["critic"].append(_grads(ac.critic))
        self._zero_grad()
        with torch.no_grad():
            for name, value in ac.named_buffers():
                value.copy_(buffers[name])
        self.fisher = {name: fisher_diagonal(grads[name], samples) for name in NETWORKS}
        self.anchor = {
            name: {key: p.detach().clone() for key, p in module.named_parameters()}
            for name, module in self.networks().items()
        }
        return {
            f"ewc/fisher_{name}": float(torch.cat([f.reshape(-1) for f in self.fisher[name].values()]).mean())
            for name in NETWORKS
        }

    def penalty(self, name: str) -> Tensor:
        """EWC's term of network ``name`` at its current weights (a scalar with gradient)."""
        params = dict(self.networks()[name].named_parameters())
        return ewc_penalty(params, self.anchor[name], self.fisher[name], self.config.ewc.weight).to(self.device)

    def train(self, batch: Mapping[str, np.ndarray | Tensor]) -> dict[str, float]:
        """DreamerV2's update, each network's loss plus its EWC term once consolidated."""
        if not self.consolidated:
            return super().train(batch)
        tensors = self.to_batch(batch)
        metrics, post = self.train_world_model(tensors, extra_loss=lambda _b, _a: {"ewc": self.penalty("world_model")})
        if self.updates >= self.config.train.actor_warmup:
            metrics.update(
                self.train_actor_critic(
                    post,
                    is_terminal=tensors["is_terminal"],
                    extra_loss=lambda: {"actor/ewc": self.penalty("actor"), "critic/ewc": self.penalty("critic")},
                )
            )
        self.updates += 1
        return metrics

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "ewc": {"anchor": self.anchor, "fisher": self.fisher}}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        super().load_state_dict(state)
        ewc = state["ewc"]
        device = self.device
        self.anchor = {n: {k: v.to(device) for k, v in p.items()} for n, p in ewc["anchor"].items()}
        self.fisher = {n: {k: v.to(device) for k, v in p.items()} for n, p in ewc["fisher"].items()}
        for name, params in self.anchor.items():
            own = dict(self.networks()[name].named_parameters())
            for key, value in params.items():
                if key not in own or own[key].shape != value.shape or self.fisher[name][key].shape != value.shape:
                    raise ValueError(f"the EWC anchor of {name}.{key} does not fit this agent")

    def _zero_grad(self) -> None:
        for module in self.networks().values():
            module.zero_grad(set_to_none=True)


def _grads(module: nn.Module) -> dict[str, Tensor]:
    """``name -> gradient`` of every parameter of ``module`` (zeros where it got none), detached copies."""
    return {
        name: (p.grad.detach().clone() if p.grad is not None else torch.zeros_like(p))
        for name, p in module.named_parameters()
    }
