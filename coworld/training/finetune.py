"""DreamerV2 fine-tuned from the source, with or without EWC: the transfer baselines CoWorld must beat, their schedule.

The agent is :class:`coworld.agents.dreamerv2.DreamerV2` (with EWC :class:`coworld.agents.dreamerv2_ewc.EwcDreamerV2`).

1. :func:`pretrain_on_source`: it learns online in the source task for ``coworld.pretrain_steps`` environment steps
   (the same pretraining CoWorld's source agent gets, so both start from equally trained source agents);
2. with EWC, :func:`consolidate_on_source`: its source weights and their Fisher information on the source experience
   become the anchor of its later losses;
3. it continues offline on the target dataset with offline DreamerV2's schedule (``offline.updates`` updates,
   :mod:`coworld.training.baselines`), keeping its weights and optimiser state:
   does CoWorld's collaboration add anything over reusing the source agent's weights?

Both phases run in one run folder: the source phase's checkpoint in ``<run>/source/``, its experience in
``<run>/source_replay.h5``, its metrics prefixed ``source/``. A run stopped in the source phase resumes it; once the
target phase has checkpointed, the run resumes from that checkpoint.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from coworld.agents.dreamerv2 import DreamerV2
from coworld.agents.dreamerv2_ewc import EwcDreamerV2
from coworld.data import open_dataset
from coworld.training.logger import Logger
from coworld.training.online import pretrain_source, source_phase

__all__ = ["consolidate_on_source", "pretrain_on_source"]


def pretrain_on_source(agent: DreamerV2, job: Any, *, logger: Logger, progress: bool = True) -> int:
    """Train ``agent`` online in ``job.source`` until ``coworld.pretrain_steps`` steps (resuming a cut phase).

    Returns the source environment steps taken.
    """
    phase = source_phase("source phase", agent="the agent", kind=job.algo, config=job.config, logdir=job.logdir)
    return pretrain_source(
        agent,
        job.source,
        config=job.config,
        logdir=job.logdir,
        logger=logger,
        algorithm=job.algo,
        phase=phase,
        progress=progress,
    )


def consolidate_on_source(agent: EwcDreamerV2, job: Any, *, logger: Logger) -> None:
    """After the source phase of ``job``'s run: :meth:`EwcDreamerV2.consolidate` on ``ewc.fisher_batches`` batches
    drawn (seeded by the run's seed) from the source experience in ``<run>/source_replay.h5``."""
    config = job.config
    with open_dataset(Path(job.logdir) / "source_replay.h5") as dataset:
        sampler = iter(dataset.sampler(config.train.batch_size, config.train.seq_len, seed=config.seed))
        batches = (next(sampler) for _ in range(config.ewc.fisher_batches))
        metrics = agent.consolidate(batches)
    logger.log(metrics, 0, unit="update")
