"""Build an agent by algorithm name (what ``coworld train`` and ``coworld eval`` share), from its record
(:mod:`coworld.algorithms`)."""

from __future__ import annotations

import importlib
from typing import Any

import torch

from coworld.algorithms import algorithm
from coworld.config import Config


def import_named(name: str) -> Any:
    """What ``module:attribute`` names in :mod:`coworld.agents`, imported only when asked for."""
    module, attribute = name.split(":")
    return getattr(importlib.import_module(f"coworld.agents.{module}"), attribute)


def agent_class(algo: str) -> type:
    """The class of the agent whose ``policy`` is evaluated for ``algo`` (ValueError for an unknown name)."""
    return import_named(algorithm(algo).agent)


def make_agent(algo: str, *, config: Config, action_size: int, device: torch.device | str) -> Any:
    """The agent whose ``policy`` is evaluated for ``algo``, built for ``config``."""
    options = algorithm(algo).options
    return agent_class(algo)(config=config, action_size=action_size, device=device, **options)
