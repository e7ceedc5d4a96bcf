"""Offline training from a fixed dataset: offline DreamerV2 and the model-free baselines share this loop.

The agent sees dataset batches only; the target environment is used for evaluation alone. The batch stream
is cut into chunks at checkpoint boundaries and each chunk's sampler is seeded by (seed, updates done), so a
run killed and resumed from its last checkpoint draws the same batches, with the same random state, as one
that was never interrupted. With ``prefetch`` the next batch is drawn (and passed through ``prepare``) on a
background thread during each update (:func:`~coworld.data.prefetch.prefetched`): the same batches in the same
order.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from coworld import interrupt
from coworld.data.prefetch import prefetched, stop_prefetch
from coworld.progress import progress_bar
from coworld.training.checkpoint import CHECKPOINT_NAME, read_run_checkpoint, restore_agent, run_state, save_checkpoint
from coworld.training.divergence import Phase
from coworld.training.evaluate import evaluate
from coworld.training.logger import METRICS_MARK, Logger, Rate
from coworld.training.openloop import log_open_loop

CHECKPOINT_KEYS = ("agent", "updates", "last_eval", "rng")
"""What an offline run's checkpoint holds beyond its kind (:meth:`OfflineTrainer.save`)."""

SamplerFactory = Callable[[int], Iterator[dict[str, np.ndarray]]]


@dataclass(frozen=True)
class OfflineSchedule:
    """How long an offline run is and how often it logs, evaluates and checkpoints (in updates)."""

    updates: int
    log_every: int
    eval_every: int
    eval_episodes: int
    checkpoint_every: int


@dataclass
class OfflineResult:
    updates: int
    last_eval_return: float | None


class OfflineTrainer:
    """Trains ``agent`` on batches from ``make_sampler(seed)`` and evaluates it in ``task``.

    Args:
        agent: has ``train(batch) -> metrics``, ``policy``, ``state_dict``, ``load_state_dict``.
        kind: the checkpoint's kind (e.g. ``dreamerv2-offline``, ``curl``), checked on resume and by eval.
        make_sampler: seed -> iterator of batches.
        discount: discount of the value check in evaluations (None for agents without a critic estimate).
        prefetch: make each next batch on a background thread while the agent trains on the current one.
        prepare: what the background thread also does to each batch (the agent's ``prepare``: work that reads no
            weight); ``agent.train`` must take its output.
        phase: what its divergence line calls the run (:mod:`coworld.training.divergence`), e.g. ``target phase``
            for a fine-tuned DreamerV2 after its source phase.
    """

    def __init__(
        self,
        *,
        agent: Any,
        kind: str,
        task: str,
        config: Any,
        schedule: OfflineSchedule,
        logdir: str | Path,
        logger: Logger,
        make_sampler: SamplerFactory,
        discount: float | None = None,
        workers: int = 1,
        prefetch: bool = False,
        prepare: Callable[[dict[str, np.ndarray]], Any] | None = None,
        phase: str = "offline training",
    ) -> None:
        self.agent, self.kind, self.task, self.config = agent, kind, task, config
        self.schedule = schedule
        self.logdir = Path(logdir)
        self.logger = logger
        self.make_sampler = make_sampler
        self.discount = discount
        self.workers = workers
        self.prefetch = prefetch
        self.prepare = prepare
        self.updates = 0
        self.last_eval: float | None = None
        self.phase = Phase(
            name=phase, agent="the agent", unit="update", kind=kind, config=config, resume_from=self.checkpoint_path
        )

    @property
    def checkpoint_path(self) -> Path:
        return self.logdir / CHECKPOINT_NAME

    def restore(self) -> bool:
        """Load the last checkpoint of this run folder, if any; True when resumed."""
        if not self.checkpoint_path.exists():
            return False
        state = read_run_checkpoint(self.checkpoint_path, self.agent, self.kind, CHECKPOINT_KEYS)
        restore_agent(self.agent, state, self.checkpoint_path, f"a {self.kind} agent of this config")
        self.updates = int(state["updates"])
        self.last_eval = state["last_eval"]
        self.logger.rewind(state.get(METRICS_MARK))  # the updates after the checkpoint are made (and logged) again
        return True

    def save(self) -> None:
        state = run_state(self.kind, self.task, self.config, self.agent)
        with self.phase.saving(self.updates):
            counters = {"updates": self.updates, "last_eval": self.last_eval, METRICS_MARK: self.logger.mark()}
            save_checkpoint(self.checkpoint_path, {**state, **counters})

    def run(self, *, progress: bool = True) -> OfflineResult:
        s = self.schedule
        bar = progress_bar(total=s.updates, initial=self.updates, desc=self.kind, unit="updates", enabled=progress)
        sampler = self._batches(self.config.seed + self.updates)
        update_rate = Rate(self.updates)
        metrics: dict[str, float] = {}
        try:
            while self.updates < s.updates:
                interrupt.check()
                metrics = self.agent.train(next(sampler))
                self.updates += 1
                self.phase.check(metrics, self.updates)
                bar.update(1)
                if self.updates % s.log_every == 0 or self.updates == s.updates:
                    metrics["perf/updates_per_s"] = update_rate(self.updates)  # this log window, evaluation included
                    self.logger.log(metrics, self.updates, unit="update")
                if self.updates % s.eval_every == 0 or self.updates == s.updates:
                    self.evaluate()
                    bar.set_postfix(eval_return=f"{self.last_eval:.1f}")
                if self.updates % s.checkpoint_every == 0 or self.updates == s.updates:
                    self.save()
                    stop_prefetch(sampler)
                    sampler = self._batches(self.config.seed + self.updates)
        finally:
            stop_prefetch(sampler)
            bar.close()
        return OfflineResult(self.updates, self.last_eval)

    def _batches(self, seed: int) -> Iterator[Any]:
        """The batch stream from ``seed``: the sampler's, made ahead on a background thread with ``prefetch``."""
        return prefetched(self.make_sampler(seed), self.prepare, self.prefetch)

    def evaluate(self) -> None:
        result, _ = evaluate(
            self.agent,
            self.task,
            episodes=self.schedule.eval_episodes,
            workers=min(self.workers, self.schedule.eval_episodes),
            seed=self.config.seed + 10_000,
            discount=self.discount,
        )
        self.last_eval = result.mean
        metrics = result.metrics()
        self.logger.log(metrics, self.updates, unit="update")
        log_open_loop(self.logger, self.agent, self.make_sampler, self.updates, tag=f"openl/{self.task}", unit="update")
