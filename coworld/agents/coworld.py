"""CoWorld's two agents and their update steps (the schedule that runs them, Alg. 1: :mod:`coworld.training.coworld`).

Both agents are DreamerV2 (:class:`coworld.agents.dreamerv2.DreamerV2`). The three domain-collaborative terms
(:mod:`coworld.losses.coworld`) enter through the DreamerV2 update's hooks:

* target world-model step (Alg. 1 line 9, Eq. 3): ``+ beta2 * KL[sg(e_S(o_T)) || e_T(o_T)]`` on the target
  batch (:func:`alignment_term`), the source model run over the same target frames without gradient. The source
  model does not change during a target phase, so :class:`TargetBatches` makes that pass with the batch, ahead on
  the prefetch thread where ``train.prefetch`` is on;
* target critic step (lines 10-11, Eq. 6): the critic's loss is :func:`regularised_critic_loss` on the target
  agent's imagined states, ``v_S`` being the source critic fed the target features (with
  ``coworld.cap_critic='target_policy'``, a critic of the target actor in the source world model instead:
  :class:`~coworld.agents.policy_value.PolicyValue`);
* source world-model step (lines 17-20, Eqs. 4-5): the source model is also run over the target batch the schedule
  passes with the source batch, and its reward head regresses Eq. 4's relabelled reward (:func:`relabel_reward`),
  the two batches' terms joined as ``coworld.reward_mix`` says (:func:`reward_mix_eta`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from torch import Tensor

from coworld.agents.dreamerv2 import DreamerV2
from coworld.agents.policy_value import PolicyValue
from coworld.config import Config
from coworld.errors import ConfigError
from coworld.losses.coworld import (
    alignment_term,
    max_min_active,
    regularised_critic_loss,
    relabel_reward,
    reward_mix_eta,
    source_reward_loss_on_target,
    value_regulariser,
)
from coworld.losses.dreamer import reward_loss

ALIGN_ON = ("latent", "embedding")
ALIGN_SOURCE = "align_source"
"""The key of a target batch's :meth:`CoWorld.source_alignment`, where :class:`TargetBatches` made it."""
PROBE_ZETAS = (2.0, 3.0, 5.0, 10.0)
"""The ``zeta`` at which each target update also measures where Eq. 6's term would bind (without effect)."""


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
        if config.coworld.align_on not in ALIGN_ON:  # a config built by hand, past make_config's check
            raise ConfigError(f"coworld.align_on must be one of {', '.join(ALIGN_ON)}, not {config.coworld.align_on!r}")
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
        self.policy_value: PolicyValue | None = None
        """The target-policy critic that caps the target critic where ``coworld.cap_critic='target_policy'``."""
        if config.coworld.cap_critic == "target_policy":
            with torch.random.fork_rng(devices=[]):  # drawn off the record: both agents train as they would without
                torch.manual_seed(config.seed)
                feat_size = self.source.world_model.feat_size
                self.policy_value = PolicyValue(
                    config=config, feat_size=feat_size, action_size=action_size, device=self.device
                )
        self.relabelled = 0
        """Source updates made with a target batch (Eqs. 4-5) so far: what Eq. 5's ``eta`` follows (a CoWorld
        checkpoint holds it)."""

    # -- the target agent's update (Alg. 1 lines 7-11) ------------------------------------------------------------
    def train_target(self, batch: Mapping[str, Any]) -> dict[str, float]:
        """One target world-model step with Eq. 3 and one target actor-critic step with Eq. 6 (the latter, as in
        :meth:`DreamerV2.train`, only once the target agent has made ``train.actor_warmup`` updates)."""
        cfg = self.config.coworld
        target_tensors = self.target.prepare(batch)  # laid out once for both world models
        extra = None
        if cfg.align:
            source = target_tensors.get(ALIGN_SOURCE)
            if source is None:
                source = self.source_alignment(target_tensors)

            def extra(_: dict[str, Tensor], aux: dict[str, Any]) -> dict[str, Tensor]:
                target = aux["post"]["logits"] if cfg.align_on == "latent" else aux["embed"]
                return {"align": cfg.beta2 * alignment_term(source, target, cfg.align_on)}

        metrics, post = self.target.train_world_model(target_tensors, extra)
        if cfg.align:
            metrics["coworld/align_kl"] = metrics.pop("wm/align") / cfg.beta2
        objective = self._capped_critic_objective() if cfg.value_reg else None
        if self.target.updates >= self.config.train.actor_warmup:  # as DreamerV2.train: the world model alone first
            metrics.update(self.target.train_actor_critic(post, objective, is_terminal=target_tensors["is_terminal"]))
        self.target.updates += 1
        return {f"target/{key}": value for key, value in metrics.items()}

    @property
    def cap_critic(self) -> Any:
        """The critic Eq. 6 caps the target critic with (``coworld.cap_critic``)."""
        return self.source.actor_critic.critic if self.policy_value is None else self.policy_value.critic

    def _capped_critic_objective(self) -> Any:
        """The target critic's loss, Eq. 6 (:func:`regularised_critic_loss`), capped by :attr:`cap_critic`, and what
        it logs: the two critics' mean values, the share of states where the max-min term binds, and where it would
        bind at each of :data:`PROBE_ZETAS`."""
        cfg = self.config.coworld
        source_critic = self.cap_critic

        def objective(feat: Tensor, value: Any, target: Tensor, weight: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
            with torch.no_grad():
                source_value = source_critic(feat).mean
            loss = regularised_critic_loss(value, target, weight, source_value, cfg.alpha, cfg.zeta, cfg.cap_form)
            with torch.no_grad():
                mean = value.mean.detach()
                metrics = {
                    "critic/regulariser": (cfg.alpha * value_regulariser(mean, source_value, cfg.zeta)).mean(),
                    "coworld/target_value": mean.mean(),
                    "coworld/source_value": source_value.mean(),
                    "coworld/maxmin_active": max_min_active(mean, source_value, cfg.zeta).float().mean(),
                }
                for zeta in PROBE_ZETAS:
                    metrics[f"coworld/binds_zeta_{zeta:g}"] = max_min_active(mean, source_value, zeta).float().mean()
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
            post, _, _ = path.observe(batch, generator=generator, priors=False)
            return post["logits"]

    # -- the source agent's update (Alg. 1 lines 17-21) -----------------------------------------------------------
    def train_source(
        self, batch: Mapping[str, np.ndarray], target_batch: Mapping[str, Any] | None = None
    ) -> dict[str, float]:
        """One source world-model step on a source batch ``(B, T, ...)``, with Eqs. 4-5 on ``target_batch`` (a target
        dataset batch, :class:`TargetBatches`' or as the dataset gives it; None: none, as while the source agent
        pretrains, or where ``coworld.reward_relabel`` is off), and one source actor-critic step (once the source
        agent has made ``train.actor_warmup`` updates, pretraining included). Its metrics are named as
        :meth:`DreamerV2.train` names them; the source agent's online trainer logs them under ``source/``."""
        cfg = self.config.coworld
        extra, seen = None, {}
        if cfg.reward_relabel and target_batch is not None:
            target_batch = self.source.to_batch(target_batch)

            def extra(source_batch: dict[str, Tensor], aux: dict[str, Any]) -> dict[str, Tensor]:
                post, _, _ = self.source.model_path.observe(target_batch, priors=False)
                head = self.source.world_model.reward_head(self.source.world_model.features(post))
                label = relabel_reward(head.mean, target_batch["reward"].float(), cfg.k, cfg.relabel)
                seen["relabel"] = target_term = source_reward_loss_on_target(head, label).mean()
                if cfg.reward_mix == "sum":  # the paper text: L_S + L_T
                    return {"relabel": target_term}
                # eta * L_S + (1 - eta) * L_T at the reward scale: the world model's loss holds scale * L_S already
                total = cfg.iterations * cfg.source_updates
                seen["eta"] = eta = reward_mix_eta(self.relabelled, total, cfg.eta_start, cfg.eta_end)
                scale = self.config.world_model.reward_scale
                source_term = reward_loss(aux["reward_head"], source_batch["reward"].float()).mean()
                return {"relabel": (1.0 - eta) * scale * target_term, "eta_mix": (eta - 1.0) * scale * source_term}

        source_tensors = self.source.to_batch(batch)
        metrics, post = self.source.train_world_model(source_tensors, extra)
        if seen:
            metrics.pop("wm/relabel")
            metrics.pop("wm/eta_mix", None)
            metrics["coworld/relabel_reward_loss"] = float(seen["relabel"].detach())
            if "eta" in seen:
                metrics["coworld/eta"] = seen["eta"]
            self.relabelled += 1
        if self.source.updates >= self.config.train.actor_warmup:
            metrics.update(self.source.train_actor_critic(post, is_terminal=source_tensors["is_terminal"]))
            if self.policy_value is not None:
                metrics.update(
                    self.policy_value.train(
                        self.source.world_model,
                        self.target.actor_critic.actor,
                        post,
                        is_terminal=source_tensors["is_terminal"],
                        step=self.source.updates,
                    )
                )
        self.source.updates += 1
        return metrics

    # -- acting (the target agent acts in the target domain) --------------------------------------------------------
    def policy(self, obs: np.ndarray, state: Any = None, mode: str = "eval", is_first: np.ndarray | None = None):
        return self.target.policy(obs, state, mode, is_first=is_first)

    def value(self, state: Any) -> np.ndarray:
        return self.target.value(state)

    def predicted_reward(self, state: Any) -> np.ndarray:
        return self.target.predicted_reward(state)

    def source_value(self, state: Any) -> np.ndarray:
        """:attr:`cap_critic`'s estimate ``(N,)`` for the target agent's latent states (``state`` from
        :meth:`policy`): what Eq. 6's cap says the target agent's states are worth (the value check's third line)."""
        latent, _ = state
        with torch.no_grad():
            value = self.cap_critic(self.target.world_model.features(latent)).mean
        return value.float().cpu().numpy()

    def state_dict(self) -> dict[str, Any]:
        state = {"target": self.target.state_dict(), "source": self.source.state_dict()}
        if self.policy_value is not None:
            state["policy_value"] = self.policy_value.state_dict()
        return state

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.target.load_state_dict(state["target"])
        self.source.load_state_dict(state["source"])
        if self.policy_value is not None:
            self.policy_value.load_state_dict(state["policy_value"])


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
        tensors = self.coworld.target.prepare(batch)
        if self.aligned > 0:
            self.aligned -= 1
            tensors = {**tensors, ALIGN_SOURCE: self.coworld.source_alignment(tensors, self.generator)}
        return tensors
