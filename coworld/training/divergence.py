"""A diverged run stops with one line and never leaves a damaged checkpoint, in any phase.

Every phase of every run holds a :class:`Phase`: online training (collection, a source agent's pretraining, CoWorld's
source phases, the fine-tuned DreamerV2's source phase), CoWorld's target phases and the target model's warm-up
before a source choice, and offline training (offline DreamerV2 and the baselines). Each update's metrics pass
:meth:`Phase.check`, each action an online phase is about to take :meth:`Phase.check_actions`, and each checkpoint it
writes goes through :meth:`Phase.saving`, where the checkpoint writer's own refusal of a non-finite tensor
(:func:`coworld.training.checkpoint.save_checkpoint`) becomes the phase's line. The first loss, action or weight
that is no longer a number raises :class:`~coworld.errors.TrainingDiverged` (exit code 2 on the command line) naming
what became non-finite, at which update of which phase, the config keys to lower, and the checkpoint a rerun starts
from (or that none was written yet). The checks read values the run computes anyway and change none of them.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from functools import reduce
from pathlib import Path
from typing import Any

import numpy as np

from coworld.algorithms import DREAMER_KNOBS, REGISTRY
from coworld.errors import NonFiniteCheckpoint, TrainingDiverged

LOSSES = {
    "wm": "world-model loss",
    "actor": "actor loss",
    "critic": "critic loss",
    "policy_value": "target-policy critic's loss",
    "coworld": "relabelled-reward loss",
    "curl": "contrastive loss",
    "alpha": "temperature loss",
}
"""What a loss is called by its metric group (``wm/loss``, ``source/actor/loss``)."""

KNOBS: dict[str, Mapping[str, tuple[str, ...]]] = {
    "dreamerv2-online": DREAMER_KNOBS,
    **{record.checkpoint: record.knobs for record in REGISTRY},
    "coworld-source": {**DREAMER_KNOBS, "policy_value": ("actor_critic.critic_lr",), "coworld": ("world_model.lr",)},
}
"""The config keys that scale what each network of a kind of run learns, by metric group: what a line about a
diverged loss says to lower. Keyed by checkpoint kind: each algorithm's (its record's ``knobs``), an agent learning
online (the collector, a source agent's pretraining) and CoWorld's source agent."""

_ENTRY_GROUPS = {
    "world_model": "wm",
    "wm_opt": "wm",
    "policy_value": "policy_value",
    "critic": "critic",
    "slow_critic": "critic",
    "critic_opt": "critic",
    "actor": "actor",
    "actor_opt": "actor",
}
"""The metric group of a checkpoint entry, by the first of its names found here (``agent/actor_critic/critic.mlp...``
is the critic's)."""


@dataclass(frozen=True)
class Phase:
    """Where a run is, as its line names it, and what its checks compare against.

    Args:
        name: the phase (``collection``, ``source pretraining``, ``target phase of iteration 2``, ...).
        agent: who learns in it (``the agent``, ``the source agent``, ``the target agent``).
        unit: what its update count counts (``update``, ``source update``, ``target update``).
        kind: the kind of run (a key of :data:`KNOBS`): which config keys to lower.
        config: the run's config (to say what those keys are now).
        resume_from: the checkpoint a rerun of this phase starts from.
    """

    name: str
    agent: str
    unit: str
    kind: str
    config: Any
    resume_from: Path

    def check(self, metrics: Mapping[str, float], step: int) -> None:
        """Stop at an update whose loss (a metric ending in ``loss``) is NaN or infinite; ``step``: the update's
        number."""
        key = next((k for k, v in metrics.items() if k.endswith("loss") and not math.isfinite(v)), None)
        if key is None:
            return
        group = key.removeprefix("source/").removeprefix("target/").split("/")[0]
        what = f"{self.agent}'s {LOSSES.get(group, 'loss')} ({key}) became {metrics[key]}"
        raise TrainingDiverged(f"{what} at {self.unit} {step} ({self.name}); {self._remedy(group)}; {self._kept()}")

    def check_actions(self, actions: np.ndarray, step: int, unit: str) -> None:
        """Stop before acting with NaN or infinite ``actions`` (those of environment step ``step``, counted in
        ``unit``)."""
        if np.isfinite(actions).all():
            return
        value = "nan" if np.isnan(actions).any() else "infinite"
        remedy = self._remedy("wm", "actor")
        what = f"{self.agent}'s actions became {value} at {unit} {step} ({self.name})"
        raise TrainingDiverged(f"{what}; {remedy}; {self._kept()}")

    @contextmanager
    def saving(self, step: int) -> Iterator[None]:
        """Where the phase writes a checkpoint after update ``step``: the writer's refusal of a non-finite tensor
        (an update that reported a finite loss and left NaN weights) becomes the phase's line."""
        try:
            yield
        except NonFiniteCheckpoint as err:
            group = next((_ENTRY_GROUPS[n] for n in err.entry.replace(".", "/").split("/") if n in _ENTRY_GROUPS), "")
            what = f"{self.agent}'s weights became non-finite by {self.unit} {step} ({self.name})"
            raise TrainingDiverged(
                f"{what}: {err.entry} holds {err.value} values; {self._remedy(group)}; {self._kept()}"
            ) from None

    def _remedy(self, *groups: str) -> str:
        """What to lower for the networks of ``groups`` (an unknown group: every key of the kind), with their values
        now."""
        knobs = KNOBS.get(self.kind, DREAMER_KNOBS)
        keys = [key for group in groups for key in knobs.get(group, ())]
        if not keys:
            keys = [key for group in knobs.values() for key in group]
        keys = list(dict.fromkeys(keys))
        named = [f"{key} (now {reduce(getattr, key.split('.'), self.config):g})" for key in keys]
        listed = named[0] if len(named) == 1 else f"{', '.join(named[:-1])} or {named[-1]}"
        return f"lower {listed} with --set and start the run over with --force"

    def _kept(self) -> str:
        if self.resume_from.exists():
            return f"the last good checkpoint is kept at {self.resume_from}"
        return "no checkpoint was written before it"
