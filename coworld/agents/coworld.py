"""CoWorld's two agents and their update steps (the schedule that runs them, Alg. 1: :mod:`coworld.training.coworld`).

Both agents are DreamerV2 (:class:`coworld.agents.dreamerv2.DreamerV2`). The three domain-collaborative terms
(:mod:`coworld.losses.coworld`) enter through the DreamerV2 update's hooks:

* target world-model step (Alg. 1 line 9, Eq. 3): ``+ beta2 * KL[sg(e_S(o_T)) || e_T(o_T)]`` on the target
  batch (:func:`alignment_term`), the source model run over the same target frames without gradient. The source
  model does not change during a target phase, so :class:`TargetBatches` makes that pass with the batch, ahead on
  the prefetch thread where ``train.prefetch`` is on;
* target critic step (lines 10-11, Eq. 6): the critic's loss is :func:`regularised_critic_loss` on the target
  agent's imagined states, ``v_S`` being the source critic fed the target features;
* source world-model step (lines 17-20, Eqs. 4-5): the source model is also run over a target batch and its
  reward head regresses ``k * sg(r_S_pred) + (1 - k) * r_T``.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np
import torch
from torch import Tensor

from coworld.agents.dreamerv2 import DreamerV2
from coworld.config import Config
from coworld.losses.coworld import (
    alignment_term,
    max_min_active,
    regularised_critic_loss,
    relabel_reward,
    source_reward_loss_on_target,
    value_regulariser,
)

ALIGN_SOURCE = "align_source"
"""The key of a target batch's :meth:`CoWorld.source_alignment`, where :class:`TargetBatches` made it."""


def source_model_action_size(source: int, target: int) -> int:
    """The width of the source world model's action input: the wider of the two action spaces.

    Only the source world model reads the other domain's actions (its posterior over target sequences, for Eq. 3's
    source side and Eqs. 4-5's relabelled reward); the target agent never reads source actions, and the critics
    read features, whose size does not depend on the action space. Each action is zero-padded at the end to this
    width (:func:`coworld.models.rssm.pad_action`), so nothing of either space is dropped.
    """
    return max(source, target)


class CoWorld:
    """The two agents and CoWorld's update steps.

    Args:
        config: resolved config; ``config.coworld`` holds the CoWorld terms and their switches.
        action_size: the target task's action size (the target agent's actor and world model).
        source_action_size: the source task's (the source actor's); None: the target's. Where the two differ, the
            source world model's action input is the wider of them (:func:`source_model_action_size`), so it reads
            its own sequences and the target's, each zero-padded to that width.
    """

    def __init__(
        self,
        *,
        config: Config,
        action_size: int,
        device: torch.device | str,
        source_action_size: int | None = None,
    ) -> None:
        self.config = config
        source_action_size = action_size if source_action_size is None else source_action_size
        self.source = DreamerV2(
            config=config,
            action_size=source_action_size,
            device=device,
            model_action_size=source_model_action_size(source_action_size, action_size),
        )
        self.target = DreamerV2(config=config, action_size=action_size, device=device)
        self.device = self.target.device
        self.target_batches: Iterator[dict[str, Any]] | None = None
        """Target-dataset batches for the source agent's relabelled-reward term (set by the schedule)."""

    # -- the target agent's update (Alg. 1 lines 7-11) ------------------------------------------------------------
    def train_target(self, batch: Mapping[str, Any]) -> dict[str, float]:
        """One target world-model step with Eq. 3 and one target actor-critic step with Eq. 6 (the latter, as in
        :meth:`DreamerV2.train`, only once the target agent has made ``train.actor_warmup`` updates)."""
        cfg = self.config.coworld
        batch_t = self.target.prepare(batch)  # laid out once for both world models
        extra = None
        if cfg.align:
            source = batch_t.get(ALIGN_SOURCE)
            if source is None:
                source = self.source_alignment(batch_t)

            def extra(_: dict[str, Tensor], aux: dict[str, Any]) -> dict[str, Tensor]:
                target = aux["post"]["logits"] if cfg.align_on == "latent" else aux["embed"]
                return {"align": cfg.beta2 * alignment_term(source, target, cfg.align_on)}

        metrics, post = self.target.train_world_model(batch_t, extra)
        if cfg.align:
            metrics["coworld/align_kl"] = metrics.pop("wm/align") / cfg.beta2
        objective = self._capped_critic_objective() if cfg.value_reg else None
        if self.target.updates >= self.config.train.actor_warmup:  # as DreamerV2.train: the world model alone first
            metrics.update(self.target.train_actor_critic(post, objective, is_terminal=batch_t["is_terminal"]))
        self.target.updates += 1
        return {f"target/{key}": value for key, value in metrics.items()}

    def _capped_critic_objective(self) -> Any:
        """The target critic's loss, Eq. 6 (:func:`regularised_critic_loss`), capped by the source critic, and what
        it logs: the two critics' mean values and the share of states where the max-min term binds."""
        cfg = self.config.coworld
        source_critic = self.source.actor_critic.critic

        def objective(feat: Tensor, value: Any, target: Tensor, weight: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
            with torch.no_grad():
                source_value = source_critic(feat).mean
            loss = regularised_critic_loss(value, target, weight, source_value, cfg.alpha, cfg.zeta)
            with torch.no_grad():
                mean = value.mean.detach()
                metrics = {
                    "critic/regulariser": (cfg.alpha * value_regulariser(mean, source_value, cfg.zeta)).mean(),
                    "coworld/target_value": mean.mean(),
                    "coworld/source_value": source_value.mean(),
                    "coworld/maxmin_active": max_min_active(mean, source_value, cfg.zeta).float().mean(),
                }
            return loss, metrics

        return objective

    def source_alignment(self, batch: Mapping[str, Tensor], generator: torch.Generator | None = None) -> Tensor:
        """What Eq. 3 aligns the target model to on a :meth:`DreamerV2.prepare`-d target batch, from the source
        model without gradient: its posterior's log-probabilities ``(B, T, S, K)`` (``align_on='latent'``; the
        latent samples' noise drawn from ``generator``, torch's default if None) or its embeddings ``(B, T, E)``
        (``'embedding'``)."""
        path = self.source.model_path
        with torch.no_grad():
            if self.config.coworld.align_on == "embedding":
                return path.embed(batch)
            post, _, _ = path.observe(batch, generator=generator)
            return post["logits"]

    # -- the source agent's update (Alg. 1 lines 16-21) -----------------------------------------------------------
    def train_source(self, batch: Mapping[str, np.ndarray]) -> dict[str, float]:
        """One source world-model step (with Eqs. 4-5 on a target batch) and one source actor-critic step (once the
        source agent has made ``train.actor_warmup`` updates, pretraining included)."""
        cfg = self.config.coworld
        extra = None
        if cfg.reward_relabel and self.target_batches is not None:
            target_batch = self.source.to_batch(next(self.target_batches))

            def extra(_: dict[str, Tensor], __: dict[str, Any]) -> dict[str, Tensor]:
                post, _, _ = self.source.model_path.observe(target_batch)
                head = self.source.world_model.reward_head(self.source.world_model.features(post))
                label = relabel_reward(head.mean, target_batch["reward"].float(), cfg.k)
                return {"relabel": source_reward_loss_on_target(head, label).mean()}

        batch_t = self.source.to_batch(batch)
        metrics, post = self.source.train_world_model(batch_t, extra)
        if "wm/relabel" in metrics:
            metrics["coworld/relabel_reward_loss"] = metrics.pop("wm/relabel")
        if self.source.updates >= self.config.train.actor_warmup:
            metrics.update(self.source.train_actor_critic(post, is_terminal=batch_t["is_terminal"]))
        self.source.updates += 1
        return {f"source/{key}": value for key, value in metrics.items()}

    # -- acting (the target agent acts in the target domain) --------------------------------------------------------
    def policy(self, obs: np.ndarray, state: Any = None, mode: str = "eval", is_first: np.ndarray | None = None):
        return self.target.policy(obs, state, mode, is_first=is_first)

    def value(self, state: Any) -> np.ndarray:
        return self.target.value(state)

    def state_dict(self) -> dict[str, Any]:
        return {"target": self.target.state_dict(), "source": self.source.state_dict()}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.target.load_state_dict(state["target"])
        self.source.load_state_dict(state["source"])


class TargetBatches:
    """The target dataset's batches as CoWorld's updates read them (a ``prepare`` for
    :class:`~coworld.data.prefetch.Prefetcher`): each :meth:`DreamerV2.prepare`-d by the target agent, and the first
    ``aligned`` with their :meth:`CoWorld.source_alignment` under :data:`ALIGN_SOURCE` (where ``coworld.align`` is on).

    A target phase's batches can carry the source model's pass because the source model does not change until
    the phase ends (its ``aligned`` batches are the phase's own); made ahead, the pass runs on the prefetch
    thread while the target update before runs. Its latent samples draw from a generator of their own, seeded
    with ``seed``, so a run makes the same passes with prefetching on or off, and a resumed phase those of an
    uninterrupted one.
    """

    def __init__(self, coworld: CoWorld, *, aligned: int, seed: int) -> None:
        self.coworld = coworld
        self.aligned = aligned if coworld.config.coworld.align else 0
        self.generator = torch.Generator(coworld.device).manual_seed(seed)

    def __call__(self, batch: Mapping[str, np.ndarray]) -> dict[str, Tensor]:
        batch_t = self.coworld.target.prepare(batch)
        if self.aligned > 0:
            self.aligned -= 1
            batch_t = {**batch_t, ALIGN_SOURCE: self.coworld.source_alignment(batch_t, self.generator)}
        return batch_t


class SourceLearner:
    """What the online trainer drives in CoWorld's source phases: the source policy, CoWorld's source update, the
    source agent's state."""

    def __init__(self, coworld: CoWorld) -> None:
        self.coworld = coworld
        self.device = coworld.device

    def policy(self, *args: Any, **kwargs: Any) -> Any:
        return self.coworld.source.policy(*args, **kwargs)

    def policy_copy(self) -> Any:
        return self.coworld.source.policy_copy()

    def value(self, state: Any) -> np.ndarray:
        return self.coworld.source.value(state)

    def train(self, batch: Mapping[str, np.ndarray]) -> dict[str, float]:
        # the online trainer adds its own "source/" prefix (to these and to its eval/ and perf/ metrics)
        return {key.removeprefix("source/"): value for key, value in self.coworld.train_source(batch).items()}

    def state_dict(self) -> dict[str, Any]:
        return self.coworld.source.state_dict()

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.coworld.source.load_state_dict(state)
