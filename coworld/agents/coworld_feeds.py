"""How the schedule feeds CoWorld's updates (:mod:`coworld.agents.coworld`): the target phase's batches with the
source model's pass made ahead (:class:`TargetBatches`), and the source agent as the online trainer drives it
(:class:`SourceLearner`)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from torch import Tensor

from coworld.agents.coworld import ALIGN_SOURCE, CoWorld

__all__ = ["SourceLearner", "TargetBatches"]


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

    def predicted_reward(self, state: Any) -> np.ndarray:
        return self.coworld.source.predicted_reward(state)

    def train(self, batch: Mapping[str, np.ndarray]) -> dict[str, float]:
        # the online trainer adds its own "source/" prefix (to these and to its eval/ and perf/ metrics)
        return {key.removeprefix("source/"): value for key, value in self.coworld.train_source(batch).items()}

    def state_dict(self) -> dict[str, Any]:
        return self.coworld.source.state_dict()

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.coworld.source.load_state_dict(state)
