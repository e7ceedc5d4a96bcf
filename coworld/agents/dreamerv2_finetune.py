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
from coworld.data import DatasetWriter
from coworld.envs import task_spec
from coworld.training.logger import Logger
from coworld.training.online import OnlineTrainer

__all__ = ["pretrain_on_source"]


def pretrain_on_source(agent: DreamerV2, job: Any, *, logger: Logger, progress: bool = True) -> int:
    """Train ``agent`` online in ``job.source`` until ``coworld.pretrain_steps`` steps (resuming a cut phase).

    Returns the source environment steps taken.
    """
    config = job.config
    logdir = Path(job.logdir)
    writer = DatasetWriter(
        logdir / "source_replay.h5",
        task=job.source,
        env_config={"task": job.source},
        quality="medium-replay",
        collector={"algorithm": "dreamerv2-finetune-source", "seed": config.seed},
        action_size=task_spec(job.source).action_size,
        resume=True,
    )
    with writer:
        trainer = OnlineTrainer(
            agent=agent,
            task=job.source,
            config=config,
            logdir=logdir / "source",
            writer=writer,
            logger=logger,
            metric_prefix="source/",
            step_unit_prefix="source_",
        )
        try:
            trainer.restore()
            if trainer.steps < config.coworld.pretrain_steps or not trainer.checkpoint_path.exists():
                trainer.run(max_steps=config.coworld.pretrain_steps, progress=progress)
        finally:
            trainer.close()
    return trainer.steps
