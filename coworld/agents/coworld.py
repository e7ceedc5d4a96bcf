"""CoWorld: an online source agent and an offline target agent that learn together (paper Alg. 1).

Both agents are DreamerV2 (:class:`coworld.agents.dreamerv2.DreamerV2`). The three domain-collaborative terms
(:mod:`coworld.losses.coworld`) enter through the DreamerV2 update's hooks:

* target world-model step (Alg. 1 line 9, Eq. 3): ``+ beta2 * KL[sg(e_S(o_T)) || e_T(o_T)]`` on the target
  batch, the source model run over the same target frames without gradient (``align_on='latent'``: the
  posteriors' KL averaged over batch and time; ``'embedding'``: the release's softmaxed conv embeddings,
  summed over time and averaged over the batch as its ``KLDivLoss(reduction="batchmean")`` does). The source
  model does not change during a target phase, so :class:`TargetBatches` makes that pass with the batch, ahead
  on the prefetch thread where ``train.prefetch`` is on;
* target critic step (line 10, Eq. 6): ``+ alpha * max(zeta * v_T(z), sg(v_S(z)))`` on the target agent's
  imagined states, ``v_S`` being the source critic fed the target features;
* source world-model step (lines 13-15, Eqs. 4-5): the source model is also run over a target batch and its
  reward head regresses ``k * sg(r_S_pred) + (1 - k) * r_T``.

Schedule: pretrain the source agent online for ``coworld.pretrain_steps`` environment steps, then
``coworld.iterations`` times: ``target_updates`` (K1) target updates on dataset batches, then
``source_updates`` (K2) source updates interleaved with source environment steps at the train ratio. The
source episodes run on across phase boundaries (the pretraining cut and the pauses leave no mark in the
source replay).
A checkpoint is written after every phase; a killed run resumes from the last one. Each iteration draws its
target batches from one stream, a sampler seeded by (seed, iteration): the target phase takes the first K1, the
source phase's relabelling the next ones, so a resumed run sees the batches an uninterrupted one would have (a
run resumed in the source phase skips the target phase's K1 first).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from coworld import interrupt
from coworld.agents.dreamerv2 import DreamerV2
from coworld.config import Config, to_dict
from coworld.data import open_dataset
from coworld.data.prefetch import Prefetcher, stop_prefetch
from coworld.envs import task_spec
from coworld.losses.coworld import (
    alignment_loss,
    embedding_alignment_loss,
    max_min_active,
    relabel_reward,
    source_reward_loss_on_target,
    value_regulariser,
)
from coworld.progress import progress_bar
from coworld.training.checkpoint import CHECKPOINT_NAME, load_checkpoint, rng_state, save_checkpoint, set_rng_state
from coworld.training.evaluate import evaluate
from coworld.training.logger import Logger, Rate
from coworld.training.online import OnlineTrainer, make_source_trainer, source_replay_writer
from coworld.training.openloop import log_open_loop
from coworld.training.train import parse_sources

CHECKPOINT_KIND = "coworld"
COWORLD_CHECKPOINT_KEYS = ("agent", "source", "source_updates", "progress", "rng")
"""What a CoWorld checkpoint holds beyond its kind (``save`` in :func:`train_coworld`)."""
UNBOUNDED = 2**62  # source phases end by pausing after K2 updates, never by a step limit
ALIGN_ON = ("latent", "embedding")
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
        if config.coworld.align_on not in ALIGN_ON:
            from coworld.errors import ConfigError

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
        self.target_batches: Iterator[dict[str, np.ndarray]] | None = None
        """Target-dataset batches for the source agent's relabelled-reward term (set by the schedule)."""

    # -- the target agent's update (Alg. 1 lines 8-10) ------------------------------------------------------------
    def train_target(self, batch: Mapping[str, np.ndarray]) -> dict[str, float]:
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
                if cfg.align_on == "latent":
                    # averaged over (B, T) like every other DreamerV2 world-model term
                    term = alignment_loss(source, aux["post"]["logits"]).mean()
                else:
                    # the release's KLDivLoss(reduction="batchmean") on (B, T, E): summed over T, divided by B
                    term = embedding_alignment_loss(source, aux["embed"]).sum(dim=1).mean()
                return {"align": cfg.beta2 * term}

        metrics, post = self.target.train_world_model(batch_t, extra)
        if cfg.align:
            metrics["coworld/align_kl"] = metrics.pop("wm/align") / cfg.beta2

        regulariser = None
        seen: dict[str, Tensor] = {}
        if cfg.value_reg:
            source_critic = self.source.actor_critic.critic

            def regulariser(feat: Tensor, value: Tensor) -> Tensor:
                with torch.no_grad():
                    source_value = source_critic(feat).mean
                seen.update(
                    target=value.detach().mean(),
                    source=source_value.mean(),
                    active=max_min_active(value.detach(), source_value, cfg.zeta).float().mean(),
                )
                return cfg.alpha * value_regulariser(value, source_value, cfg.zeta)

        if self.target.updates >= self.config.train.actor_warmup:  # as DreamerV2.train: the world model alone first
            metrics.update(self.target.train_actor_critic(post, regulariser, is_terminal=batch_t["is_terminal"]))
        if seen:
            metrics.update({f"coworld/{key}_value": float(seen[key]) for key in ("target", "source")})
            metrics["coworld/maxmin_active"] = float(seen["active"])
        self.target.updates += 1
        return {f"target/{key}": value for key, value in metrics.items()}

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

    # -- the source agent's update (Alg. 1 lines 12-16) -----------------------------------------------------------
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
    """The target dataset's batches as CoWorld's updates read them (a ``prepare`` for :class:`Prefetcher`):
    each :meth:`DreamerV2.prepare`-d by the target agent, and the first ``aligned`` with their
    :meth:`CoWorld.source_alignment` under :data:`ALIGN_SOURCE` (where ``coworld.align`` is on).

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


class _SourceLearner:
    """What the online trainer drives in the source phases: the source policy, CoWorld's source update."""

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


def _show(bar: Any, state: Mapping[str, Any], iterations: int) -> None:
    """The progress bar's postfix: iteration, phase and the last evaluation return."""
    postfix = {"iteration": f"{int(state['iteration']) + 1}/{iterations}", "phase": state["phase"]}
    if state["last_eval"] is not None:
        postfix["eval_return"] = f"{state['last_eval']:.1f}"
    bar.set_postfix(postfix)


def train_coworld(job: Any, *, device: torch.device, resumed: bool, progress: bool = True) -> dict[str, Any]:
    """Run Algorithm 1 for a checked :class:`coworld.training.train.TrainJob`; resumes its run folder."""
    config: Config = job.config
    cfg = config.coworld
    logdir = Path(job.logdir)
    spec = task_spec(job.target)
    dataset = open_dataset(job.dataset)
    warm_target = None
    candidates = parse_sources(str(job.source))
    if len(candidates) > 1:  # several sources: choose one first, then Algorithm 1 with it (coworld.agents.choice)
        import dataclasses

        from coworld.agents.choice import choose_source

        try:
            choice, warm_target = choose_source(job, candidates, dataset=dataset, device=device, progress=progress)
        except BaseException:
            dataset.close()
            raise
        job = dataclasses.replace(job, source=choice.chosen)
    agent = CoWorld(
        config=config,
        action_size=spec.action_size,
        source_action_size=task_spec(job.source).action_size,
        device=device,
    )
    ckpt_path = logdir / CHECKPOINT_NAME
    progress_state = {"iteration": 0, "phase": "pretrain", "last_eval": None}

    writer = source_replay_writer(logdir, job.source, algorithm="coworld", seed=config.seed)
    with Logger(logdir) as logger, writer:
        source_trainer = make_source_trainer(
            _SourceLearner(agent), job.source, config=config, logdir=logdir, writer=writer, logger=logger
        )
        # restore: the combined checkpoint once past pretraining, else the pretraining checkpoint
        source_trainer.restore()
        if ckpt_path.exists():
            state = load_checkpoint(ckpt_path, map_location=device, keys=COWORLD_CHECKPOINT_KEYS)
            if state.get("kind") != CHECKPOINT_KIND:
                from coworld.errors import CheckpointError

                raise CheckpointError(f"{ckpt_path} is a {state.get('kind')!r} checkpoint, not a coworld one")
            agent.target.load_state_dict(state["agent"])
            agent.source.load_state_dict(state["source"])
            source_trainer.updates = int(state["source_updates"])
            if "source_act_rng" in state:
                source_trainer.act_rng.set_state(state["source_act_rng"])
            progress_state.update(state["progress"])
            set_rng_state(state["rng"])
        elif warm_target is not None:  # the first checkpoint of a run that chose its source: the warmed-up target
            from coworld.agents.choice import restore_warm_target

            restore_warm_target(agent, warm_target, device)

        def save() -> None:
            save_checkpoint(
                ckpt_path,
                {
                    "kind": CHECKPOINT_KIND,
                    "task": job.target,
                    "source_task": job.source,
                    "config": to_dict(config),
                    "agent": agent.target.state_dict(),
                    "source": agent.source.state_dict(),
                    "source_updates": source_trainer.updates,
                    "source_act_rng": source_trainer.act_rng.get_state(),
                    "progress": dict(progress_state),
                    "rng": rng_state(),
                },
            )

        try:
            if progress_state["phase"] == "pretrain":
                source_trainer.run(max_steps=cfg.pretrain_steps, progress=progress, cut_episodes=False)
                progress_state["phase"] = "target"
                save()
            per_iteration = cfg.target_updates + cfg.source_updates
            done = progress_state["iteration"] * per_iteration
            done += cfg.target_updates if progress_state["phase"] == "source" else 0
            bar = progress_bar(
                total=cfg.iterations * per_iteration, initial=done, desc="coworld", unit="updates", enabled=progress
            )
            log_every = max(1, min(config.train.log_every, cfg.target_updates))
            while progress_state["iteration"] < cfg.iterations:
                iteration = int(progress_state["iteration"])
                _show(bar, progress_state, cfg.iterations)
                seed = config.seed + 1000 * (iteration + 1)
                stop_prefetch(agent.target_batches)
                batches = dataset.sampler(config.train.batch_size, config.train.seq_len, seed=seed)
                if progress_state["phase"] == "source":
                    # resumed inside the source phase (it restarts from its beginning): its relabelling batches
                    # follow the target phase's K1 in the stream, as in an uninterrupted run
                    batches.skip(cfg.target_updates)
                # laid out for the world models, with the source model's pass for the target phase's own batches;
                # made ahead on a background thread where train.prefetch is on (the same batches either way)
                aligned = cfg.target_updates if progress_state["phase"] == "target" else 0
                made = TargetBatches(agent, aligned=aligned, seed=seed)
                agent.target_batches = Prefetcher(batches, made) if config.train.prefetch else map(made, batches)
                if progress_state["phase"] == "target":
                    rate = Rate(agent.target.updates)
                    for i in range(cfg.target_updates):
                        interrupt.check()
                        metrics = agent.train_target(next(agent.target_batches))
                        bar.update(1)
                        if (i + 1) % log_every == 0 or i + 1 == cfg.target_updates:
                            metrics["target/perf/updates_per_s"] = rate(agent.target.updates)
                            logger.log(metrics, agent.target.updates, unit="target_update")
                    progress_state["phase"] = "source"
                    save()
                if progress_state["phase"] == "source":
                    goal = source_trainer.updates + cfg.source_updates
                    counted = [source_trainer.updates]

                    def pause(trainer: OnlineTrainer, goal: int = goal, counted: list[int] = counted) -> bool:
                        bar.update(trainer.updates - counted[0])
                        counted[0] = trainer.updates
                        return trainer.updates >= goal

                    _show(bar, progress_state, cfg.iterations)
                    source_trainer.run(max_steps=UNBOUNDED, progress=False, should_pause=pause)
                    if (iteration + 1) % cfg.eval_every == 0 or iteration + 1 == cfg.iterations:
                        result, _ = evaluate(
                            agent,
                            job.target,
                            episodes=config.train.eval_episodes,
                            workers=min(config.train.envs, config.train.eval_episodes),
                            seed=config.seed + 10_000,
                            discount=config.actor_critic.discount,
                        )
                        progress_state["last_eval"] = result.mean
                        logger.log(result.metrics(), agent.target.updates, unit="target_update")
                        log_open_loop(
                            logger,
                            agent,
                            dataset,
                            agent.target.updates,
                            tag=f"openl/{job.target}",
                            unit="target_update",
                        )
                    progress_state.update(iteration=iteration + 1, phase="target")
                    save()
                    _show(bar, {**progress_state, "iteration": iteration}, cfg.iterations)
            bar.close()
        finally:
            source_trainer.close()
            stop_prefetch(agent.target_batches)
            dataset.close()
    return {
        "logdir": str(logdir),
        "iterations": progress_state["iteration"],
        "target_updates": agent.target.updates,
        "source_steps": source_trainer.steps,
        "last_eval_return": progress_state["last_eval"],
    }
