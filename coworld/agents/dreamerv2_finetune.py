"""DreamerV2 fine-tuned from the source: the transfer baseline CoWorld must beat.

The agent is :class:`coworld.agents.dreamerv2.DreamerV2`. It first learns online in the source task for
``coworld.pretrain_steps`` environment steps (the same pretraining CoWorld's source agent gets, so both start from
equally trained source agents), then continues offline on the target dataset with offline DreamerV2's schedule
(``coworld.iterations`` x ``coworld.target_updates`` updates), keeping its weights and optimiser state: does
CoWorld's collaboration add anything over reusing the source agent's weights?

Both phases run in one run folder: the source phase is :class:`coworld.training.online.OnlineTrainer` (checkpoint
in ``<run>/source/``, experience in ``<run>/source_replay.h5``, metrics prefixed ``source/``), the target phase
the shared offline loop (:mod:`coworld.training.baselines`). A run killed in the source phase resumes it; once the
target phase has checkpointed, the run resumes from that checkpoint.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from coworld.agents.dreamerv2 import DreamerV2
from coworld.training.logger import Logger
from coworld.training.online import make_source_trainer, source_replay_writer

__all__ = ["pretrain_on_source"]


def pretrain_on_source(agent: DreamerV2, job: Any, *, logger: Logger, progress: bool = True) -> int:
    """Train ``agent`` online in ``job.source`` until ``coworld.pretrain_steps`` steps (resuming a cut phase).

    Returns the source environment steps taken.
    """
    config = job.config
    logdir = Path(job.logdir)
    writer = source_replay_writer(logdir, job.source, algorithm=job.algo, seed=config.seed)
    with writer:
        trainer = make_source_trainer(agent, job.source, config=config, logdir=logdir, writer=writer, logger=logger)
        try:
            trainer.restore()
            if trainer.steps < config.coworld.pretrain_steps or not trainer.checkpoint_path.exists():
                trainer.run(max_steps=config.coworld.pretrain_steps, progress=progress)
        finally:
            trainer.close()
    return trainer.steps
