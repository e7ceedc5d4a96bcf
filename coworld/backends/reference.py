"""The reference path: the world model's own modules and loss, as a researcher reads them."""

from __future__ import annotations

from typing import Any, Protocol

import torch
from torch import Tensor

from coworld.models.rssm import State
from coworld.models.world_model import WorldModel

__all__ = ["ModelPath", "ReferencePath"]


class ModelPath(Protocol):
    """What the agents call to train a world model (``name`` says which path it is)."""

    name: str
    world_model: WorldModel

    def prepare(self, batch: dict[str, Tensor]) -> dict[str, Tensor]: ...

    def embed(self, batch: dict[str, Tensor]) -> Tensor: ...

    def observe(
        self,
        batch: dict[str, Tensor],
        state: State | None = None,
        generator: torch.Generator | None = None,
        priors: bool = True,
    ) -> tuple[State, State | None, Tensor]: ...

    def loss(
        self, batch: dict[str, Tensor], generator: torch.Generator | None = None
    ) -> tuple[dict[str, Tensor], dict[str, Any]]: ...


class ReferencePath:
    """The reference modules as they are: :meth:`WorldModel.loss`, :meth:`WorldModel.observe`, the encoder."""

    name = "reference"

    def __init__(self, world_model: WorldModel) -> None:
        self.world_model = world_model

    def prepare(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        """The batch as it is (the reference reads ``image``)."""
        return batch

    def embed(self, batch: dict[str, Tensor]) -> Tensor:
        return self.world_model.encode(batch["image"])

    def observe(
        self,
        batch: dict[str, Tensor],
        state: State | None = None,
        generator: torch.Generator | None = None,
        priors: bool = True,
    ) -> tuple[State, State | None, Tensor]:
        return self.world_model.observe(batch, state, generator, priors)

    def loss(
        self, batch: dict[str, Tensor], generator: torch.Generator | None = None
    ) -> tuple[dict[str, Tensor], dict[str, Any]]:
        return self.world_model.loss(batch, generator)
