"""Build an agent by algorithm name (what ``coworld train`` and ``coworld eval`` share)."""

from __future__ import annotations

import importlib
from typing import Any

import torch

from coworld.config import Config

AGENT_CLASSES = {
    "coworld": "dreamerv2:DreamerV2",
    "dreamerv2": "dreamerv2:DreamerV2",
    "dreamerv2-finetune": "dreamerv2:DreamerV2",
    "curl": "curl:Curl",
    "curl-cql": "curl:Curl",
    "dreamerv2-penalty": "dreamerv2_penalty:PenaltyDreamerV2",
    "lompo": "lompo:Lompo",
    "dreamerv2-finetune-ewc": "dreamerv2_ewc:EwcDreamerV2",
    "drq-bc": "drq_bc:DrqBc",
}
"""Algorithm -> ``module:class`` (in :mod:`coworld.agents`) of the agent whose ``policy`` is evaluated (for CoWorld:
the target agent, a DreamerV2)."""


def agent_class(algo: str) -> type:
    """The class of the agent whose ``policy`` is evaluated for ``algo``, imported only when asked for."""
    if algo not in AGENT_CLASSES:
        raise ValueError(f"unknown algorithm {algo!r}")
    module, name = AGENT_CLASSES[algo].split(":")
    return getattr(importlib.import_module(f"coworld.agents.{module}"), name)


def make_agent(algo: str, *, config: Config, action_size: int, device: torch.device | str) -> Any:
    """The agent whose ``policy`` is evaluated for ``algo``, built for ``config``."""
    extra = {"cql": algo == "curl-cql"} if algo in ("curl", "curl-cql") else {}
    return agent_class(algo)(config=config, action_size=action_size, device=device, **extra)
