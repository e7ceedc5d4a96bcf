"""Algorithm 1 of the paper: CoWorld's schedule, the source agent online and the target agent offline in turns.

The paper's Algorithm 1, line by line, and where each line runs (the update steps themselves are
:class:`coworld.agents.coworld.CoWorld`'s)::

    3       Pretrain the source domain agent                     Algorithm1.pretrain_source
    4       while not converged do                               Algorithm1.run: coworld.iterations iterations
    5       for k_t = 1 .. K1 do                                 Algorithm1.target_phase: K1 = coworld.target_updates
    6           draw a target batch from B_T                     next(target_batches)
    7-11        Eq. 3 world model, imagine, Eq. 6 critic, actor  CoWorld.train_target
    15      for k_s = 1 .. K2 do                                 Algorithm1.source_phase: K2 = coworld.source_updates
    22          append B_S by acting in the source environment   OnlineTrainer.act (see below)
    16          draw a source batch from B_S                     OnlineTrainer.sample
                (and a target batch from B_T, for Eq. 4)         next(target_batches)
    17-21       Eq. 4, Eq. 5, dynamics, actor-critic             CoWorld.train_source

Line 22 is the interaction between two source updates: the source environment steps that make the next update due
at the train ratio (one update every ``train.train_every`` steps, as in the pretraining), so each source batch is
drawn from B_S as those steps left it. An iteration's target batches come from one stream seeded by (seed,
iteration): the target phase takes the first K1, the source phase's the next K2. Source episodes run on across
phase boundaries. A checkpoint is written after every phase, its :class:`Progress` naming the next, with the source
agent's online state (its running episodes among it), so a stopped run resumes at that phase's start with its
source replay cut back to the checkpoint and goes on exactly as an uninterrupted one (the same batches, source steps
and weights); stopped while pretraining, it resumes that way from the last source checkpoint
(:meth:`~coworld.training.online.OnlineTrainer.restore`). Runs that differ only in what the target phases read can
share one pretraining (:mod:`coworld.training.pretrained`).
"""

from __future__ import annotations

import dataclasses
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from coworld import interrupt
from coworld.agents.coworld import CoWorld, TargetBatches
from coworld.config import to_dict
from coworld.data import open_dataset
from coworld.data.prefetch import Prefetcher, stop_prefetch
from coworld.envs import task_spec
from coworld.errors import CheckpointError
from coworld.progress import progress_bar
from coworld.training import pretrained
from coworld.training.checkpoint import (
    CHECKPOINT_NAME,
    load_checkpoint,
    refuse_earlier_format,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from coworld.training.divergence import Phase
from coworld.training.evaluate import evaluate
from coworld.training.job import TrainJob
from coworld.training.logger import Logger, Rate
from coworld.training.multi_source import restore_warm_target, settle_source
from coworld.training.online import make_source_trainer, source_phase, source_replay_writer
from coworld.training.openloop import log_open_loop

CHECKPOINT_KIND = "coworld"
CHECKPOINT_KEYS = ("agent", "source", "source_updates", "progress", "rng")
"""What a CoWorld checkpoint holds beyond its kind (:meth:`Algorithm1.checkpoint`), with :data:`FORMAT_KEYS`."""
FORMAT_KEYS = ("source_online", "relabelled")
"""The entries this release's CoWorld checkpoints hold that earlier ones lack: one without them is refused."""


@dataclass
class Progress:
    """Where Algorithm 1 stands, as its checkpoint records it: the iteration, the phase to run next ('pretrain',
    'target' or 'source') and the last evaluation's mean return."""

    iteration: int = 0
    phase: str = "pretrain"
    last_eval: float | None = None


def train_coworld(job: TrainJob, *, device: torch.device, resumed: bool, progress: bool = True) -> dict[str, Any]:
    """Run Algorithm 1 for a checked job, resuming what its run folder holds (so ``resumed`` changes nothing); with
    several sources (``--source A,B``) the closest is chosen first
    (:func:`coworld.training.multi_source.settle_source`)."""
    dataset = open_dataset(job.dataset)
    try:
        job, warm_target = settle_source(job, dataset=dataset, device=device, progress=progress)
        if job.pretrained_from:
            start_from_shared_pretraining(job)
        writer = source_replay_writer(job.logdir, str(job.source), algorithm="coworld", seed=job.config.seed)
        with Logger(job.logdir) as logger, writer:
            algorithm = Algorithm1(job, dataset, device=device, logger=logger, writer=writer, progress=progress)
            try:
                algorithm.restore(warm_target)
                return algorithm.run()
            finally:
                algorithm.close()
    finally:
        dataset.close()


def start_from_shared_pretraining(job: TrainJob) -> None:
    """A new run's folder seeded with the first ``--pretrained-from`` run's kept pretraining, where one has it."""
    donor = pretrained.start_from(Path(job.logdir), job.pretrained_from, job.config)
    if donor is not None:
        tqdm.write(f"source pretraining copied from {donor / pretrained.SNAPSHOT}", file=sys.stderr)
    elif not (Path(job.logdir) / CHECKPOINT_NAME).exists():
        tqdm.write("no --pretrained-from run has kept its pretraining yet: pretraining here", file=sys.stderr)


class Algorithm1:
    """One CoWorld run: the two agents, the source agent's online trainer, the target dataset and the schedule."""

    def __init__(
        self, job: TrainJob, dataset: Any, *, device: torch.device, logger: Logger, writer: Any, progress: bool
    ) -> None:
        self.job, self.dataset, self.logger, self.show_progress = job, dataset, logger, progress
        self.config = job.config
        self.cfg = job.config.coworld
        self.agent = CoWorld(
            config=self.config,
            action_size=task_spec(job.target).action_size,
            source_action_size=task_spec(str(job.source)).action_size,
            device=device,
        )
        self.pretraining = source_phase(
            "source pretraining", agent="the source agent", kind="coworld-source", config=self.config, logdir=job.logdir
        )
        self.source = make_source_trainer(
            self.agent.source,
            str(job.source),
            config=self.config,
            logdir=job.logdir,
            writer=writer,
            logger=logger,
            phase=self.pretraining,
            train=self.agent.train_source,
            checkpoint_extra=self.policy_value_state,
        )
        """The source agent's online trainer: its replay B_S, its environments, its updates' schedule."""
        self.target_batches: Iterator[dict[str, Any]] | None = None
        """The running iteration's target batches from B_T (:meth:`begin_iteration`)."""
        self.state = Progress()
        self.checkpoint_path = Path(job.logdir) / CHECKPOINT_NAME
        self.bar: Any = progress_bar(total=0, desc="coworld", unit="updates", enabled=False)

    # -- Algorithm 1 --------------------------------------------------------------------------------------------------
    def run(self) -> dict[str, Any]:
        cfg = self.cfg
        if self.state.phase == "pretrain":  # line 3
            self.pretrain_source()
        per_iteration = cfg.target_updates + cfg.source_updates
        done = self.state.iteration * per_iteration + (cfg.target_updates if self.state.phase == "source" else 0)
        total = cfg.iterations * per_iteration
        self.bar = progress_bar(total=total, initial=done, desc="coworld", unit="updates", enabled=self.show_progress)
        while self.state.iteration < cfg.iterations:  # line 4
            self.begin_iteration()
            if self.state.phase == "target":  # lines 5-12
                self.target_phase()
                self.state.phase = "source"
                with self.target_phase_check().saving(self.agent.target.updates):
                    self.save()
            self.source_phase()  # lines 14-22
            if (self.state.iteration + 1) % cfg.eval_every == 0 or self.state.iteration + 1 == cfg.iterations:
                self.evaluate()
            source = self.source.phase
            self.state = Progress(iteration=self.state.iteration + 1, phase="target", last_eval=self.state.last_eval)
            with source.saving(self.source.updates):
                self.save()
        self.bar.close()
        return {
            "logdir": str(self.job.logdir),
            "iterations": self.state.iteration,
            "target_updates": self.agent.target.updates,
            "source_steps": self.source.steps,
            "last_eval_return": self.state.last_eval,
        }

    def pretrain_source(self) -> None:
        """The source agent alone, online, for ``coworld.pretrain_steps`` source environment steps (a copy of the run
        as it then stands kept with ``--keep-pretrained``)."""
        self.source.run(max_steps=self.cfg.pretrain_steps, progress=self.show_progress, cut_episodes=False)
        self.state.phase = "target"
        state = self.checkpoint()
        with self.pretraining.saving(self.source.updates):
            if self.job.keep_pretrained:
                pretrained.keep(Path(self.job.logdir), state)
            save_checkpoint(self.checkpoint_path, state)

    def begin_iteration(self) -> None:
        """The iteration's stream of target batches, laid out for the world models (the target phase's own with the
        source model's pass), made ahead on a background thread where ``train.prefetch`` is on."""
        cfg, train = self.cfg, self.config.train
        seed = self.config.seed + 1000 * (self.state.iteration + 1)
        stop_prefetch(self.target_batches)
        batches = self.dataset.sampler(train.batch_size, train.seq_len, seed=seed)
        if self.state.phase == "source":  # resumed inside the source phase: its batches follow the target phase's
            batches.skip(cfg.target_updates)
        made = TargetBatches(self.agent, aligned=cfg.target_updates if self.state.phase == "target" else 0, seed=seed)
        self.target_batches = Prefetcher(batches, made) if train.prefetch else map(made, batches)
        self._show()

    def target_phase(self) -> None:
        """Lines 5-12: K1 target updates, each on a batch from the target dataset (Eq. 3, imagination, Eq. 6)."""
        k1 = self.cfg.target_updates
        log_every = max(1, min(self.config.train.log_every, k1))
        rate = Rate(self.agent.target.updates)
        phase = self.target_phase_check()
        for k_t in range(k1):  # line 5
            interrupt.check()
            target_batch = next(self.target_batches)  # line 6
            metrics = self.agent.train_target(target_batch)  # lines 7-11
            phase.check(metrics, self.agent.target.updates)
            self.bar.update(1)
            if (k_t + 1) % log_every == 0 or k_t + 1 == k1:
                metrics["target/perf/updates_per_s"] = rate(self.agent.target.updates)
                self.logger.log(metrics, self.agent.target.updates, unit="target_update")

    def source_phase(self) -> None:
        """Lines 14-22: K2 source updates, each on a source batch and (Eq. 4) a target batch, with the source
        environment steps at the train ratio before each; the running source episodes carry on into the next phase.
        """
        relabel = self.cfg.reward_relabel
        # a rerun of a stopped source phase starts from the combined checkpoint written at the phase's start
        name = f"source phase of iteration {self.state.iteration + 1}"
        self.source.phase = dataclasses.replace(self.pretraining, name=name, resume_from=self.checkpoint_path)
        self._show()
        with self.source.acting():
            for _ in range(self.cfg.source_updates):  # line 15
                self.source.act()  # line 22, the steps that make this update due
                source_batch = self.source.sample()  # line 16
                target_batch = next(self.target_batches) if relabel else None  # Eq. 4's target batch
                self.source.update(self.agent.train_source, source_batch, target_batch)  # lines 17-21
                self.bar.update(1)

    def evaluate(self) -> None:
        """The target agent in the target environment (returns and the value check), and the open-loop strips."""
        train, target = self.config.train, self.job.target
        episodes, seed, discount = train.eval_episodes, self.config.seed + 10_000, self.config.actor_critic.discount
        workers = min(train.envs, episodes)
        result, _ = evaluate(self.agent, target, episodes=episodes, workers=workers, seed=seed, discount=discount)
        self.state.last_eval = result.mean
        self._show()
        step = self.agent.target.updates
        self.logger.log(result.metrics(), step, unit="target_update")
        log_open_loop(self.logger, self.agent, self.dataset, step, tag=f"openl/{target}", unit="target_update")

    def target_phase_check(self) -> Phase:
        """The running iteration's target phase, as :mod:`coworld.training.divergence` checks it: a rerun starts from
        the combined checkpoint written at its start."""
        return Phase(
            name=f"target phase of iteration {self.state.iteration + 1}",
            agent="the target agent",
            unit="target update",
            kind="coworld",
            config=self.config,
            resume_from=self.checkpoint_path,
        )

    # -- checkpoints ----------------------------------------------------------------------------------------------
    def save(self) -> None:
        save_checkpoint(self.checkpoint_path, self.checkpoint())

    def checkpoint(self) -> dict[str, Any]:
        """The combined checkpoint: both agents, the source trainer's online state, where the schedule stands."""
        return {
            "kind": CHECKPOINT_KIND,
            "task": self.job.target,
            "source_task": self.job.source,
            "config": to_dict(self.config),
            "agent": self.agent.target.state_dict(),
            "source": self.agent.source.state_dict(),
            "source_updates": self.source.updates,
            "source_online": self.source.online_state(),
            "relabelled": self.agent.relabelled,
            "progress": dataclasses.asdict(self.state),
            "rng": rng_state(),
            **self.policy_value_state(),
        }

    def policy_value_state(self) -> dict[str, Any]:
        """The target-policy critic's entry of a checkpoint, where the run has one: it learns from the first source
        update, so the source agent's pretraining checkpoints hold it too."""
        return {} if self.agent.policy_value is None else {"policy_value": self.agent.policy_value.state_dict()}

    def restore(self, warm_target: Path | None) -> None:
        """Continue from the run folder: the combined checkpoint once past pretraining, else the source's
        pretraining checkpoint (with the target-policy critic it holds, and a chosen source's warmed-up target agent
        where the choice made one)."""
        if not self.checkpoint_path.exists():
            source_state = self.source.restore(rollback=True)
            if self.agent.policy_value is not None and source_state is not None and "policy_value" in source_state:
                self.agent.policy_value.load_state_dict(source_state["policy_value"])
            if warm_target is not None:
                restore_warm_target(self.agent, warm_target, self.agent.device)
            return
        keys = CHECKPOINT_KEYS + (() if self.agent.policy_value is None else ("policy_value",))
        state = load_checkpoint(self.checkpoint_path, map_location=self.agent.device, keys=keys)
        if state.get("kind") != CHECKPOINT_KIND:
            raise CheckpointError(f"{self.checkpoint_path} is a {state.get('kind')!r} checkpoint, not a coworld one")
        refuse_earlier_format(self.checkpoint_path, state, FORMAT_KEYS)
        self.agent.target.load_state_dict(state["agent"])
        self.agent.source.load_state_dict(state["source"])
        if self.agent.policy_value is not None:
            self.agent.policy_value.load_state_dict(state["policy_value"])
        # the source's online state holds the metrics file's mark: resuming it cuts the file back to this checkpoint
        self.source.resume(state["source_online"], rollback=True)
        self.agent.relabelled = int(state["relabelled"])
        self.state = Progress(**state["progress"])
        set_rng_state(state["rng"])

    def close(self) -> None:
        self.source.close()
        stop_prefetch(self.target_batches)

    def _show(self) -> None:
        """The progress bar's postfix: iteration, phase and the last evaluation return."""
        last = "-" if self.state.last_eval is None else f"{self.state.last_eval:.1f}"
        iteration = f"{self.state.iteration + 1}/{self.cfg.iterations}"
        self.bar.set_postfix(iteration=iteration, phase=self.state.phase, eval_return=last)
